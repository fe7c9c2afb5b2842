"""The numpy formulation the numba kernels (mfg_autopilot/paper/kernels.py) replaced, verbatim from
commit c6952e1 (features.MonomialFeatures tables, learners.hjb_update, DefaultMFGController._phi_G /
_fpk_update, MeanField.fpk_update): the reference that tests/test_kernels.py compares the kernels with."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from mfg_autopilot.paper.costs import cs_kernel, phi_L_state
from mfg_autopilot.paper.model import nominal_drift, optimal_action, saturate, saturate_jacobian


class NumpyFeatures:
    """features.MonomialFeatures as it was: factor tables per dimension, then products."""

    def __init__(self, feats) -> None:
        self.exponents, self.scale = feats.exponents, feats.scale
        self._max_deg = int(self.exponents.max())
        self.M = self.exponents.shape[0]

    # -- factor tables -------------------------------------------------------------
    def _factors(self, s: np.ndarray, order: int):
        """Per-dimension factors F[d] = st_d^e, dF[d] = e st_d^(e-1), d2F[d] = e(e-1) st_d^(e-2), each (n, M)."""
        s = np.asarray(s, dtype=float)
        if s.ndim != 2 or s.shape[1] != 4:
            raise ValueError(f"states must be (n, 4), got {s.shape}")
        st = s / self.scale
        D = self._max_deg
        powers = st[:, :, None] ** np.arange(D + 1)[None, None, :]    # (n, 4, D+1)
        E = self.exponents
        F, dF, d2F = [], [], []
        for d in range(4):
            e = E[:, d]
            p = powers[:, d, :]
            F.append(p[:, e])
            if order >= 1:
                dF.append(e * p[:, np.maximum(e - 1, 0)])
            if order >= 2:
                d2F.append(e * (e - 1) * p[:, np.maximum(e - 2, 0)])
        return F, dF, d2F

    def value(self, s: np.ndarray) -> np.ndarray:
        """sigma(s), (n, M)."""
        F, _, _ = self._factors(s, 0)
        return F[0] * F[1] * F[2] * F[3]

    def value_grad(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """sigma(s) (n, M) and d sigma / d s (n, M, 4)."""
        F, dF, _ = self._factors(s, 1)
        return F[0] * F[1] * F[2] * F[3], self._grad(F, dF)

    def _grad(self, F, dF) -> np.ndarray:
        n, M = F[0].shape
        J = np.empty((n, M, 4))
        for d in range(4):
            g = dF[d]
            for e in range(4):
                if e != d:
                    g = g * F[e]
            J[:, :, d] = g / self.scale[d]
        return J

    def _hess_entry(self, F, dF, d2F, d: int, e: int) -> np.ndarray:
        if d == e:
            h = d2F[d]
            others = [k for k in range(4) if k != d]
        else:
            h = dF[d] * dF[e]
            others = [k for k in range(4) if k not in (d, e)]
        for k in others:
            h = h * F[k]
        return h / (self.scale[d] * self.scale[e])

    def value_grad_hessvel(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """sigma (n, M), gradient (n, M, 4), and the velocity block of the Hessian
        d^2 sigma / d v d v (n, M, 2, 2): all that tr(G G^T nabla^2) needs, since
        G = [0; V_o] (eq. 9) only acts on the velocity."""
        F, dF, d2F = self._factors(s, 2)
        sig = F[0] * F[1] * F[2] * F[3]
        J = self._grad(F, dF)
        n, M = sig.shape
        Hv = np.empty((n, M, 2, 2))
        Hv[:, :, 0, 0] = self._hess_entry(F, dF, d2F, 2, 2)
        Hv[:, :, 1, 1] = self._hess_entry(F, dF, d2F, 3, 3)
        Hv[:, :, 0, 1] = Hv[:, :, 1, 0] = self._hess_entry(F, dF, d2F, 2, 3)
        return sig, J, Hv

    def hessian(self, s: np.ndarray) -> np.ndarray:
        """Full Hessian d^2 sigma / d s^2, (n, M, 4, 4)."""
        F, dF, d2F = self._factors(s, 2)
        n, M = F[0].shape
        H = np.empty((n, M, 4, 4))
        for d in range(4):
            for e in range(d, 4):
                H[:, :, d, e] = H[:, :, e, d] = self._hess_entry(F, dF, d2F, d, e)
        return H


def _normalised(g: np.ndarray) -> np.ndarray:
    """g / |g| row-wise, 0 where g = 0 (the paper's sign(x) = x/|x|)."""
    nrm = np.linalg.norm(g, axis=1, keepdims=True)
    return np.where(nrm > 0, g / np.maximum(nrm, 1e-300), 0.0)


def policy_action(sigma_H: MonomialFeatures, w_H: np.ndarray, s_rel: np.ndarray, preset: Preset) -> np.ndarray:
    """a* = sat(-(1/(2 c3)) B^T grad psi_hat(s)) for states s_rel (n, 4) and weights w_H (n, M)."""
    _, J = NumpyFeatures(sigma_H).value_grad(s_rel)
    grad_psi = np.einsum("nmd,nm->nd", J, w_H)
    return saturate(optimal_action(grad_psi, preset.cost.c3), preset.learner.acc_max_m_s2)


def hjb_update(sigma_H: MonomialFeatures, w_H: np.ndarray, s_rel: np.ndarray, phi_g: np.ndarray, preset: Preset):
    """One weight update of Algorithm 3, step 2, for every learner of a bank.

    Returns (w_new (n, M), residual H_hat (n,), R active (n,) bool, feature tuple at s).
    """
    cost, lp = preset.cost, preset.learner
    sig, J, Hv = NumpyFeatures(sigma_H).value_grad_hessvel(s_rel)
    GGt = cost.V_o @ cost.V_o.T
    T = np.einsum("nmab,ab->nm", Hv, GGt)                       # tr(G G^T hess sigma_k)
    grad_psi = np.einsum("nmd,nm->nd", J, w_H)
    f0 = nominal_drift(s_rel, np.zeros((s_rel.shape[0], 2)), cost)   # A s + B c0 v_o
    p = grad_psi[:, 2:4]                                          # B^T grad psi
    H_hat = (np.einsum("nd,nd->n", f0, grad_psi) - np.einsum("nd,nd->n", p, p) / (4 * cost.c3)
             + 0.5 * np.einsum("nm,nm->n", w_H, T) + phi_L_state(s_rel, cost) + cost.c4 * phi_g)
    dH_dw = (np.einsum("nmd,nd->nm", J, f0) - np.einsum("nmv,nv->nm", J[:, :, 2:4], p) / (2 * cost.c3) + 0.5 * T)
    grad_l = H_hat[:, None] * dH_dw                              # grad_w of l_H = H_hat^2 / 2

    # Regulariser R = max(0, s~^T ds~/dt), s~ = s / scale, nominal drift under sat(a*).
    scale = sigma_H.scale
    u = optimal_action(grad_psi, cost.c3)
    a = saturate(u, lp.acc_max_m_s2)
    ds = nominal_drift(s_rel, a, cost)
    st = s_rel / scale
    R = np.einsum("nd,nd->n", st, ds / scale)
    active = R > 0
    grad_R = np.zeros_like(w_H)
    if np.any(active):
        Ds = saturate_jacobian(u[active], lp.acc_max_m_s2)             # (k, 2, 2)
        du_dw = -J[active][:, :, 2:4] / (2 * cost.c3)                 # (k, M, 2)
        coef = st[active][:, 2:4] / scale[2:4]                         # d R / d v
        grad_R[active] = np.einsum("kv,kvu,kmu->km", coef, Ds, du_dw)
    w_new = w_H - lp.mu * _normalised(grad_l) - lp.c_H * grad_R
    return w_new, H_hat, active, (sig, J, Hv)


class DefaultMFGNumpy:
    """DefaultMFGController._phi_G and _fpk_update as they were, on a controller's state (ctrl)."""

    def __init__(self, ctrl) -> None:
        self.c = ctrl

    def __getattr__(self, name):
        return getattr(self.c, name)

    def _phi_G(self, own: np.ndarray, centroid: np.ndarray) -> tuple[np.ndarray, int]:
        tp = self.preset.tracking
        x = self.plan.states
        # (row, particle) pairs within the radius (k-d tree against k-d tree, all in C), in row order with
        # particles ascending (the order of each row's sorted query_ball_point list), own particle left out
        near = cKDTree(own[:, 0:2]).sparse_distance_matrix(cKDTree(x[:, 0:2]), tp.phi_g_radius_m, output_type="ndarray")
        rows, cols = near["i"].astype(np.int64), near["j"].astype(np.int64)
        order = np.argsort(rows * np.int64(x.shape[0]) + cols)      # distinct keys: any sort gives one order
        rows, cols = rows[order], cols[order]
        keep = cols != self.own_index[rows]
        rows, cols = rows[keep], cols[keep]
        if cols.size == 0:
            return np.zeros(self.n), 0
        k = cs_kernel(own[rows], x[cols], self.preset.cost)
        if tp.learn_fpk:
            # sigma_F is elementwise per row: evaluate it once per particle used (the used ones ascending, as
            # np.unique gives them), then gather per pair
            present = np.bincount(cols, minlength=x.shape[0]) > 0
            used = np.flatnonzero(present)
            pos = (np.cumsum(present) - 1)[cols]
            # per pair m_hat = sum_m sig[m] w_F[m], summed sequentially over m = 0..M-1 (what einsum does with the
            # pair axis contiguous, bit for bit on the 16 reference runs; tests/test_scaling.py checks phi_G against a
            # per-row brute-force quadrature), one feature at a time
            # from transposed tables: no (pairs, M_F) temporaries
            sigT = np.ascontiguousarray(NumpyFeatures(self.sigma_F).value(x[used] - centroid[None, :]).T)      # (M_F, used)
            wT = np.ascontiguousarray(self.w_F.T)                                              # (M_F, n)
            w = np.zeros(cols.size)
            for m in range(sigT.shape[0]):
                w += sigT[m][pos] * wT[m][rows]
            w = np.maximum(w, 0.0)
        else:
            w = np.ones(cols.size)
        tot = np.bincount(rows, w, self.n)
        cnt = np.bincount(rows, minlength=self.n)
        w = np.where(tot[rows] > 0, w / np.maximum(tot[rows], 1e-300), 1.0 / np.maximum(cnt[rows], 1))
        return np.bincount(rows, w * k, self.n), int(cols.size)

    def _fpk_update(self, own: np.ndarray, e: np.ndarray, a: np.ndarray, centroid: np.ndarray, centroid_rate: np.ndarray,
                    hess_v_psi_trace: np.ndarray) -> None:
        """Algorithm 4 step 3 at the own state, FPK model in the plan's co-moving frame:
        F = J_F (b - d s_bar/dt) + sigma_F div b - 1/2 tr(G G^T hess m_hat), linear in w_F."""
        cost, lp = self.preset.cost, self.preset.learner
        b = nominal_drift(own, a, cost)
        div_b = -2.0 * cost.c0_per_s - hess_v_psi_trace / (2.0 * cost.c3)
        sigF, JF, HvF = NumpyFeatures(self.sigma_F).value_grad_hessvel(own - centroid[None, :])
        T_F = np.einsum("nmab,ab->nm", HvF, cost.V_o @ cost.V_o.T)
        g_F = np.einsum("nmd,nd->nm", JF, b - centroid_rate[None, :]) + sigF * div_b[:, None] - 0.5 * T_F
        F = np.einsum("nm,nm->n", self.w_F, g_F)
        g = F[:, None] * g_F
        nrm = np.linalg.norm(g, axis=1, keepdims=True)
        self.w_F = self.w_F - lp.mu * np.where(nrm > 0, g / np.maximum(nrm, 1e-300), 0.0)


def meanfield_fpk_update(self, s_abs, s_rel, w_H, hjb_feats):
    """MeanField.fpk_update as it was (self: a MeanField); returns (w_F, F) without changing self."""
    cost, lp = self.preset.cost, self.preset.learner
    _, J_H, Hv_H = hjb_feats
    grad_psi = np.einsum("nmd,nm->nd", J_H, w_H)
    a_star = optimal_action(grad_psi, cost.c3)                    # eq. 10: unsaturated a*
    b = nominal_drift(s_rel, a_star, cost)
    lap_v_psi = np.einsum("nm,nm->n", Hv_H[:, :, 0, 0] + Hv_H[:, :, 1, 1], w_H)
    div_b = -2.0 * cost.c0_per_s - lap_v_psi / (2.0 * cost.c3)
    sigF, JF, HvF = NumpyFeatures(self.sigma_F).value_grad_hessvel(s_abs - self.centroid)
    T_F = np.einsum("nmab,ab->nm", HvF, cost.V_o @ cost.V_o.T)
    g_F = np.einsum("nmd,nd->nm", JF, b - self._centroid_rate) + sigF * div_b[:, None] - 0.5 * T_F
    F = np.einsum("nm,nm->n", self.w_F, g_F)                       # eq. 10 residual (linear in w_F)
    g = F[:, None] * g_F
    nrm = np.linalg.norm(g, axis=1, keepdims=True)
    return self.w_F - lp.mu * np.where(nrm > 0, g / np.maximum(nrm, 1e-300), 0.0), F

