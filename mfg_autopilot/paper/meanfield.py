"""The mean field m(t) each MFG vehicle holds locally after the t = 0 exchange.

The paper leaves open how phi_G(s_i, m) (eq. 11) is computed without communication
(SPEC erratum 7). This project's representation (docs/mean_field.md):

1. Particles. The N states exchanged at t = 0 are the initial empirical measure
   m(0) = 1/N sum_j delta_{s_j(0)} (Algorithm 4, k = 0). Each vehicle propagates
   them locally, once per control period, with the nominal closed-loop drift of
   eq. 10, A s + B(a*(s) + c0 v_o), where a* is the vehicle's *own* current HJB
   model (the MFG assumption: identical agents play the same policy). No noise:
   a particle is the mean of its law. No communication after t = 0.

2. FPK model. m_hat(s, t) = w_F^T sigma_F((s - s_bar(t)) / fpk_scale), i.e. the
   paper's FPK model expressed in the co-moving frame of the particles' centroid
   s_bar(t), so d_t m_hat = -(d s_bar/dt)^T grad m_hat exactly. w_F is trained as in
   Algorithm 4 step 3: a normalised gradient step on L_F = F^2 / 2 with the FPK
   residual of eq. 10,
       F = d_t m_hat + div(b m_hat) - 1/2 tr(G G^T hess m_hat),
       b = A s + B(a*(s) + c0 v_o),  div b = -2 c0 - (1/(2 c3)) (psi_vxvx + psi_vyvy).
   Since F is linear in w_F, w_F = 0 would never move (erratum 7), so w_F(0) is the
   least-squares fit of sigma_F to a Gaussian kernel density of the t = 0 states.

3. Coupling. eq. 11 is evaluated by quadrature on the particles, weighted by the FPK
   model's density: phi_G(s_i, m_hat) = sum_{j != i} omega_j k(s_i, s_j) with
   omega_j proportional to max(m_hat(s_j), 0) (uniform if all are 0). So the HJB
   model sees the FPK model (Algorithm 4 step 1 uses m_hat^[k-1]) and the FPK model
   sees the HJB model (through b), as the K inner iterations intend.

Shapes for a bank of n vehicles holding P = N particles each: particles (n, P, 4).
"""

from __future__ import annotations

import numpy as np

from mfg_autopilot.paper import kernels
from mfg_autopilot.paper.costs import cs_kernel
from mfg_autopilot.paper.features import MonomialFeatures, make_sigma_F
from mfg_autopilot.paper.model import nominal_drift, optimal_action, saturate
from mfg_autopilot.paper.params import Preset

__all__ = ["MeanField", "fit_initial_fpk_weights", "kde_at", "KDE_EXACT_MAX_POINTS", "KDE_TRUNCATION_TOL"]


KDE_EXACT_MAX_POINTS = 1024
"""Up to this many t = 0 states the KDE of :func:`fit_initial_fpk_weights` is the exact all-pairs sum."""

KDE_TRUNCATION_TOL = 1e-12
"""Above it, kernels beyond c = sqrt(2 ln(P / tol)) bandwidths are left out: each is < tol / P, so the
density (a mean over P kernels, peak >= 1 / P) changes by < tol of its peak (docs/mean_field.md)."""


def kde_at(Y: np.ndarray, X: np.ndarray, bandwidth: np.ndarray, exact_max_points: int = KDE_EXACT_MAX_POINTS,
           tol: float = KDE_TRUNCATION_TOL) -> np.ndarray:
    """Gaussian kernel density of the points X (P, 4) with diagonal bandwidth h (4,), at Y (q, 4):
    dens(y) = 1/P sum_j exp(-|(y - x_j) / h|^2 / 2), (q,).

    P <= exact_max_points: the exact all-pairs sum (row blocks, O(q P)). Above: a k-d tree in
    the scaled space keeps the kernels within c = sqrt(2 ln(P / tol)) bandwidths (O((q + P) log P
    + pairs)); |dens_truncated - dens| < tol / P <= tol * max(dens) when Y contains X."""
    X = np.asarray(X, dtype=float)
    Y = np.asarray(Y, dtype=float)
    h = np.asarray(bandwidth, dtype=float)
    P = X.shape[0]
    dens = np.empty(Y.shape[0])
    if P <= exact_max_points:
        # in row blocks (memory O(block P) instead of O(q P)); each row's reduction is unchanged
        block = max(1, int(2**21 // max(P, 1)))
        for b in range(0, Y.shape[0], block):
            z = (Y[b:b + block, None, :] - X[None, :, :]) / h
            dens[b:b + block] = np.exp(-0.5 * np.sum(z * z, axis=2)).mean(axis=1)
        return dens
    from scipy.spatial import cKDTree
    c = float(np.sqrt(2.0 * np.log(P / tol)))
    near = cKDTree(Y / h).sparse_distance_matrix(cKDTree(X / h), c, output_type="ndarray")
    return np.bincount(near["i"], np.exp(-0.5 * near["v"] ** 2), Y.shape[0]) / P


def fit_initial_fpk_weights(sigma_F: MonomialFeatures, states_rel: np.ndarray, bandwidth: np.ndarray, ridge: float = 1e-6,
                            exact_max_points: int = KDE_EXACT_MAX_POINTS) -> np.ndarray:
    """w_F(0): least squares of sigma_F to a Gaussian kernel density of the t = 0 states.

    states_rel: (P, 4), relative to their centroid. The density (:func:`kde_at`: exact up to
    exact_max_points states, k-d tree truncated beyond) is evaluated on the states and on
    +-h offsets along each axis (9P points) and normalised to a peak of 1. Deterministic in
    the exchanged states: every vehicle fits the same w_F(0). Returns (M_F,).
    """
    X = np.asarray(states_rel, dtype=float)
    h = np.asarray(bandwidth, dtype=float)
    offsets = [np.zeros(4)] + [sgn * h[d] * np.eye(4)[d] for d in range(4) for sgn in (-1.0, 1.0)]
    Y = np.concatenate([X + o for o in offsets], axis=0)
    dens = kde_at(Y, X, h, exact_max_points)
    dens /= dens.max()
    Phi = sigma_F.value(Y)
    A = Phi.T @ Phi + ridge * np.trace(Phi.T @ Phi) / Phi.shape[1] * np.eye(Phi.shape[1])
    return np.linalg.solve(A, Phi.T @ dens)


class MeanField:
    """Particles + FPK model for a bank of n MFG vehicles (see module docstring)."""

    def __init__(self, exchanged_states: np.ndarray, destinations_m: np.ndarray, own_index: np.ndarray, preset: Preset) -> None:
        S0 = np.asarray(exchanged_states, dtype=float)
        if S0.ndim != 2 or S0.shape[1] != 4 or not np.all(np.isfinite(S0)):
            raise ValueError(f"exchanged_states must be a finite (N, 4) array, got {S0.shape}")
        P = S0.shape[0]
        dest = np.asarray(destinations_m, dtype=float).reshape(P, 2)
        own = np.asarray(own_index, dtype=np.int64).reshape(-1)
        if np.any(own < 0) or np.any(own >= P):
            raise ValueError("own_index out of range of the exchanged states")
        n = own.size
        self.preset = preset
        self.n_particles = P
        self.dest_particles = np.concatenate([dest, np.zeros((P, 2))], axis=1)       # (P, 4) frame offsets
        self.own_index = own
        self.own_destination = dest[own]                                              # (n, 2)
        self.particles = np.broadcast_to(S0, (n, P, 4)).copy()
        self.sigma_F = make_sigma_F(preset.learner.fpk_scale)
        w0 = fit_initial_fpk_weights(self.sigma_F, S0 - S0.mean(axis=0), np.asarray(preset.learner.fpk_kde_bandwidth))
        self.w_F = np.tile(w0, (n, 1))
        self._mask = np.ones((n, P))
        self._mask[np.arange(n), own] = 0.0                                         # exclude the own particle
        self._drift = None
        self._centroid_rate = None
        self._sigF_particles = None

    @property
    def centroid(self) -> np.ndarray:
        """s_bar(t) of each vehicle's particles, (n, 4)."""
        return self.particles.mean(axis=1)

    def begin_step(self, sigma_H: MonomialFeatures, w_H: np.ndarray) -> np.ndarray:
        """Evaluate the particles' drift under the current HJB models (one policy
        evaluation per particle) and cache sigma_F at the particles. Returns the
        number of mean-field evaluations made per vehicle (n,)."""
        n, P = self.particles.shape[:2]
        rel = (self.particles - self.dest_particles[None]).reshape(n * P, 4)
        grad_psi = sigma_H.grad_psi(rel, np.repeat(w_H, P, axis=0))
        acc = saturate(optimal_action(grad_psi, self.preset.cost.c3), self.preset.learner.acc_max_m_s2)
        self._drift = nominal_drift(rel, acc, self.preset.cost).reshape(n, P, 4)
        self._centroid_rate = self._drift.mean(axis=1)
        cen = self.centroid
        self._sigF_particles = self.sigma_F.value((self.particles - cen[:, None, :]).reshape(n * P, 4)).reshape(n, P, -1)
        return np.full(n, P, dtype=np.int64)

    def weights(self) -> np.ndarray:
        """Quadrature weights omega (n, P) from the FPK model, own particle excluded."""
        m_hat = np.maximum(np.einsum("npm,nm->np", self._sigF_particles, self.w_F), 0.0) * self._mask
        tot = m_hat.sum(axis=1, keepdims=True)
        uniform = self._mask / np.maximum(self._mask.sum(axis=1, keepdims=True), 1.0)
        return np.where(tot > 0, m_hat / np.maximum(tot, 1e-300), uniform)

    def phi_G(self, s_abs: np.ndarray) -> np.ndarray:
        """phi_G(s_i, m_hat) of eq. 11 by weighted particle quadrature, (n,)."""
        return np.einsum("np,np->n", self.weights(), cs_kernel(s_abs[:, None, :], self.particles, self.preset.cost))

    def fpk_update(self, s_abs: np.ndarray, s_rel: np.ndarray, hjb_post) -> None:
        """Algorithm 4 step 3: w_F <- w_F - mu * grad L_F / |grad L_F| at the own state.
        hjb_post: (grad psi (n, 4), psi_vxvx + psi_vyvy (n,)) at s_rel with the current w_H
        (what learners.hjb_update returns)."""
        cost, lp = self.preset.cost, self.preset.learner
        grad_psi, lap_v_psi = hjb_post
        a_star = optimal_action(grad_psi, cost.c3)                    # eq. 10: unsaturated a*
        self.w_F, self.last_residual = kernels.fpk_update_rows(
            self.sigma_F.exponents, self.sigma_F.scale, s_abs - self.centroid, s_rel, a_star, self._centroid_rate, lap_v_psi,
            self.w_F, cost.c0_per_s, cost.v_o, cost.c3, lp.mu, cost.V_o @ cost.V_o.T)

    def end_step(self, dt_s: float) -> None:
        """Propagate every particle one control period along its drift (explicit Euler)."""
        self.particles = self.particles + self._drift * dt_s
