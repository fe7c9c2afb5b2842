"""Polynomial feature maps of the HJB and FPK models (paper Sec. V).

- sigma_H (M_H = 54): the non-constant monomials of (1 + x + v_x)^6 + (1 + y + v_y)^6,
  i.e. x^a v_x^b and y^a v_y^b with 1 <= a + b <= 6 (27 per axis).
- sigma_F (M_F = 69): the non-constant monomials of (1 + x + v_x + y + v_y)^4, i.e.
  x^a y^b v_x^c v_y^d with 1 <= a + b + c + d <= 4.

The monomials are taken with unit coefficients (the expansion's multinomial
coefficients would only rescale the weights). They are evaluated on a scaled state
s_tilde = (s - origin) / scale (docs/errata.md: without scaling, 150^6 ~ 1e13 and the
first step diverges); values, gradients and Hessians are returned with respect to the
physical state s, so that the models' nabla psi and nabla^2 psi are in SI units.

Shapes: ``s`` (n, 4) with columns [x_m, y_m, vx_m_s, vy_m_s]; values (n, M);
gradients (n, M, 4); Hessians (n, M, 4, 4); velocity-block Hessians (n, M, 2, 2).
The tables are computed row by row by ``mfg_autopilot.paper.kernels`` (numba); the learners
use its fused kernels, which contract with the weights without building the tables.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

from mfg_autopilot.paper import kernels

__all__ = ["MonomialFeatures", "sigma_H_exponents", "sigma_F_exponents", "make_sigma_H", "make_sigma_F"]


def sigma_H_exponents() -> np.ndarray:
    """Exponents (54, 4) of sigma_H over (x, y, v_x, v_y): the (x, v_x) block, then (y, v_y)."""
    rows = []
    for pos_dim, vel_dim in ((0, 2), (1, 3)):
        for total in range(1, 7):
            for a in range(total, -1, -1):
                e = [0, 0, 0, 0]
                e[pos_dim] = a
                e[vel_dim] = total - a
                rows.append(e)
    return np.array(rows, dtype=np.int64)


def sigma_F_exponents() -> np.ndarray:
    """Exponents (69, 4) of sigma_F over (x, y, v_x, v_y), by total degree 1..4."""
    rows = [e for total in range(1, 5) for e in itertools.product(range(total + 1), repeat=4) if sum(e) == total]
    return np.array(sorted(rows, key=lambda e: (sum(e), tuple(-x for x in e))), dtype=np.int64)


@dataclass(frozen=True, eq=False)
class MonomialFeatures:
    """sigma(s) = [prod_d s_tilde_d ** E[k, d]]_k with s_tilde = s / scale."""

    exponents: np.ndarray            # (M, 4) non-negative integers
    scale: np.ndarray                # (4,) positive

    def __post_init__(self) -> None:
        e = np.asarray(self.exponents)
        if e.ndim != 2 or e.shape[1] != 4 or np.any(e < 0):
            raise ValueError("exponents must be a non-negative (M, 4) integer array")
        sc = np.asarray(self.scale, dtype=float)
        if sc.shape != (4,) or np.any(~np.isfinite(sc)) or np.any(sc <= 0):
            raise ValueError(f"scale must be 4 finite positive numbers, got {self.scale}")
        object.__setattr__(self, "exponents", e.astype(np.int64))
        object.__setattr__(self, "scale", sc)
        object.__setattr__(self, "_max_deg", int(e.max()))

    @property
    def M(self) -> int:
        return self.exponents.shape[0]

    def _states(self, s: np.ndarray) -> np.ndarray:
        s = np.asarray(s, dtype=float)
        if s.ndim != 2 or s.shape[1] != 4:
            raise ValueError(f"states must be (n, 4), got {s.shape}")
        return s

    def value(self, s: np.ndarray) -> np.ndarray:
        """sigma(s), (n, M)."""
        return kernels.feature_tables(self.exponents, self.scale, self._states(s), 0)[0]

    def value_grad(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """sigma(s) (n, M) and d sigma / d s (n, M, 4)."""
        sig, J, _ = kernels.feature_tables(self.exponents, self.scale, self._states(s), 1)
        return sig, J

    def value_grad_hessvel(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """sigma (n, M), gradient (n, M, 4), and the velocity block of the Hessian
        d^2 sigma / d v d v (n, M, 2, 2): all that tr(G G^T nabla^2) needs, since
        G = [0; V_o] (eq. 9) only acts on the velocity."""
        return kernels.feature_tables(self.exponents, self.scale, self._states(s), 2)

    def hessian(self, s: np.ndarray) -> np.ndarray:
        """Full Hessian d^2 sigma / d s^2, (n, M, 4, 4)."""
        return kernels.hessian_table(self.exponents, self.scale, self._states(s))

    def grad_psi(self, s: np.ndarray, w: np.ndarray) -> np.ndarray:
        """nabla psi(s) = sum_k w_k nabla sigma_k(s) for psi = w^T sigma, row by row: s (n, 4), w (n, M) -> (n, 4).
        Without the (n, M, 4) table."""
        w = np.asarray(w, dtype=float)
        if w.shape != (np.shape(s)[0], self.M):
            raise ValueError(f"weights must be (n, {self.M}), got {w.shape}")
        return kernels.grad_psi(self.exponents, self.scale, self._states(s), w)


def make_sigma_H(state_scale) -> MonomialFeatures:
    """The HJB model's features sigma_H (54) on s / state_scale."""
    return MonomialFeatures(sigma_H_exponents(), np.asarray(state_scale, dtype=float))


def make_sigma_F(fpk_scale) -> MonomialFeatures:
    """The FPK model's features sigma_F (69) on s / fpk_scale."""
    return MonomialFeatures(sigma_F_exponents(), np.asarray(fpk_scale, dtype=float))
