"""Groups as rigid translations on a time-staggered schedule, checked in space-time at t = 0.

The general case of the conflict-free plan (issue 18; docs/default_controller.md, "Separation by
construction"). When the target layout is not one rigid motion of the start (``rigid_plan.py``: a
translation of a single group, a half turn of several), every *group* (the UAVs sharing a site) still
moves rigidly: slot_j = site_g + (r_j(0) - centroid_g) (the slot rule of ``planner.slots_from_sites``),
so group g translates by d_g = site_g - centroid_g along a rest-to-rest trapezoid (v_max, a_kin_max),
starting at its own time T_g:

    r_j(t) = r_j(0) + s_g(t - T_g) u_g + w(t),   u_g = d_g / |d_g|,  s_g(tau) = 0 for tau <= 0,

w(t) the common offset of the swarm's mean start velocity (as in ``RigidPlan``: common to every
particle, it changes no distance). Pairs within a group keep their start distance for the whole
flight. Pairs of different groups are what the schedule is for: :func:`schedule_groups` starts with
every T_g = 0 and, while the space-time check (:func:`plan_min_separation`, every pair along the plan
sampled at ``check_dt_s`` with the distance between samples bounded from below) finds two groups
closer than the required clearance, delays the later-ordered of the two by ``delay_step_s``, up to a
total delay budget. The order is deterministic (by group index, i.e. by site coordinates), so every UAV
computes the same schedule from the t = 0 exchange.

The schedule either certifies a clearance (every pair of particles, for all t, at least
``clearance_m`` apart) or fails: two groups whose straight paths cross each other's parked start or
site block cannot be separated by waiting; :func:`group_plan_for` then returns None and the controller
keeps the interacting plan (no guarantee, and the flight's metrics say so).

Shapes: states (N, 4) [x_m, y_m, vx_m_s, vy_m_s]; accelerations (N, 2).
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial import cKDTree

from mfg_autopilot.guidance.planner import min_spacing_m
from mfg_autopilot.guidance.rigid_plan import _duration, trapezoid
from mfg_autopilot.paper.params import CostParams

__all__ = ["GroupPlan", "group_plan_for", "plan_min_separation", "schedule_groups"]


class GroupPlan:
    """Time-staggered rigid group translations (module docstring). Same face as ``RigidPlan``:
    ``states`` at step k, ``action()``, ``advance()``, ``slots_m``, ``group``, ``sites_m``, ``spacing_m``,
    ``N``, ``k``; plus ``start_s`` (G,) the schedule and ``clearance_m`` the certified clearance."""

    kind = "groups"

    def __init__(self, S0: np.ndarray, sites_m: np.ndarray, dt_s: float, cost: CostParams, v_max_m_s: float,
                 a_kin_max_m_s2: float, start_s: np.ndarray | None = None, wind_tau_s: float = 4.0) -> None:
        S0 = np.asarray(S0, dtype=float)
        self.N = S0.shape[0]
        self.r0 = S0[:, 0:2].copy()
        self.sites_m = np.asarray(sites_m, dtype=float).reshape(self.N, 2)
        _, grp = np.unique(self.sites_m, axis=0, return_inverse=True)
        self.group = grp.reshape(-1)
        self.G = int(self.group.max()) + 1 if self.N else 0
        cnt = np.bincount(self.group, minlength=self.G).astype(float)
        cen = np.stack([np.bincount(self.group, self.r0[:, d], self.G) for d in range(2)], axis=1) / cnt[:, None]
        site_g = np.zeros((self.G, 2))
        site_g[self.group] = self.sites_m
        self.slots_m = self.sites_m + self.r0 - cen[self.group]
        d = site_g - cen
        self.dist_g = np.linalg.norm(d, axis=1)
        self.u_g = d / np.maximum(self.dist_g, 1e-12)[:, None]
        self.v_max, self.a_max = float(v_max_m_s), float(a_kin_max_m_s2)
        self.dur_g = np.array([_duration(float(x), self.v_max, self.a_max) for x in self.dist_g])
        self.start_s = np.zeros(self.G) if start_s is None else np.asarray(start_s, dtype=float).reshape(self.G)
        self.T = float(np.max(self.start_s + self.dur_g)) if self.G else 0.0
        self.spacing_m = float(min(min_spacing_m(self.slots_m), min_spacing_m(self.r0)))
        self.radius_m = 0.5 * self.spacing_m
        self.clearance_m = float("nan")
        self.dt_s, self.cost = float(dt_s), cost
        self.v0 = S0[:, 2:4].mean(axis=0) if self.N else np.zeros(2)
        self.tau = float(wind_tau_s)
        self.k = 0
        self.rep_active = np.zeros(self.N, dtype=bool)
        self._cache: tuple[int, np.ndarray, np.ndarray] | None = None

    def with_schedule(self, start_s: np.ndarray) -> "GroupPlan":
        """The same plan with another schedule (G,)."""
        out = GroupPlan.__new__(GroupPlan)
        out.__dict__.update(self.__dict__)
        out.start_s = np.asarray(start_s, dtype=float).reshape(self.G).copy()
        out.T = float(np.max(out.start_s + self.dur_g)) if self.G else 0.0
        out.k, out._cache, out.clearance_m = 0, None, float("nan")
        return out

    def group_profile(self, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(s, s_dot, s_ddot) of every group at time t, (G,) each."""
        out = np.zeros((3, self.G))
        for g in range(self.G):
            out[:, g] = trapezoid(float(self.dist_g[g]), self.v_max, self.a_max, t - float(self.start_s[g]))
        return out[0], out[1], out[2]

    def positions_at(self, t: float) -> np.ndarray:
        """Every particle's position at time t without the common offset (it changes no distance), (N, 2)."""
        s, _, _ = self.group_profile(t)
        return self.r0 + (s[:, None] * self.u_g)[self.group]

    def _offset(self, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        e = math.exp(-t / self.tau)
        return self.v0 * t * e, self.v0 * (1.0 - t / self.tau) * e, self.v0 * (t / self.tau - 2.0) / self.tau * e

    def at(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """Every particle's state (N, 4) and kinematic acceleration (N, 2) at time t."""
        s, sd, sdd = self.group_profile(t)
        w, wd, wdd = self._offset(t)
        pos = self.r0 + (s[:, None] * self.u_g)[self.group] + w[None, :]
        vel = (sd[:, None] * self.u_g)[self.group] + wd[None, :]
        acc = (sdd[:, None] * self.u_g)[self.group] + wdd[None, :]
        return np.concatenate([pos, vel], axis=1), acc

    def _now(self) -> tuple[np.ndarray, np.ndarray]:
        if self._cache is None or self._cache[0] != self.k:
            s, a = self.at(self.k * self.dt_s)
            self._cache = (self.k, s, a)
        return self._cache[1], self._cache[2]

    @property
    def states(self) -> np.ndarray:
        return self._now()[0]

    def action(self) -> np.ndarray:
        """Kinematic acceleration plus the model's wind drag c0 (v - v_o) (eq. 9 without noise follows the plan)."""
        s, a = self._now()
        return a + self.cost.c0_per_s * (s[:, 2:4] - self.cost.v_o[None, :])

    def advance(self) -> None:
        self.k += 1


def _segment_min_dist(d0: np.ndarray, d1: np.ndarray) -> np.ndarray:
    """Smallest |d0 + s (d1 - d0)| over s in [0, 1], per row. (p, 2) -> (p,)."""
    e = d1 - d0
    ee = np.einsum("pd,pd->p", e, e)
    s = np.clip(-np.einsum("pd,pd->p", d0, e) / np.maximum(ee, 1e-300), 0.0, 1.0)
    return np.linalg.norm(d0 + s[:, None] * e, axis=1)


def _pair_min_separation(plan: GroupPlan, ga: int, gb: int, start_s: np.ndarray, check_dt_s: float, cutoff_m: float
                         ) -> tuple[float, tuple[int, int, float] | None]:
    """:func:`plan_min_separation` restricted to the particles of groups ga and gb under the schedule start_s."""
    ia, ib = np.flatnonzero(plan.group == ga), np.flatnonzero(plan.group == gb)
    idx = np.concatenate([ia, ib])
    in_a = np.zeros(idx.size, dtype=bool)
    in_a[:ia.size] = True
    r0 = plan.r0[idx]
    shift = np.where(in_a[:, None], plan.u_g[ga][None, :], plan.u_g[gb][None, :])
    t_lo = min(start_s[ga], start_s[gb])
    t_hi = max(start_s[ga] + plan.dur_g[ga], start_s[gb] + plan.dur_g[gb])
    h = float(check_dt_s)
    n_int = max(1, int(math.ceil((t_hi - t_lo) / h)))

    def pos(t: float) -> np.ndarray:
        sa = trapezoid(float(plan.dist_g[ga]), plan.v_max, plan.a_max, t - float(start_s[ga]))[0]
        sb = trapezoid(float(plan.dist_g[gb]), plan.v_max, plan.a_max, t - float(start_s[gb]))[0]
        return r0 + shift * np.where(in_a, sa, sb)[:, None]

    best, where = float("inf"), None
    p0 = pos(t_lo)
    for m in range(n_int):
        t0 = t_lo + m * h
        p1 = pos(t0 + h)
        step = float(np.max(np.linalg.norm(p1 - p0, axis=1)))
        pairs = cKDTree(p0).query_pairs(cutoff_m + 2.0 * step, output_type="ndarray")
        if pairs.size:
            pairs = pairs[in_a[pairs[:, 0]] != in_a[pairs[:, 1]]]
        if pairs.size:
            dmin = _segment_min_dist(p0[pairs[:, 1]] - p0[pairs[:, 0]], p1[pairs[:, 1]] - p1[pairs[:, 0]])
            k = int(np.argmin(dmin))
            if dmin[k] < best:
                best, where = float(dmin[k]), (int(idx[pairs[k, 0]]), int(idx[pairs[k, 1]]), t0)
        p0 = p1
    return best, where


def _candidate_group_pairs(plan: GroupPlan, cutoff_m: float) -> list[tuple[int, int]]:
    """Pairs of groups whose swept areas (bounding box of the start and end layouts: a translation sweeps inside
    it) come within cutoff_m of each other: only those can ever conflict."""
    lo, hi = np.full((plan.G, 2), np.inf), np.full((plan.G, 2), -np.inf)
    for pts in (plan.r0, plan.slots_m):
        for d in range(2):
            np.minimum.at(lo[:, d], plan.group, pts[:, d])
            np.maximum.at(hi[:, d], plan.group, pts[:, d])
    out = []
    for a in range(plan.G):
        for b in range(a + 1, plan.G):
            if np.all(lo[a] - cutoff_m <= hi[b]) and np.all(lo[b] - cutoff_m <= hi[a]):
                out.append((a, b))
    return out


def plan_min_separation(plan: GroupPlan, check_dt_s: float, cutoff_m: float, _memo: dict | None = None
                        ) -> tuple[float, tuple[int, int, float] | None]:
    """The smallest distance between two particles of *different* groups over the whole plan, (d_min, (i, j, t))
    with t the start of the sample interval, or (inf, None) if no such pair comes within ``cutoff_m``.

    Only pairs of groups whose swept areas come within cutoff_m are checked, each over the time either of the
    two moves. Positions are sampled every ``check_dt_s``; between two samples a pair's relative position is
    taken as the straight segment joining them. The true path differs from that chord by at most a_rel h^2 / 8
    (|relative acceleration| <= 2 a_kin_max, h = check_dt_s), which :func:`schedule_groups` adds to its
    clearance. Pairs are found per interval with a k-d tree within cutoff_m + twice the largest particle
    displacement over the interval (no pair closer than cutoff_m is missed). ``_memo`` caches a pair of groups'
    result by their start times (the schedule search re-checks the pairs it did not change)."""
    if plan.N < 2 or plan.G < 2:
        return float("inf"), None
    best, where = float("inf"), None
    for ga, gb in _candidate_group_pairs(plan, cutoff_m):
        key = (ga, gb, float(plan.start_s[ga]), float(plan.start_s[gb]), cutoff_m)
        if _memo is not None and key in _memo:
            d, w = _memo[key]
        else:
            d, w = _pair_min_separation(plan, ga, gb, plan.start_s, check_dt_s, cutoff_m)
            if _memo is not None:
                _memo[key] = (d, w)
        if d < best:
            best, where = d, w
    return best, where


def schedule_groups(plan: GroupPlan, clearance_m: float, check_dt_s: float = 0.25, delay_step_s: float = 2.0,
                    max_delay_s: float | None = None, max_rounds: int = 60) -> GroupPlan | None:
    """A schedule under which particles of different groups stay ``clearance_m`` apart (plus the chord margin
    of :func:`plan_min_separation`) for the whole plan, or None (module docstring). Deterministic."""
    a_rel = 2.0 * plan.a_max
    need = clearance_m + a_rel * check_dt_s ** 2 / 8.0
    budget = float(max_delay_s) if max_delay_s is not None else 2.0 * float(np.max(plan.dur_g, initial=0.0)) + 10.0
    start = plan.start_s.copy()
    seen: set[tuple] = set()
    memo: dict = {}
    for _ in range(max_rounds):
        cand = plan.with_schedule(start)
        d, where = plan_min_separation(cand, check_dt_s, need, memo)
        if where is None or d >= need:
            # pairs the check did not list are at least `need` apart: the certificate is min(d, need, spacing)
            cand.clearance_m = float(min(d, need, plan.spacing_m)) - a_rel * check_dt_s ** 2 / 8.0
            return cand
        ga, gb = int(plan.group[where[0]]), int(plan.group[where[1]])
        t = where[2]
        parked = [t < start[g] for g in (ga, gb)]                      # still at its start at the conflict
        done = [t >= start[g] + plan.dur_g[g] for g in (ga, gb)]        # already at its site
        if parked[0] != parked[1]:
            # one crosses the other's start area: the parked one goes first (it leaves, then the other passes)
            first, other = (ga, gb) if parked[0] else (gb, ga)
            if start[first] > 0.0:
                start[first] = max(0.0, start[first] - delay_step_s)
            else:
                start[other] += delay_step_s
            late = other
        elif done[0] != done[1]:
            # one crosses the other's site block: the mover must pass before the other arrives
            mover, fixed = (gb, ga) if done[0] else (ga, gb)
            if start[mover] > 0.0:
                start[mover] = max(0.0, start[mover] - delay_step_s)
            else:
                start[fixed] += delay_step_s
            late = fixed
        else:
            # both moving: delay the one whose delay opens the gap more (one step ahead; ties to the higher index)
            best_d, late = -1.0, max(ga, gb)
            for g in (max(ga, gb), min(ga, gb)):
                trial = start.copy()
                trial[g] += delay_step_s
                d_g, _ = plan_min_separation(plan.with_schedule(trial), check_dt_s, need, memo)
                if d_g > best_d:
                    best_d, late = d_g, g
            start[late] += delay_step_s
        key = tuple(np.round(start, 6))
        if start[late] > budget or key in seen:
            return None
        seen.add(key)
    return None


def group_plan_for(S0: np.ndarray, sites_m: np.ndarray, dt_s: float, cost: CostParams, v_max_m_s: float,
                   a_kin_max_m_s2: float, clearance_fraction: float = 0.5, **schedule_kw) -> GroupPlan | None:
    """The scheduled group plan of the t = 0 exchange certified to keep particles of different groups at least
    ``clearance_fraction`` x the smallest start/slot spacing apart, or None if the schedule fails."""
    S0 = np.asarray(S0, dtype=float)
    if S0.shape[0] < 2:
        return None
    plan = GroupPlan(S0, sites_m, dt_s, cost, v_max_m_s, a_kin_max_m_s2)
    if plan.G < 2 or not np.isfinite(plan.spacing_m) or plan.spacing_m <= 0:
        return None            # one group: its rigid translation is rigid_plan's (DefaultPreset.rigid_translation)
    return schedule_groups(plan, clearance_fraction * plan.spacing_m, **schedule_kw)
