"""Running costs of eq. 3: phi_L (local) and phi_G (Cucker-Smale interaction), and
the mean-field interaction of eq. 11.

    phi_L(s_i) = v_i . r_i / |r_i| + c1 |r_i|^2 + c2 |v_i|^2 + c3 |a_i|^2
    phi_G(s_i) = 1/(N_i - 1) sum_{j in N_i \\ i} |v_j - v_i|^2 / (eps + |r_j - r_i|^2)^beta
    phi_G(s_i, m) = int m(s) |v - v_i|^2 / (eps + |r - r_i|^2)^beta ds          (eq. 11)

(SPEC erratum 4: c4 multiplies phi_G where it enters a cost; eq. 11's eps^2 is read as eps.)
Shapes: states (n, 4); positions are relative to the vehicle's destination where it matters.
"""

from __future__ import annotations

import numpy as np

from mfg_autopilot.paper.params import CostParams

__all__ = ["phi_L_state", "phi_L", "cs_kernel", "phi_G_pairs", "phi_G_weighted"]


def phi_L_state(s: np.ndarray, cost: CostParams) -> np.ndarray:
    """The state part of phi_L: v.r/|r| + c1|r|^2 + c2|v|^2, (n,). Inside the HJB
    residual the c3|a|^2 term is already in the minimised Hamiltonian (SPEC erratum 3).
    At r = 0 the direction term is taken as 0."""
    r, v = s[:, 0:2], s[:, 2:4]
    rn = np.linalg.norm(r, axis=1)
    proj = np.where(rn > 0, np.einsum("nd,nd->n", v, r) / np.maximum(rn, 1e-300), 0.0)
    return proj + cost.c1 * rn**2 + cost.c2 * np.einsum("nd,nd->n", v, v)


def phi_L(s: np.ndarray, acc_m_s2: np.ndarray, cost: CostParams) -> np.ndarray:
    """phi_L of eq. 3 including c3|a|^2, (n,)."""
    return phi_L_state(s, cost) + cost.c3 * np.einsum("nd,nd->n", acc_m_s2, acc_m_s2)


def cs_kernel(s_i: np.ndarray, s_j: np.ndarray, cost: CostParams) -> np.ndarray:
    """Cucker-Smale term |v_j - v_i|^2 / (eps + |r_j - r_i|^2)^beta, broadcast over leading axes."""
    dr = s_j[..., 0:2] - s_i[..., 0:2]
    dv = s_j[..., 2:4] - s_i[..., 2:4]
    return np.sum(dv * dv, axis=-1) / (cost.eps_m2 + np.sum(dr * dr, axis=-1)) ** cost.beta


def phi_G_pairs(states: np.ndarray, pairs: np.ndarray, cost: CostParams) -> tuple[np.ndarray, np.ndarray]:
    """phi_G of eq. 3 for every vehicle from an undirected neighbour list.

    states: (n, 4); pairs: (p, 2) int, each unordered pair once (i < j).
    Returns (phi_G (n,), neighbour counts N_i - 1 (n,)); phi_G is 0 without neighbours.
    """
    n = states.shape[0]
    pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    if pairs.size == 0:
        return np.zeros(n), np.zeros(n, dtype=np.int64)
    k = cs_kernel(states[pairs[:, 0]], states[pairs[:, 1]], cost)
    total = np.bincount(pairs[:, 0], k, n) + np.bincount(pairs[:, 1], k, n)
    count = np.bincount(pairs[:, 0], minlength=n) + np.bincount(pairs[:, 1], minlength=n)
    return np.where(count > 0, total / np.maximum(count, 1), 0.0), count


def phi_G_weighted(s_i: np.ndarray, particles: np.ndarray, weights: np.ndarray, cost: CostParams) -> np.ndarray:
    """Eq. 11 by quadrature over particles: sum_j weights_j kernel(s_i, s_j).

    s_i: (n, 4); particles: (n, P, 4); weights: (n, P), each row summing to 1 (0 for
    excluded particles). Returns (n,).
    """
    return np.einsum("np,np->n", weights, cs_kernel(s_i[:, None, :], particles, cost))
