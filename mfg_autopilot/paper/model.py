"""The controller's own model of the dynamics (eq. 9) and of the optimal action (eq. 7).

    ds = (A s + B (a + c0 v_o)) dt + G dW,   A = [[0, I], [0, -c0 I]], B = [0; I], G = [0; V_o]

The controller never imports the plant that really moves a vehicle
(``mock_vehicle.plant``); this module is its model of it, used inside the HJB and
FPK residuals (nominal drift, no noise, as Sec. IV-A prescribes for ds/dt).

Shapes: states (n, 4) [x_m, y_m, vx_m_s, vy_m_s]; accelerations (n, 2).
"""

from __future__ import annotations

import numpy as np
from scipy.linalg import solve_continuous_are

from mfg_autopilot.paper.features import MonomialFeatures
from mfg_autopilot.paper.params import CostParams

__all__ = ["A_matrix", "B_matrix", "G_matrix", "nominal_drift", "optimal_action", "saturate", "saturate_jacobian",
           "lqr_riccati_axis", "lqr_value_weights"]


def A_matrix(c0_per_s: float) -> np.ndarray:
    """A of eq. 9 (4x4)."""
    A = np.zeros((4, 4))
    A[0:2, 2:4] = np.eye(2)
    A[2:4, 2:4] = -c0_per_s * np.eye(2)
    return A


def B_matrix() -> np.ndarray:
    """B of eq. 9 (4x2)."""
    return np.vstack([np.zeros((2, 2)), np.eye(2)])


def G_matrix(V_o: np.ndarray) -> np.ndarray:
    """G of eq. 9 (4x2)."""
    return np.vstack([np.zeros((2, 2)), np.asarray(V_o, dtype=float)])


def nominal_drift(s: np.ndarray, acc_m_s2: np.ndarray, cost: CostParams) -> np.ndarray:
    """ds/dt without the wind noise: A s + B (a + c0 v_o), (n, 4) (Sec. IV-A, after eq. 13)."""
    v = s[:, 2:4]
    return np.concatenate([v, acc_m_s2 - cost.c0_per_s * v + cost.c0_per_s * cost.v_o], axis=1)


def optimal_action(grad_psi: np.ndarray, c3: float) -> np.ndarray:
    """a* = -(1 / (2 c3)) B^T nabla psi (eqs. 7, 8, 10; SPEC erratum 1 fixes the '+' of
    Algorithms 1-4). grad_psi: (n, 4) -> (n, 2)."""
    return -grad_psi[:, 2:4] / (2.0 * c3)


def saturate(acc: np.ndarray, limit: float) -> np.ndarray:
    """Scale rows of acc (n, 2) so that |a| <= limit."""
    norm = np.linalg.norm(acc, axis=1, keepdims=True)
    return acc * np.minimum(1.0, limit / np.maximum(norm, 1e-300))


def cap_norm(a: np.ndarray, limit) -> np.ndarray:
    """Scale rows of a (n, 2) so that |a| <= limit (limit scalar or (n,))."""
    nrm = np.linalg.norm(a, axis=1)
    lim = np.broadcast_to(np.asarray(limit, dtype=float), nrm.shape)
    return a * np.minimum(1.0, lim / np.maximum(nrm, 1e-300))[:, None]


def saturate_jacobian(u: np.ndarray, limit: float) -> np.ndarray:
    """d sat(u) / d u for rows of u (n, 2): I inside the limit, (limit/|u|)(I - u u^T/|u|^2) outside. (n, 2, 2)."""
    n = u.shape[0]
    norm = np.linalg.norm(u, axis=1)
    jac = np.broadcast_to(np.eye(2), (n, 2, 2)).copy()
    out = norm > limit
    if np.any(out):
        uh = u[out] / norm[out, None]
        jac[out] = (limit / norm[out])[:, None, None] * (np.eye(2)[None] - uh[:, :, None] * uh[:, None, :])
    return jac


def lqr_riccati_axis(cost: CostParams) -> np.ndarray:
    """P (2x2) of the per-axis LQ problem contained in the paper's cost:
    min int c1 x^2 + c2 v^2 + c3 a^2 dt, dx = v dt, dv = (a - c0 v) dt.
    The value is s^T P s per axis and a* = -(1/c3) [0 1] P s (CARE)."""
    A1 = np.array([[0.0, 1.0], [0.0, -cost.c0_per_s]])
    B1 = np.array([[0.0], [1.0]])
    return solve_continuous_are(A1, B1, np.diag([cost.c1, cost.c2]), np.array([[cost.c3]]))


def lqr_value_weights(sigma_H: MonomialFeatures, cost: CostParams) -> np.ndarray:
    """w_H such that w_H^T sigma_H(s) = sum over axes of s_axis^T P s_axis exactly
    (the LQ value is a quadratic form, which sigma_H represents). Shape (M_H,)."""
    P = lqr_riccati_axis(cost)
    w = np.zeros(sigma_H.M)
    sc = sigma_H.scale
    for pos_dim, vel_dim in ((0, 2), (1, 3)):
        for (a, b), coef in (((2, 0), P[0, 0]), ((1, 1), 2.0 * P[0, 1]), ((0, 2), P[1, 1])):
            e = np.zeros(4, dtype=np.int64)
            e[pos_dim], e[vel_dim] = a, b
            k = int(np.flatnonzero(np.all(sigma_H.exponents == e, axis=1))[0])
            w[k] = coef * sc[pos_dim] ** a * sc[vel_dim] ** b
    return w
