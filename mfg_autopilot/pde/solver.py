"""Finite-difference solvers of the HJB (eq. 8) and of the coupled HJB-FPK MFG system
(eqs. 8, 10, 11): the solved controllers of Algorithms 1 and 2 (pure numerics, no I/O).

Structure used (docs/pde.md has the full design and the measured figures)
-------------------------------------------------------------------------
The dynamics (eq. 9) and the local cost decouple per axis: (x, v_x) and (y, v_y) each obey

    dx = v dt,   dv = (a - c0 v + c0 v_o) dt + sigma dW,          sigma = V_o[axis, axis]

with running cost c1 x^2 + c2 v^2 + c3 a^2, so every axis is a 2-D problem on its own grid.
Two terms do not decouple:

* v.r/|r| (eq. 3): split by evaluating the other axis on the straight line from the
  destination through the mission's start direction e = r0/|r0|, where x/|r| = |e_x| sign(x).
  The axis cost is then kappa v sign(x) with kappa = |e_x| (kappa_x^2 + kappa_y^2 = 1): exact
  on that line, an approximation off it.
* phi_G(s, m) (eq. 11, c4 and eps as in docs/errata.md R3): its numerator splits,
  |v' - v|^2 = (v'_x - v_x)^2 + (v'_y - v_y)^2, the denominator (eps + |r' - r|^2)^beta does
  not. With the mean field held as a product of per-axis marginals m = m_x (x) m_y, the x-part
  is evaluated with the representative's other coordinate at the mean field's current mean
  y_bar(t) (the coupling evaluated on the current iterate), and likewise for y.

Schemes
-------
Generator of the controlled diffusion on a grid (x_i, v_j) (monotone upwind, a Markov chain):
rates to the +x / -x neighbour max(v, 0)/dx, max(-v, 0)/dx; to the +v / -v neighbour
max(b, 0)/dv + D/dv^2, max(-b, 0)/dv + D/dv^2 with b = a - c0 v + c0 v_o, D = sigma^2 / 2.
Boundaries are state constraints: a rate leaving the grid is set to 0 (reflecting).

* Stationary HJB (Algorithm 1's value; discount rho, time-invariant like the learned model,
  docs/errata.md R4): rho psi = min_a {Q_a psi + f(a)}, solved by Howard's policy iteration,
  each policy evaluated by a sparse direct solve of (rho I - Q_a) psi = f_a (an M-matrix:
  implicit, monotone, no CFL restriction).
* Time-dependent HJB (MFG, finite horizon with terminal value the stationary psi) backward and
  FPK forward, explicit:  psi^n = psi^{n+1} + dt min_a (Q_a psi^{n+1} + f_a + c4 phi_G^n),
  m^{n+1} = m^n + dt Q_{a^n}^T m^n (the FPK is the adjoint of the HJB's generator, so its total
  mass is conserved to round-off). Both are monotone / positivity preserving under the CFL
  condition  dt * max_ij (|v_j|/dx + |b|_max/dv + 2 D/dv^2) <= 1,  with |b|_max = a_box +
  c0 (v_max + |v_o|), which is why the MFG needs a bounded control (a_box).
* MFG fixed point (Algorithm 2): m^[0] = FPK under the uncoupled policy from the smoothed
  empirical t = 0 measure; for k = 1..K: HJB backward against phi_G(., m^[k-1]), FPK forward,
  m^[k] = (1 - theta) m^[k-1] + theta FPK(psi^[k]) (damping, applied to the marginals).

Units: x in m, v in m/s, a in m/s^2, t in s, psi in cost units (cost * s). Shapes: a grid of
one axis is (nx, nv); masses m are cell masses summing to 1 (not densities).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from mfg_autopilot.paper.features import MonomialFeatures
from mfg_autopilot.paper.params import CostParams

__all__ = ["AxisGrid", "AxisProblem", "axis_problems", "StationarySolution", "solve_stationary_hjb",
           "cfl_dt_s", "hjb_backward_step", "fpk_forward_step", "deposit_cic", "interp_bilinear",
           "MFGSolution", "solve_mfg", "project_on_sigma_H"]


# ----------------------------------------------------------------------------------------------
# grids and per-axis problems
# ----------------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class AxisGrid:
    """Uniform grid of one axis: positions x_m (nx,) and velocities v_m_s (nv,)."""

    x_m: np.ndarray
    v_m_s: np.ndarray

    @staticmethod
    def make(x_min_m: float, x_max_m: float, v_max_m_s: float, dx_m: float, dv_m_s: float) -> "AxisGrid":
        """Grid over [x_min, x_max] x [-v_max, v_max] with spacings close to (dx, dv); the
        origin is a node when x_min <= 0 <= x_max (the value's minimum sits there)."""
        if not (dx_m > 0 and dv_m_s > 0 and v_max_m_s > 0 and x_max_m > x_min_m):
            raise ValueError("AxisGrid.make needs dx_m > 0, dv_m_s > 0, v_max_m_s > 0, x_max_m > x_min_m")
        if x_min_m <= 0.0 <= x_max_m:
            lo, hi = math.ceil(-x_min_m / dx_m - 1e-9), math.ceil(x_max_m / dx_m - 1e-9)
            x = np.arange(-lo, hi + 1) * dx_m
        else:
            x = np.linspace(x_min_m, x_max_m, int(round((x_max_m - x_min_m) / dx_m)) + 1)
        nvh = math.ceil(v_max_m_s / dv_m_s - 1e-9)
        v = np.arange(-nvh, nvh + 1) * dv_m_s
        return AxisGrid(x, v)

    @property
    def shape(self) -> tuple[int, int]:
        return (self.x_m.size, self.v_m_s.size)

    @property
    def dx_m(self) -> float:
        return float(self.x_m[1] - self.x_m[0])

    @property
    def dv_m_s(self) -> float:
        return float(self.v_m_s[1] - self.v_m_s[0])

    @cached_property
    def _mesh(self) -> tuple[np.ndarray, np.ndarray]:
        X, V = np.meshgrid(self.x_m, self.v_m_s, indexing="ij")
        X.setflags(write=False); V.setflags(write=False)
        return X, V

    def mesh(self) -> tuple[np.ndarray, np.ndarray]:
        """(X, V) each (nx, nv), read-only (cached)."""
        return self._mesh

    @cached_property
    def x_rates(self) -> tuple[np.ndarray, np.ndarray]:
        """Upwind jump rates (1/s) of the position drift v to the +x / -x neighbour, (nx, nv) each;
        0 across the boundary (state constraint)."""
        _, V = self._mesh
        rxp = np.maximum(V, 0.0) / self.dx_m
        rxm = np.maximum(-V, 0.0) / self.dx_m
        rxp[-1, :] = 0.0
        rxm[0, :] = 0.0
        return rxp, rxm

    @cached_property
    def _cost_cache(self) -> dict:
        return {}

    def state_cost(self, prob: "AxisProblem") -> np.ndarray:
        """c1 x^2 + c2 v^2 + kappa v sign(x) on the grid, (nx, nv) (cached per problem)."""
        f = self._cost_cache.get(prob)
        if f is None:
            X, V = self._mesh
            f = prob.c1 * X ** 2 + prob.c2 * V ** 2 + prob.kappa * V * np.sign(X)
            self._cost_cache[prob] = f
        return f


@dataclass(frozen=True)
class AxisProblem:
    """The per-axis control problem (eq. 3 restricted to one axis, eq. 9 per axis).

    running cost f = c1 x^2 + c2 v^2 + kappa v sign(x) + c3 a^2 (+ c4 phi_G share),
    drift (v, a - c0 v + c0 v_o), diffusion D = sigma^2/2 on v, discount rho_per_s
    (stationary problem only), control box |a| <= acc_box_m_s2 (None: unconstrained, eq. 8).
    """

    c0_per_s: float
    c1: float
    c2: float
    c3: float
    v_o_m_s: float = 0.0
    sigma_m_s: float = 0.0               # V_o[axis, axis], m/s per sqrt(s)
    kappa: float = 0.0                   # weight of the split v.r/|r| term
    acc_box_m_s2: float | None = None
    rho_per_s: float = 1e-3

    @property
    def D(self) -> float:
        return 0.5 * self.sigma_m_s ** 2


def axis_problems(cost: CostParams, direction: np.ndarray, acc_box_m_s2: float | None,
                  rho_per_s: float = 1e-3) -> tuple[AxisProblem, AxisProblem]:
    """The x and y problems of the paper's cost. direction (2,): start offset from the
    destination (its unit vector gives kappa = |e|); V_o must be diagonal."""
    V = cost.V_o
    if abs(V[0, 1]) > 0 or abs(V[1, 0]) > 0:
        raise ValueError("axis splitting needs a diagonal V_o")
    d = np.asarray(direction, dtype=float)
    nrm = float(np.linalg.norm(d))
    kap = np.abs(d) / nrm if nrm > 0 else np.full(2, np.sqrt(0.5))
    return tuple(AxisProblem(cost.c0_per_s, cost.c1, cost.c2, cost.c3, float(cost.v_o[k]), float(V[k, k]),
                             float(kap[k]), acc_box_m_s2, rho_per_s) for k in range(2))


# ----------------------------------------------------------------------------------------------
# the upwind generator
# ----------------------------------------------------------------------------------------------
def _rates(grid: AxisGrid, prob: AxisProblem, a: np.ndarray):
    """Jump rates (1/s) to the +x, -x, +v, -v neighbours, each (nx, nv); 0 across the boundary."""
    _, V = grid.mesh()
    dv = grid.dv_m_s
    rxp, rxm = grid.x_rates
    b = a - prob.c0_per_s * V + prob.c0_per_s * prob.v_o_m_s
    diff = prob.D / dv ** 2
    rvp = np.maximum(b, 0.0) / dv + diff
    rvm = np.maximum(-b, 0.0) / dv + diff
    rvp[:, -1] = 0.0
    rvm[:, 0] = 0.0
    return rxp, rxm, rvp, rvm


def _apply_Q(rates, psi: np.ndarray) -> np.ndarray:
    """(Q psi)_ij = sum over neighbours of rate * (psi_nb - psi_ij)."""
    rxp, rxm, rvp, rvm = rates
    out = np.zeros_like(psi)
    d = psi[1:, :] - psi[:-1, :]
    out[:-1] += rxp[:-1] * d
    out[1:] -= rxm[1:] * d
    d = psi[:, 1:] - psi[:, :-1]
    out[:, :-1] += rvp[:, :-1] * d
    out[:, 1:] -= rvm[:, 1:] * d
    return out


def _apply_QT(rates, m: np.ndarray) -> np.ndarray:
    """(Q^T m): the conservative upwind FPK operator (outflow minus inflow of each cell)."""
    rxp, rxm, rvp, rvm = rates
    out = -(rxp + rxm + rvp + rvm) * m
    out[1:] += rxp[:-1] * m[:-1]
    out[:-1] += rxm[1:] * m[1:]
    out[:, 1:] += rvp[:, :-1] * m[:, :-1]
    out[:, :-1] += rvm[:, 1:] * m[:, 1:]
    return out


def _Q_matrix(rates, shape) -> sp.csc_matrix:
    """Sparse Q (N x N), N = nx nv, flat index i nv + j."""
    rxp, rxm, rvp, rvm = (r.ravel() for r in rates)
    nv = shape[1]
    diag = -(rxp + rxm + rvp + rvm)
    return sp.diags([diag, rxp[:-nv], rxm[nv:], rvp[:-1], rvm[1:]], [0, nv, -nv, 1, -1], format="csc")


def _running_cost(grid: AxisGrid, prob: AxisProblem, a: np.ndarray, extra: np.ndarray | None) -> np.ndarray:
    f = grid.state_cost(prob) + prob.c3 * a * a
    return f if extra is None else f + extra


def _policy(grid: AxisGrid, prob: AxisProblem, psi: np.ndarray) -> np.ndarray:
    """argmin over |a| <= a_box of max(b, 0) Df + min(b, 0) Db + c3 a^2 with b = a + w,
    w = -c0 v + c0 v_o, Df / Db the forward / backward v-differences (0 across the boundary).
    The minimiser is one of three candidates (each convex piece's clipped minimiser, and b = 0)."""
    dv = grid.dv_m_s
    d = np.diff(psi, axis=1) / dv
    Df = np.zeros_like(psi); Df[:, :-1] = d
    Db = np.zeros_like(psi); Db[:, 1:] = d
    _, V = grid.mesh()
    w = -prob.c0_per_s * V + prob.c0_per_s * prob.v_o_m_s
    A = np.inf if prob.acc_box_m_s2 is None else prob.acc_box_m_s2
    c3 = prob.c3
    cands = (np.clip(np.maximum(-Df / (2 * c3), -w), -A, A),
             np.clip(np.minimum(-Db / (2 * c3), -w), -A, A),
             np.clip(-w, -A, A))
    best = None
    a_out = None
    for a in cands:
        b = a + w
        g = np.maximum(b, 0.0) * Df + np.minimum(b, 0.0) * Db + c3 * a * a
        if best is None:
            best, a_out = g, a.copy()
        else:
            take = g < best
            best = np.where(take, g, best)
            a_out = np.where(take, a, a_out)
    return a_out


# ----------------------------------------------------------------------------------------------
# stationary HJB (Algorithm 1's value)
# ----------------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class StationarySolution:
    """psi (nx, nv) solving rho psi = min_a {Q_a psi + f_a} on grid; a_m_s2 (nx, nv) the policy."""

    grid: AxisGrid
    problem: AxisProblem
    psi: np.ndarray
    a_m_s2: np.ndarray
    iterations: int
    policy_change: float          # max |a^{k+1} - a^k| at the last iteration (m/s^2)

    def dpsi_dv(self) -> np.ndarray:
        """d psi / d v on the grid (central differences inside, one-sided at the edges), (nx, nv)."""
        return np.gradient(self.psi, self.grid.dv_m_s, axis=1)


def _lqr_policy(grid: AxisGrid, prob: AxisProblem) -> np.ndarray:
    from scipy.linalg import solve_continuous_are
    A1 = np.array([[0.0, 1.0], [0.0, -prob.c0_per_s]]) - 0.5 * prob.rho_per_s * np.eye(2)
    P = solve_continuous_are(A1, np.array([[0.0], [1.0]]), np.diag([prob.c1, prob.c2]), np.array([[prob.c3]]))
    X, V = grid.mesh()
    a = -(P[0, 1] * X + P[1, 1] * V) / prob.c3
    A = np.inf if prob.acc_box_m_s2 is None else prob.acc_box_m_s2
    return np.clip(a, -A, A)


def solve_stationary_hjb(grid: AxisGrid, prob: AxisProblem, extra: np.ndarray | None = None,
                         max_iter: int = 50, tol_m_s2: float = 1e-6,
                         a0: np.ndarray | None = None) -> StationarySolution:
    """Howard policy iteration for the discounted stationary HJB of one axis (eq. 8 with
    d_t psi = 0, docs/errata.md R4, plus the discount rho):

        rho psi = min_{|a| <= a_box} { v d_x psi + (a - c0 v + c0 v_o) d_v psi + D d_vv psi + f(x, v, a) }

    discretised with the monotone upwind generator (state-constrained boundaries). Each policy
    evaluation is one sparse LU solve; the start policy is the (clipped) LQR policy of the LQ
    part (a0 overrides it, e.g. a warm start). extra (nx, nv): an added running cost."""
    if not prob.rho_per_s > 0:
        raise ValueError("the stationary solver needs rho_per_s > 0")
    a = _lqr_policy(grid, prob) if a0 is None else np.array(a0, dtype=float)
    N = grid.x_m.size * grid.v_m_s.size
    eye = sp.identity(N, format="csc")
    change = np.inf
    psi = None
    it = 0
    for it in range(1, max_iter + 1):
        rates = _rates(grid, prob, a)
        M = prob.rho_per_s * eye - _Q_matrix(rates, grid.shape)
        f = _running_cost(grid, prob, a, extra)
        psi = spla.spsolve(M, f.ravel()).reshape(grid.shape)
        a_new = _policy(grid, prob, psi)
        change = float(np.max(np.abs(a_new - a)))
        a = a_new
        if change <= tol_m_s2:
            break
    return StationarySolution(grid, prob, psi, a, it, change)


# ----------------------------------------------------------------------------------------------
# explicit time stepping (MFG)
# ----------------------------------------------------------------------------------------------
def cfl_dt_s(grid: AxisGrid, prob: AxisProblem, safety: float = 0.9) -> float:
    """Largest explicit step with dt * max(|v|/dx + |b|_max/dv + 2D/dv^2) <= safety, where
    |b|_max = a_box + c0 (v_max + |v_o|): under it the HJB step is monotone and the FPK step
    keeps m >= 0 (the CFL condition of Sec. IV for this grid and drift)."""
    if prob.acc_box_m_s2 is None:
        raise ValueError("the explicit scheme needs a bounded control (acc_box_m_s2)")
    vmax = float(np.max(np.abs(grid.v_m_s)))
    bmax = prob.acc_box_m_s2 + prob.c0_per_s * (vmax + abs(prob.v_o_m_s))
    rate = vmax / grid.dx_m + bmax / grid.dv_m_s + 2.0 * prob.D / grid.dv_m_s ** 2
    return safety / rate


def hjb_backward_step(grid: AxisGrid, prob: AxisProblem, psi_next: np.ndarray, dt_s: float,
                      extra: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """One explicit backward step of the time-dependent HJB (eq. 8; eq. 8 of the MFG with the
    interaction share in extra): psi^n = psi^{n+1} + dt min_a (Q_a psi^{n+1} + f_a).
    Returns (psi^n, a^n), each (nx, nv)."""
    a = _policy(grid, prob, psi_next)
    rates = _rates(grid, prob, a)
    return psi_next + dt_s * (_apply_Q(rates, psi_next) + _running_cost(grid, prob, a, extra)), a


def fpk_forward_step(grid: AxisGrid, prob: AxisProblem, m: np.ndarray, a: np.ndarray, dt_s: float) -> np.ndarray:
    """One explicit step of the FPK (eq. 10) as the adjoint of the HJB's generator:
    m^{n+1} = m^n + dt Q_a^T m^n. Conserves sum(m) exactly in exact arithmetic (Q's rows sum to
    0); m^{n+1} >= 0 when dt satisfies cfl_dt_s."""
    return m + dt_s * _apply_QT(_rates(grid, prob, a), m)


def deposit_cic(grid: AxisGrid, x_m: np.ndarray, v_m_s: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """Cloud-in-cell (bilinear) deposit of point masses on the grid: the smoothed empirical
    measure of Algorithm 2's m^[0](0) = 1/N sum delta_{s_i}. Points outside are clamped to the
    boundary. Returns cell masses (nx, nv) summing to sum(weights) (1/N each by default)."""
    x = np.asarray(x_m, dtype=float); v = np.asarray(v_m_s, dtype=float)
    w = np.full(x.size, 1.0 / x.size) if weights is None else np.asarray(weights, dtype=float)
    nx, nv = grid.shape
    fx = np.clip((x - grid.x_m[0]) / grid.dx_m, 0.0, nx - 1.0)
    fv = np.clip((v - grid.v_m_s[0]) / grid.dv_m_s, 0.0, nv - 1.0)
    i0 = np.minimum(np.floor(fx).astype(int), nx - 2); tx = fx - i0
    j0 = np.minimum(np.floor(fv).astype(int), nv - 2); tv = fv - j0
    m = np.zeros(grid.shape)
    for di, wx in ((0, 1 - tx), (1, tx)):
        for dj, wv in ((0, 1 - tv), (1, tv)):
            np.add.at(m, (i0 + di, j0 + dj), w * wx * wv)
    return m


def interp_bilinear(grid: AxisGrid, field_: np.ndarray, x_m: np.ndarray, v_m_s: np.ndarray) -> np.ndarray:
    """Bilinear interpolation of a grid field (nx, nv) at points (k,); points outside the grid
    take the boundary value (clamped)."""
    nx, nv = grid.shape
    fx = np.clip((np.asarray(x_m, dtype=float) - grid.x_m[0]) / grid.dx_m, 0.0, nx - 1.0)
    fv = np.clip((np.asarray(v_m_s, dtype=float) - grid.v_m_s[0]) / grid.dv_m_s, 0.0, nv - 1.0)
    i0 = np.minimum(np.floor(fx).astype(int), nx - 2); tx = fx - i0
    j0 = np.minimum(np.floor(fv).astype(int), nv - 2); tv = fv - j0
    f = field_
    return ((1 - tx) * (1 - tv) * f[i0, j0] + tx * (1 - tv) * f[i0 + 1, j0]
            + (1 - tx) * tv * f[i0, j0 + 1] + tx * tv * f[i0 + 1, j0 + 1])


# ----------------------------------------------------------------------------------------------
# the MFG fixed point (Algorithm 2)
# ----------------------------------------------------------------------------------------------
def _moments(grid: AxisGrid, m: np.ndarray) -> np.ndarray:
    """(3, nx): sum over v of m v^k, k = 0, 1, 2."""
    v = grid.v_m_s
    return np.stack([m.sum(axis=1), m @ v, m @ (v * v)])


class _Interaction:
    """c4 phi_G share of one axis (eq. 11 with the numerator split per axis), evaluated with the
    representative's other coordinate at the other marginal's mean."""

    def __init__(self, grid: AxisGrid, other: AxisGrid, cost: CostParams) -> None:
        nx = grid.x_m.size
        self.offsets = (np.arange(-(nx - 1), nx) * grid.dx_m)            # x' - x, (2nx-1,)
        self.idx = np.arange(nx)[None, :] - np.arange(nx)[:, None] + nx - 1   # [i, i'] -> offset index
        self.other_x = other.x_m
        self.v = grid.v_m_s
        self.eps, self.beta, self.c4 = cost.eps_m2, cost.beta, cost.c4

    def __call__(self, mom: np.ndarray, other_mass: np.ndarray) -> np.ndarray:
        """mom (3, nx) this axis' moments, other_mass (nx_other,) the other marginal over
        positions. Returns c4 * sum_{x', v'} m (v' - v)^2 W(x' - x), (nx, nv)."""
        ybar = float(other_mass @ self.other_x / max(other_mass.sum(), 1e-300))
        dy2 = (self.other_x - ybar) ** 2
        Wd = ((self.eps + self.offsets[:, None] ** 2 + dy2[None, :]) ** (-self.beta)) @ other_mass   # (2nx-1,)
        T = Wd[self.idx]                                                  # (nx, nx)
        C = T @ mom.T                                                     # (nx, 3): sum_i' W m_k(i')
        v = self.v[None, :]
        return self.c4 * (C[:, 2:3] - 2.0 * v * C[:, 1:2] + v * v * C[:, 0:1])


@dataclass(eq=False)
class MFGSolution:
    """The MFG solution of Algorithm 2 over a horizon of n_periods control periods.

    dpsi_dv[axis][k] (nx, nv): d psi / d v at t = k period_s (k = 0..n_periods), m[axis][k]
    (nx, nv) the mean-field marginals at the same times; change[k] the relative L1 change of
    the marginals at fixed-point iteration k (damped)."""

    grids: tuple[AxisGrid, AxisGrid]
    problems: tuple[AxisProblem, AxisProblem]
    period_s: float
    dt_s: float
    substeps: int
    dpsi_dv: list = field(default_factory=list)
    psi: list = field(default_factory=list)
    m: list = field(default_factory=list)
    change: list = field(default_factory=list)
    stationary: tuple = ()


def solve_mfg(grids: tuple[AxisGrid, AxisGrid], problems: tuple[AxisProblem, AxisProblem], cost: CostParams,
              states0_rel: np.ndarray, period_s: float, n_periods: int, K: int = 5, damping: float = 0.5,
              cfl_safety: float = 0.9, stationary=None) -> MFGSolution:
    """Algorithm 2 from the t = 0 exchange, by finite differences.

    states0_rel (N, 4): the exchanged states relative to the (common) destination. The mean
    field is a product of per-axis marginals, m^[0](0) the CIC-smoothed empirical measure.
    Horizon T = n_periods * period_s with terminal value the stationary (discounted) psi of
    the local cost; m^[0](t) is the FPK under that stationary policy. K damped fixed-point
    iterations (HJB backward with phi_G(., m^[k-1]) of eq. 11, FPK forward). Time step:
    period_s / substeps with substeps the least integer satisfying cfl_dt_s on both axes."""
    s0 = np.asarray(states0_rel, dtype=float)
    if stationary is None:
        stationary = tuple(solve_stationary_hjb(g, p) for g, p in zip(grids, problems))
    dt_cfl = min(cfl_dt_s(g, p, cfl_safety) for g, p in zip(grids, problems))
    sub = max(1, math.ceil(period_s / dt_cfl))
    dt = period_s / sub
    nsteps = n_periods * sub
    sol = MFGSolution(grids, problems, period_s, dt, sub, stationary=stationary)
    inter = (_Interaction(grids[0], grids[1], cost), _Interaction(grids[1], grids[0], cost))
    m0 = [deposit_cic(grids[0], s0[:, 0], s0[:, 2]), deposit_cic(grids[1], s0[:, 1], s0[:, 3])]

    def forward(policies):
        """FPK forward for both axes; policies[ax] callable n -> a^n. Returns moments
        (2, nsteps+1, 3, nx) and marginal snapshots at period times."""
        moms, snaps = [], []
        for ax in range(2):
            g, p = grids[ax], problems[ax]
            m = m0[ax].copy()
            mo = np.empty((nsteps + 1, 3, g.x_m.size)); sn = [m.copy()]
            mo[0] = _moments(g, m)
            for n in range(nsteps):
                m = fpk_forward_step(g, p, m, policies[ax](n), dt)
                mo[n + 1] = _moments(g, m)
                if (n + 1) % sub == 0:
                    sn.append(m.copy())
            moms.append(mo); snaps.append(sn)
        return moms, snaps

    # m^[0]: the FPK under the uncoupled stationary policy
    moms, snaps = forward([lambda n, a=st.a_m_s2: a for st in stationary])
    pol = [None, None]
    for _k in range(K):
        new_pol, psis, dpsis = [], [], []
        for ax in range(2):
            g, p = grids[ax], problems[ax]
            psi = stationary[ax].psi.copy()
            A = np.empty((nsteps,) + g.shape, dtype=np.float32)
            ps = [None] * (n_periods + 1); ps[n_periods] = psi.copy()
            for n in range(nsteps - 1, -1, -1):
                extra = inter[ax](moms[ax][n], moms[1 - ax][n][0])
                psi, a = hjb_backward_step(g, p, psi, dt, extra)
                A[n] = a
                if n % sub == 0:
                    ps[n // sub] = psi.copy()
            new_pol.append(A); psis.append(ps)
            dpsis.append([np.gradient(q, g.dv_m_s, axis=1) for q in ps])
        pol = new_pol
        new_moms, new_snaps = forward([lambda n, A=A: A[n].astype(float) for A in pol])
        num = sum(float(np.abs(new_moms[ax][:, 0] - moms[ax][:, 0]).sum()) for ax in range(2))
        den = sum(float(np.abs(moms[ax][:, 0]).sum()) for ax in range(2))
        sol.change.append(num / den)
        moms = [(1 - damping) * moms[ax] + damping * new_moms[ax] for ax in range(2)]
        snaps = [[(1 - damping) * a + damping * b for a, b in zip(snaps[ax], new_snaps[ax])] for ax in range(2)]
        sol.psi, sol.dpsi_dv = psis, dpsis
    sol.m = snaps
    return sol


# ----------------------------------------------------------------------------------------------
# projection on sigma_H (for logging the solved value as weights)
# ----------------------------------------------------------------------------------------------
def project_on_sigma_H(sigma_H: MonomialFeatures, sols, box: tuple[tuple[float, float], tuple[float, float]] | None = None
                       ) -> np.ndarray:
    """Least-squares w_H (M_H,) with w_H^T sigma_H(s) ~ sum over axes of (psi_axis(x, v) -
    psi_axis(0, 0)) on the grid nodes (optionally only |v| <= box[axis][1], x within box[axis][0]).
    sols: the two StationarySolution (x axis, y axis). sigma_H has no constant, so the value at
    the destination is subtracted first."""
    w = np.zeros(sigma_H.M)
    E = sigma_H.exponents
    for ax, (pos_dim, vel_dim) in enumerate(((0, 2), (1, 3))):
        st = sols[ax]
        X, V = st.grid.mesh()
        keep = np.ones(X.shape, dtype=bool)
        if box is not None:
            (xl, xh), vm = box[ax][0], box[ax][1]
            keep = (X >= xl) & (X <= xh) & (np.abs(V) <= vm)
        psi0 = interp_bilinear(st.grid, st.psi, np.array([0.0]), np.array([0.0]))[0]
        y = (st.psi - psi0)[keep]
        S = np.zeros((y.size, 4)); S[:, pos_dim] = X[keep]; S[:, vel_dim] = V[keep]
        cols = np.flatnonzero((E[:, pos_dim] + E[:, vel_dim]) == E.sum(axis=1))
        F = sigma_H.value(S)[:, cols]
        nrm = np.linalg.norm(F, axis=0); nrm[nrm == 0] = 1.0
        coef, *_ = np.linalg.lstsq(F / nrm, y, rcond=None)
        w[cols] = coef / nrm
    return w
