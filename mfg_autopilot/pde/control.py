"""The solved controllers: HJB control (Algorithm 1) and MFG control (Algorithm 2) acting from
the finite-difference solutions of ``mfg_autopilot.pde.solver`` behind the Controller interface
(``mfg_autopilot.paper.controllers``). Registered as modes "hjb-pde" and "mfg-pde" of the `paper`
preset. No I/O. Design and measured figures: docs/pde.md.

Action (eqs. 7, 8, 10 with SPEC erratum 1, saturated as docs/errata.md E3):

    a* = sat(-(1/(2 c3)) B^T grad psi),   B^T grad psi = (d psi_x/d v_x, d psi_y/d v_y)

with the per-axis derivatives interpolated (bilinear) from the solved grids; a state outside
a grid takes the boundary value (clamped) and is counted in ``out_of_grid``.

* HJB control (Algorithm 1, "hjb-pde"): psi_L, the stationary discounted value of the local
  cost, is solved once per bank at the first step on grids covering the bank's states and the
  destination. Neighbours heard at step t enter as a local correction: one value-iteration
  sweep from psi_L with c4 phi_G(s_{N_i}) (eq. 3, neighbours frozen, as Algorithm 1 takes them)
  charged over one control period dt gives, to first order in dt,
  psi_i = psi_L + dt c4 phi_G(s; s_{-i}(t)), hence
  B^T grad psi_i = d_v psi_L - dt c4 mean_j 2 (v_j - v) / (eps + |r_j - r|^2)^beta.
* MFG control (Algorithm 2, "mfg-pde"): at the t = 0 exchange the HJB-FPK fixed point is
  solved over a finite horizon (``PDEParams.horizon_s``) with K damped iterations from the
  smoothed empirical measure; step k uses d_v psi at t = k dt. Algorithm 2's per-step
  iterations start from the previous step's converged mean field and receive no new data
  (no communication after t = 0), so they are not repeated; past the horizon psi_L is used.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from mfg_autopilot.interface import Observation, StepInfo
from mfg_autopilot.paper.features import make_sigma_H
from mfg_autopilot.paper.model import nominal_drift, optimal_action, saturate
from mfg_autopilot.paper.params import Preset
from mfg_autopilot.pde.solver import AxisGrid, axis_problems, interp_bilinear, project_on_sigma_H, solve_mfg, solve_stationary_hjb

__all__ = ["PDEParams", "HJBPDEController", "MFGPDEController", "grids_for"]


@dataclass(frozen=True)
class PDEParams:
    """Grids and schemes of the solved controllers (units in names)."""

    dx_m: float = 2.0                 # position spacing
    dv_m_s: float = 0.5               # velocity spacing
    margin_m: float = 20.0            # grid extends this far beyond the states and the destination
    v_max_m_s: float | None = None    # None: terminal speed (a_box + c0 |v_o|)/c0 + 1 m/s, in [5, 30]
    rho_per_s: float = 1e-3           # discount of the stationary problem
    horizon_s: float = 40.0           # MFG horizon (the paper scenario arrives in ~25 s)
    damping: float = 0.5              # MFG fixed-point damping theta
    K: int | None = None              # MFG iterations (None: preset.learner.K)
    cfl_safety: float = 0.9


def grids_for(rel_states: np.ndarray, preset: Preset, pp: PDEParams) -> tuple[AxisGrid, AxisGrid]:
    """Per-axis grids covering rel_states (N, 4) (relative to the destination), the destination
    and a margin; |v| <= v_max."""
    c = preset.cost
    box = preset.learner.acc_max_m_s2 / math.sqrt(2.0)
    vmax = pp.v_max_m_s
    if vmax is None:
        vmax = float(np.clip((box + c.c0_per_s * float(np.max(np.abs(c.v_o)))) / c.c0_per_s + 1.0, 5.0, 30.0))
    vmax = max(vmax, float(np.max(np.abs(rel_states[:, 2:4]))) + 1.0)
    out = []
    for ax in range(2):
        lo = min(0.0, float(rel_states[:, ax].min())) - pp.margin_m
        hi = max(0.0, float(rel_states[:, ax].max())) + pp.margin_m
        out.append(AxisGrid.make(lo, hi, vmax, pp.dx_m, pp.dv_m_s))
    return out[0], out[1]


class _PDEBase:
    def __init__(self, preset: Preset, destination_site_m: np.ndarray, params: PDEParams | None = None) -> None:
        self.preset = preset
        self.params = params or PDEParams()
        self.destination_site_m = np.asarray(destination_site_m, dtype=float).reshape(-1, 2)
        self._dest4 = np.concatenate([self.destination_site_m, np.zeros_like(self.destination_site_m)], axis=1)
        self.sigma_H = make_sigma_H(preset.learner.state_scale)
        self.grids: tuple[AxisGrid, AxisGrid] | None = None
        self.stationary = None
        self._w_H = np.zeros(self.sigma_H.M)
        self.out_of_grid = 0            # decisions taken at a state outside a grid (clamped)
        self.solve_s = 0.0              # wall time of the solves (s)

    @property
    def n(self) -> int:
        return self.destination_site_m.shape[0]

    @property
    def destinations_m(self) -> np.ndarray:
        return self.destination_site_m

    @property
    def acc_box_m_s2(self) -> float:
        return self.preset.learner.acc_max_m_s2 / math.sqrt(2.0)

    def _solve_stationary(self, rel_states: np.ndarray) -> None:
        import time
        t = time.perf_counter()
        self.grids = grids_for(rel_states, self.preset, self.params)
        self.problems = axis_problems(self.preset.cost, rel_states[:, 0:2].mean(axis=0), self.acc_box_m_s2,
                                      self.params.rho_per_s)
        self.stationary = tuple(solve_stationary_hjb(g, p) for g, p in zip(self.grids, self.problems))
        self._dpsi_L = tuple(st.dpsi_dv() for st in self.stationary)
        self.solve_s += time.perf_counter() - t
        box = tuple(((g.x_m[0] + self.params.margin_m, g.x_m[-1] - self.params.margin_m), g.v_m_s[-1]) for g in self.grids)
        self._w_H = project_on_sigma_H(self.sigma_H, self.stationary, box)

    def _count_out(self, s_rel: np.ndarray) -> None:
        gx, gy = self.grids
        out = ((s_rel[:, 0] < gx.x_m[0]) | (s_rel[:, 0] > gx.x_m[-1]) | (s_rel[:, 1] < gy.x_m[0]) | (s_rel[:, 1] > gy.x_m[-1])
               | (np.abs(s_rel[:, 2]) > gx.v_m_s[-1]) | (np.abs(s_rel[:, 3]) > gy.v_m_s[-1]))
        self.out_of_grid += int(out.sum())

    def _grad_v(self, s_rel: np.ndarray, dpsi) -> np.ndarray:
        """B^T grad psi at s_rel (n, 4) from per-axis d_v psi grids, (n, 2)."""
        gx, gy = self.grids
        return np.stack([interp_bilinear(gx, dpsi[0], s_rel[:, 0], s_rel[:, 2]),
                         interp_bilinear(gy, dpsi[1], s_rel[:, 1], s_rel[:, 3])], axis=1)

    def _info(self, s_rel: np.ndarray, p_v: np.ndarray, mf_evals: int = 0) -> StepInfo:
        c = self.preset.cost
        grad = np.zeros((s_rel.shape[0], 4)); grad[:, 2:4] = p_v
        acc = saturate(optimal_action(grad, c.c3), self.preset.learner.acc_max_m_s2)
        scale = self.sigma_H.scale                      # R = max(0, s~^T ds~/dt) as Algorithm 3 logs it
        R = np.einsum("nd,nd->n", s_rel / scale, nominal_drift(s_rel, acc, c) / scale)
        n = s_rel.shape[0]
        return StepInfo(acc, np.ones(n, dtype=np.int64), R > 0, np.full(n, np.nan), np.full(n, mf_evals, dtype=np.int64))

    def value_rel(self, s_rel: np.ndarray, step: int | None = None) -> np.ndarray:
        """Solved value psi(s) - psi(0) (sum over axes) at states relative to the destination (n,)."""
        psis = self._psi_at(step)
        out = np.zeros(s_rel.shape[0])
        for ax, (pd, vd) in enumerate(((0, 2), (1, 3))):
            g = self.grids[ax]
            out += interp_bilinear(g, psis[ax], s_rel[:, pd], s_rel[:, vd]) - interp_bilinear(g, psis[ax], np.zeros(1), np.zeros(1))[0]
        return out

    def _psi_at(self, step):
        return tuple(st.psi for st in self.stationary)

    def weights(self) -> dict[str, np.ndarray]:
        """{"w_H": (n, 54)}: least-squares projection of the solved stationary value psi_L - psi_L(0)
        onto sigma_H over the grid region without its margin (zeros before the first solve)."""
        return {"w_H": np.tile(self._w_H, (self.n, 1))}


class HJBPDEController(_PDEBase):
    """HJB control (Algorithm 1) by finite differences, with per-step neighbour correction."""

    mode = "hjb-pde"
    uses_t0_exchange = False

    def exchange_t0(self, states, ids, own_index, sites_m) -> None:
        """HJB_d has no swarm-wide exchange."""

    def step(self, obs: Observation) -> StepInfo:
        own = np.asarray(obs.own_states, dtype=float)
        s_rel = own - self._dest4
        if self.stationary is None:
            self._solve_stationary(s_rel)
        self._count_out(s_rel)
        p_v = self._grad_v(s_rel, self._dpsi_L)
        nb = obs.neighbours
        if nb is not None and nb.states.shape[0] > 0:
            c = self.preset.cost
            me = own[nb.owner]
            dv = nb.states[:, 2:4] - me[:, 2:4]
            dr = nb.states[:, 0:2] - me[:, 0:2]
            w = (c.eps_m2 + np.sum(dr * dr, axis=1)) ** (-c.beta)
            g = -2.0 * dv * w[:, None]                              # d/dv_i of the Cucker-Smale kernel
            cnt = np.maximum(np.bincount(nb.owner, minlength=self.n), 1)
            dphi = np.stack([np.bincount(nb.owner, g[:, k], self.n) for k in range(2)], axis=1) / cnt[:, None]
            p_v = p_v + self.preset.dt_s * c.c4 * dphi
        return self._info(s_rel, p_v)


class MFGPDEController(_PDEBase):
    """MFG control (Algorithm 2) by finite differences from the t = 0 exchange."""

    mode = "mfg-pde"
    uses_t0_exchange = True

    def __init__(self, preset: Preset, destination_site_m: np.ndarray, params: PDEParams | None = None) -> None:
        super().__init__(preset, destination_site_m, params)
        self.mfg = None
        self._centre = None

    def exchange_t0(self, states, ids, own_index, sites_m) -> None:
        """Solve Algorithm 2's fixed point from all N exchanged states (N, 4). The mean field is
        held relative to the mean of the sites; each vehicle evaluates psi at its own state
        relative to its own site (exact when all share one destination, as in `paper`)."""
        import time
        states = np.asarray(states, dtype=float)
        sites = np.asarray(sites_m, dtype=float).reshape(-1, 2)
        self._centre = sites.mean(axis=0)
        rel = states - np.concatenate([self._centre, np.zeros(2)])
        self._solve_stationary(rel)
        pp = self.params
        t = time.perf_counter()
        n_periods = max(1, int(round(pp.horizon_s / self.preset.dt_s)))
        self.mfg = solve_mfg(self.grids, self.problems, self.preset.cost, rel, self.preset.dt_s, n_periods,
                             K=pp.K or self.preset.learner.K, damping=pp.damping, cfl_safety=pp.cfl_safety,
                             stationary=self.stationary)
        self.solve_s += time.perf_counter() - t

    def _dpsi_at(self, step: int):
        if step < len(self.mfg.dpsi_dv[0]):
            return (self.mfg.dpsi_dv[0][step], self.mfg.dpsi_dv[1][step])
        return self._dpsi_L

    def _psi_at(self, step):
        if step is not None and self.mfg is not None and step < len(self.mfg.psi[0]):
            return (self.mfg.psi[0][step], self.mfg.psi[1][step])
        return super()._psi_at(step)

    def step(self, obs: Observation) -> StepInfo:
        if self.mfg is None:
            raise RuntimeError("MFGPDEController.step before exchange_t0(): the t = 0 exchange has not happened")
        s_rel = np.asarray(obs.own_states, dtype=float) - self._dest4
        self._count_out(s_rel)
        return self._info(s_rel, self._grad_v(s_rel, self._dpsi_at(int(obs.step))))


