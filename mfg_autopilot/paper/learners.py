"""HJB learning control (Algorithm 3) and MFG learning control (Algorithm 4).

Both are written as *banks*: ``n`` independent learners updated at once with numpy
(the in-process simulator runs all vehicles in one bank; a vehicle's controller
process runs a bank of one). Nothing here does I/O. Every vehicle's state is given
relative to its own destination (the paper's origin), shape (n, 4).

HJB residual (eq. 7 with the errata of docs/errata.md), at the own state s:

    H_hat(w) = (A s + B c0 v_o)^T grad psi - |B^T grad psi|^2 / (4 c3)
               + 1/2 tr(G G^T hess psi) + phi_L(s) + c4 phi_G

with psi = w^T sigma_H(s); the model is time-invariant, so the partial d_t psi = 0
(SPEC erratum 5, stationary reading: the drift is counted once, in the Hamiltonian).
The loss is l_H = H_hat^2 / 2, the regulariser R = max(0, s~^T ds~/dt) on the scaled
state with the nominal drift under the saturated action, and Algorithm 3's update is

    w <- w - mu * grad_w l_H / |grad_w l_H| - c_H grad_w R          (normalised GD)

followed by the action a* = sat(-(1/(2 c3)) B^T grad psi) (erratum 1: minus sign).

MFG (Algorithm 4) iterates K times: HJB update against phi_G(s, m_hat) (eq. 11), then
the FPK model's update on the residual of eq. 10. The mean field is described in
``mfg_autopilot.paper.meanfield`` and ``docs/mean_field.md``.
"""

from __future__ import annotations

import numpy as np

from mfg_autopilot.interface import StepInfo
from mfg_autopilot.paper import kernels
from mfg_autopilot.paper.features import MonomialFeatures, make_sigma_H
from mfg_autopilot.paper.meanfield import MeanField
from mfg_autopilot.paper.model import lqr_value_weights, optimal_action, saturate
from mfg_autopilot.paper.params import Preset

__all__ = ["StepInfo", "HJBLearner", "MFGLearner", "hjb_update", "policy_action"]


def policy_action(sigma_H: MonomialFeatures, w_H: np.ndarray, s_rel: np.ndarray, preset: Preset) -> np.ndarray:
    """a* = sat(-(1/(2 c3)) B^T grad psi_hat(s)) for states s_rel (n, 4) and weights w_H (n, M)."""
    grad_psi = sigma_H.grad_psi(s_rel, w_H)
    return saturate(optimal_action(grad_psi, preset.cost.c3), preset.learner.acc_max_m_s2)


def hjb_update(sigma_H: MonomialFeatures, w_H: np.ndarray, s_rel: np.ndarray, phi_g: np.ndarray, preset: Preset):
    """One weight update of Algorithm 3, step 2, for every learner of a bank.

    Returns (w_new (n, M), residual H_hat (n,), R active (n,) bool, (grad psi (n, 4),
    psi_vxvx + psi_vyvy (n,))): the last pair is the value model's gradient and velocity
    Laplacian at s_rel with the NEW weights - what the action a* (eq. 8) and the FPK
    model's drift divergence (eq. 10) need - so that nobody evaluates the features again.

    Computed row by row by ``kernels.hjb_update_rows`` (the formulas of the module docstring;
    a row's result does not depend on the bank size).
    """
    cost, lp = preset.cost, preset.learner
    s_rel = np.asarray(s_rel, dtype=float)
    phi_g = np.broadcast_to(np.asarray(phi_g, dtype=float), (s_rel.shape[0],))
    w_new, H_hat, active, grad_psi, lap_v_psi = kernels.hjb_update_rows(
        sigma_H.exponents, sigma_H.scale, s_rel, w_H, phi_g, cost.c0_per_s, cost.v_o, cost.c1, cost.c2, cost.c3, cost.c4,
        lp.mu, lp.c_H, lp.acc_max_m_s2, cost.V_o @ cost.V_o.T)
    return w_new, H_hat, active, (grad_psi, lap_v_psi)


class HJBLearner:
    """A bank of n HJB learning controllers (Algorithm 3, the baseline HJB_d)."""

    def __init__(self, n: int, preset: Preset) -> None:
        if n < 1:
            raise ValueError(f"n must be >= 1, got {n}")
        self.preset = preset
        kernels.warm_up()                   # load the compiled kernels now, not in the first control step
        self.sigma_H = make_sigma_H(preset.learner.state_scale)
        w0 = lqr_value_weights(self.sigma_H, preset.cost) if preset.learner.w_H_init == "lqr" else np.zeros(self.sigma_H.M)
        self.w_H = np.tile(w0, (n, 1))

    @property
    def n(self) -> int:
        return self.w_H.shape[0]

    def step(self, s_rel: np.ndarray, phi_g: np.ndarray) -> StepInfo:
        """Algorithm 3 at time t: s_rel (n, 4) own states relative to the destination,
        phi_g (n,) the interaction cost phi_G(s_{N_i}) from the states received this step."""
        s_rel = np.asarray(s_rel, dtype=float)
        self.w_H, H_hat, active, (grad_psi, _) = hjb_update(self.sigma_H, self.w_H, s_rel, np.asarray(phi_g, dtype=float),
                                                            self.preset)
        acc = saturate(optimal_action(grad_psi, self.preset.cost.c3), self.preset.learner.acc_max_m_s2)   # policy_action
        return StepInfo(acc, 1 + active.astype(np.int64), active, H_hat, np.zeros(self.n, dtype=np.int64))


class MFGLearner:
    """A bank of n MFG learning controllers (Algorithm 4): an HJB model and an FPK
    model per vehicle, and the locally held mean field built from the t = 0 exchange."""

    def __init__(self, n: int, preset: Preset) -> None:
        self.preset = preset
        self.hjb = HJBLearner(n, preset)
        self.sigma_H = self.hjb.sigma_H
        self.mean_field: MeanField | None = None

    @property
    def n(self) -> int:
        return self.hjb.n

    @property
    def w_H(self) -> np.ndarray:
        return self.hjb.w_H

    def initialise(self, exchanged_states: np.ndarray, destinations_m: np.ndarray, own_index: np.ndarray) -> None:
        """The t = 0 exchange: states of all N vehicles (N, 4) absolute, their destinations
        (N, 2), and for each learner of this bank the index of its own vehicle (n,)."""
        self.mean_field = MeanField(exchanged_states, destinations_m, np.asarray(own_index), self.preset)

    def step(self, s_rel: np.ndarray) -> StepInfo:
        """Algorithm 4 at time t (no communication): K HJB/FPK iterations, the action,
        then the mean field is propagated one control period."""
        if self.mean_field is None:
            raise RuntimeError("MFGLearner.step before initialise(): the t = 0 exchange has not happened")
        mf, lp = self.mean_field, self.preset.learner
        s_rel = np.asarray(s_rel, dtype=float)
        s_abs = s_rel + np.concatenate([mf.own_destination, np.zeros_like(mf.own_destination)], axis=1)
        n = self.n
        mf_evals = mf.begin_step(self.sigma_H, self.w_H)
        grad_evals = np.zeros(n, dtype=np.int64)
        reg_any = np.zeros(n, dtype=bool)
        H_hat = np.zeros(n)
        for _ in range(lp.K):
            phi_g = mf.phi_G(s_abs)                                   # eq. 11 with m_hat^[k-1]
            mf_evals += mf.n_particles
            self.hjb.w_H, H_hat, active, post = hjb_update(self.sigma_H, self.w_H, s_rel, phi_g, self.preset)
            grad_evals += 1 + active
            reg_any |= active
            mf.fpk_update(s_abs, s_rel, post)                         # Algorithm 4 step 3
            grad_evals += 1
        # the action at the final weights (policy_action; grad psi from the last update, same s and w_H)
        acc = saturate(optimal_action(post[0], self.preset.cost.c3), lp.acc_max_m_s2)
        mf.end_step(self.preset.dt_s)
        return StepInfo(acc, grad_evals, reg_any, H_hat, mf_evals)
