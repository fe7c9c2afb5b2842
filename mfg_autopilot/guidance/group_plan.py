"""Groups as rigid translations on a time-staggered schedule, checked in space-time at t = 0.

The general case of the conflict-free plan (issue 18; docs/default_controller.md, "Separation by
construction"). When the target layout is not one rigid motion of the start (``rigid_plan.py``: a
translation of a single group, a half turn of several), every *group* (the UAVs sharing a site) still
moves rigidly: slot_j = site_g + (r_j(0) - centroid_g) (the slot rule of ``planner.slots_from_sites``),
so group g's centroid flies from its start to its site along straight legs (one, or two through a waypoint),
each leg a rest-to-rest trapezoid (v_max, a_kin_max), from its own start time T_g:

    r_j(t) = r_j(0) + o_g(t - T_g) + w(t),   o_g(tau) = 0 for tau <= 0, o_g = site_g - centroid_g at the end,

w(t) the common offset of the swarm's mean start velocity (as in ``RigidPlan``: common to every
particle, it changes no distance). Pairs within a group keep their start distance for the whole
flight. Pairs of different groups are what the schedule is for. Two groups' separation depends only on
their start offset T_b - T_a; :func:`schedule_groups` searches start times on a grid by backtracking, each
pair checked in space-time (:func:`_pair_min_separation`: sampled with steps that cannot miss an
approach, so the clearance holds between samples too), and checks the plan found once more as a whole.
Paths tried, in order (:func:`group_plan_for`): straight to the site; sliding out along the group's long
axis first (:func:`slide_out_waypoints`); spreading out from the swarm's centroid first
(:func:`expand_waypoints`). Everything is deterministic (groups by index, i.e. by site coordinates;
bounded search), so every UAV computes the same plan from the t = 0 exchange.

The plan either certifies a clearance (every pair of particles of different groups, for all t, at least
``clearance_m`` apart; pairs within a group at their start distance) or fails: two groups each of which
must cross the other's parked start area or site block cannot be separated by waiting;
:func:`group_plan_for` then returns None and the controller keeps the interacting plan (no guarantee,
and the flight's metrics say so: ``plan``).

Shapes: states (N, 4) [x_m, y_m, vx_m_s, vy_m_s]; accelerations (N, 2).
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial import cKDTree

from mfg_autopilot.guidance.planner import min_spacing_m
from mfg_autopilot.guidance.rigid_plan import TimedPlan, _duration, trapezoid
from mfg_autopilot.paper.params import CostParams

__all__ = ["GroupPlan", "group_plan_for", "plan_min_separation", "schedule_groups", "slide_out_waypoints", "expand_waypoints"]


class GroupPlan(TimedPlan):
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
        self.d_g = site_g - cen                          # each group's whole displacement (G, 2)
        self.v_max, self.a_max = float(v_max_m_s), float(a_kin_max_m_s2)
        self.set_waypoints([np.zeros((0, 2))] * self.G)
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

    def set_waypoints(self, via_m: list[np.ndarray]) -> None:
        """Each group's path: straight legs through its waypoints (offsets of its centroid from the start, (k, 2) each;
        none: one straight leg to the site), every leg a rest-to-rest trapezoid, flown back to back."""
        self.via_m = [np.asarray(v, dtype=float).reshape(-1, 2) for v in via_m]
        self.legs: list[list[tuple[np.ndarray, float, float]]] = []      # per group: (start offset, direction * length, duration)
        for g in range(self.G):
            pts = np.concatenate([np.zeros((1, 2)), self.via_m[g], self.d_g[g][None, :]])
            legs = []
            for a, b in zip(pts[:-1], pts[1:]):
                length = float(np.linalg.norm(b - a))
                if length > 0.0:
                    legs.append((a, b - a, _duration(length, self.v_max, self.a_max)))
            self.legs.append(legs)
        self.dur_g = np.array([sum(leg[2] for leg in legs) for legs in self.legs])
        if hasattr(self, "start_s"):
            self.T = float(np.max(self.start_s + self.dur_g)) if self.G else 0.0

    def group_motion(self, g: int, tau: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Offset, velocity and acceleration (2,) each of group g's centroid tau seconds after its start."""
        zero = np.zeros(2)
        if tau <= 0.0 or not self.legs[g]:
            return zero, zero, zero
        for a, vec, dur in self.legs[g]:
            if tau < dur:
                length = float(np.linalg.norm(vec))
                sp, sv, sa = trapezoid(length, self.v_max, self.a_max, tau)
                u = vec / length
                return a + sp * u, sv * u, sa * u
            tau -= dur
        return self.d_g[g].copy(), zero, zero

    def offsets_at(self, t: float) -> np.ndarray:
        """Each group's centroid offset from its start at time t, (G, 2)."""
        return np.array([self.group_motion(g, t - float(self.start_s[g]))[0] for g in range(self.G)]).reshape(-1, 2)

    def with_schedule(self, start_s: np.ndarray) -> "GroupPlan":
        """The same plan with another schedule (G,)."""
        out = GroupPlan.__new__(GroupPlan)
        out.__dict__.update(self.__dict__)
        out.start_s = np.asarray(start_s, dtype=float).reshape(self.G).copy()
        out.T = float(np.max(out.start_s + self.dur_g)) if self.G else 0.0
        out.k, out._cache, out.clearance_m = 0, None, float("nan")
        return out

    def positions_at(self, t: float) -> np.ndarray:
        """Every particle's position at time t without the common offset (it changes no distance), (N, 2)."""
        return self.r0 + self.offsets_at(t)[self.group]

    def at(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """Every particle's state (N, 4) and kinematic acceleration (N, 2) at time t."""
        m = [self.group_motion(g, t - float(self.start_s[g])) for g in range(self.G)]
        off, gv, ga = (np.array([x[i] for x in m]).reshape(-1, 2) for i in range(3))
        w, wd, wdd = self._offset(t)
        pos = self.r0 + off[self.group] + w[None, :]
        vel = gv[self.group] + wd[None, :]
        acc = ga[self.group] + wdd[None, :]
        return np.concatenate([pos, vel], axis=1), acc


def _pair_min_separation(plan: GroupPlan, ga: int, gb: int, start_s: np.ndarray, cutoff_m: float,
                         min_step_s: float = 0.02) -> tuple[float, tuple[int, int, float] | None]:
    """Whether groups ga and gb, started at start_s[ga] and start_s[gb], ever come closer than cutoff_m: (d, where).

    Sampled with a step that cannot miss an approach: at a sample where the two groups are d >= cutoff + 2 v_max
    min_step apart (nearest pair, k-d tree of gb's start layout queried with ga's shifted points), no pair can get
    closer than cutoff before (d - cutoff) / (2 v_max) seconds (2 v_max bounds any relative speed: the common offset
    cancels), which is the next step. A sample closer than cutoff + 2 v_max min_step ends the check as a conflict
    (conservative by at most 2 v_max min_step). Before either group moves, and after both stopped, nothing changes.
    Returns (smallest sampled distance, None) if no conflict, else (that distance, (i, j, t)), i in ga, j in gb."""
    ia, ib = np.flatnonzero(plan.group == ga), np.flatnonzero(plan.group == gb)
    trees = plan.__dict__.setdefault("_trees", {})
    if gb not in trees:
        trees[gb] = cKDTree(plan.r0[ib])
    tree = trees[gb]
    v_rel = 2.0 * plan.v_max
    guard = cutoff_m + v_rel * min_step_s
    ta, tb = float(start_s[ga]), float(start_s[gb])
    t = min(ta, tb)
    t_end = max(ta + plan.dur_g[ga], tb + plan.dur_g[gb])
    best = float("inf")
    while True:
        shift = plan.group_motion(ga, t - ta)[0] - plan.group_motion(gb, t - tb)[0]
        d, j = tree.query(plan.r0[ia] + shift[None, :], k=1)
        k = int(np.argmin(d))
        dk = float(d[k])
        best = min(best, dk)
        if dk < guard:
            return dk, (int(ia[k]), int(ib[int(j[k])]), t)
        if t >= t_end:
            return best, None
        t = min(t + max((dk - cutoff_m) / v_rel, min_step_s), t_end)


def _candidate_group_pairs(plan: GroupPlan, cutoff_m: float) -> list[tuple[int, int]]:
    """Pairs of groups whose swept areas (bounding box of the start and end layouts: a translation sweeps inside
    it) come within cutoff_m of each other: only those can ever conflict."""
    lo, hi = np.full((plan.G, 2), np.inf), np.full((plan.G, 2), -np.inf)
    layouts = [plan.r0, plan.slots_m]
    k_max = max((len(v) for v in plan.via_m), default=0)
    for k in range(k_max):                     # every waypoint layout (a group without one: its start again)
        off = np.array([v[k] if len(v) > k else np.zeros(2) for v in plan.via_m])
        layouts.append(plan.r0 + off[plan.group])
    for pts in layouts:
        for d in range(2):
            np.minimum.at(lo[:, d], plan.group, pts[:, d])
            np.maximum.at(hi[:, d], plan.group, pts[:, d])
    out = []
    for a in range(plan.G):
        for b in range(a + 1, plan.G):
            if np.all(lo[a] - cutoff_m <= hi[b]) and np.all(lo[b] - cutoff_m <= hi[a]):
                out.append((a, b))
    return out


def plan_min_separation(plan: GroupPlan, cutoff_m: float) -> tuple[float, tuple[int, int, float] | None]:
    """Whether particles of different groups ever come closer than cutoff_m in the whole plan: (d, None) if not (d the
    smallest distance sampled, >= cutoff_m; between samples too, see :func:`_pair_min_separation`), else (d, (i, j, t))
    for the first pair of groups found in conflict. Only pairs of groups whose swept areas come within cutoff_m are
    checked (:func:`_candidate_group_pairs`)."""
    if plan.N < 2 or plan.G < 2:
        return float("inf"), None
    best = float("inf")
    for ga, gb in _candidate_group_pairs(plan, cutoff_m):
        d, where = _pair_min_separation(plan, ga, gb, plan.start_s, cutoff_m)
        if where is not None:
            return d, where
        best = min(best, d)
    return best, None


def schedule_groups(plan: GroupPlan, clearance_m: float, delay_step_s: float = 2.0,
                    max_delay_s: float | None = None, max_pair_checks: int = 400,
                    max_nodes: int = 20000) -> GroupPlan | None:
    """A schedule under which particles of different groups stay ``clearance_m`` apart for the whole plan, or None.
    Deterministic (every UAV finds the same).

    Two groups' separation depends only on their start offset tau = T_b - T_a, and only for tau inside
    (-dur_b, dur_a): beyond it one group has finished (or not begun) before the other moves, and every larger
    offset looks the same. The start times are searched on a grid of ``delay_step_s`` in [0, max_delay_s] by
    depth-first backtracking (groups by index, earliest time first), each pair's feasibility at an offset
    computed once (:func:`_pair_min_separation`) and at most ``max_pair_checks`` times in all, the search
    visiting at most ``max_nodes`` (group, start time) choices; the schedule found
    is shifted so that the earliest group starts at 0 and checked once more as a whole."""
    need = float(clearance_m)
    h = float(delay_step_s)
    budget = float(max_delay_s) if max_delay_s is not None else float(np.sum(plan.dur_g)) + h
    grid = np.arange(0.0, budget + 0.5 * h, h)
    pairs = _candidate_group_pairs(plan, need)
    partners: list[list[int]] = [[] for _ in range(plan.G)]
    for a, b in pairs:
        partners[b].append(a)                    # b > a: checked when b is placed, a already is
    memo: dict[tuple[int, int, float], bool] = {}
    checks = [0, 0]                              # pair checks computed, search nodes visited

    def ok(a: int, b: int, ta: float, tb: float) -> bool:
        tau = tb - ta
        hi = math.ceil(plan.dur_g[a] / h) * h + h      # b starts after a has stopped: all alike
        lo = -(math.ceil(plan.dur_g[b] / h) * h + h)
        tau = float(min(max(tau, lo), hi))
        key = (a, b, tau)
        if key not in memo:
            if checks[0] >= max_pair_checks:
                raise _SearchExhausted
            checks[0] += 1
            st = np.zeros(plan.G)
            st[a], st[b] = max(-tau, 0.0), max(tau, 0.0)
            memo[key] = _pair_min_separation(plan, a, b, st, need)[1] is None
        return memo[key]

    start = np.zeros(plan.G)

    def place(g: int) -> bool:
        if g == plan.G:
            return True
        for t in grid:
            checks[1] += 1
            if checks[1] > max_nodes:
                raise _SearchExhausted
            if all(ok(a, g, start[a], t) for a in partners[g]):
                start[g] = t
                if place(g + 1):
                    return True
        return False

    try:
        found = place(0)
    except _SearchExhausted:
        found = False
    if not found:
        return None
    start -= start.min()
    cand = plan.with_schedule(start)
    if plan_min_separation(cand, need)[1] is not None:   # cannot happen if the pair checks are right; refuse rather than trust
        return None
    cand.clearance_m = float(min(need, plan.spacing_m))
    return cand


class _SearchExhausted(Exception):
    pass


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
    for via in (None, slide_out_waypoints, expand_waypoints):
        if via is not None:
            plan.set_waypoints(via(plan))
        out = schedule_groups(plan, clearance_fraction * plan.spacing_m, **schedule_kw)
        if out is not None:
            return out
    return None


def expand_waypoints(plan: GroupPlan, factor: float = 3.0) -> list[np.ndarray]:
    """One waypoint per group: its centroid moved away from the swarm's centroid C to C + factor (c_g - C) (the
    groups spread out as in a homothety, each keeping its shape), then straight to the site. Groups side by side
    move apart along the line between them, so none crosses another while spreading; the second legs come in from
    outside the start region."""
    cen = np.array([plan.r0[plan.group == g].mean(axis=0) for g in range(plan.G)])
    C = plan.r0.mean(axis=0)
    return [((factor - 1.0) * (cen[g] - C))[None, :] for g in range(plan.G)]


def slide_out_waypoints(plan: GroupPlan) -> list[np.ndarray]:
    """One waypoint per group: slide along the group's long axis (the principal axis of its start points), towards its
    site's side, until the group is clear of every start point of the swarm, then fly straight to the site. Groups that
    start side by side (bands) slide parallel to each other, so none crosses another's start area; the second legs start
    outside the start region, where waiting can separate them (:func:`schedule_groups`)."""
    out = []
    for g in range(plan.G):
        pts = plan.r0[plan.group == g]
        c = pts.mean(axis=0)
        if pts.shape[0] > 1:
            cov = np.cov((pts - c).T)
            w, v = np.linalg.eigh(cov)
            axis = v[:, int(np.argmax(w))]
        else:
            axis = np.array([1.0, 0.0])
        if float(axis @ plan.d_g[g]) < 0.0 or (float(axis @ plan.d_g[g]) == 0.0 and axis[0] + axis[1] < 0):
            axis = -axis
        lead = float(np.max((plan.r0 - c) @ axis))             # the swarm's start region ahead of the group's centroid
        trail = float(np.max((c - pts) @ axis))                # the group's own extent behind its centroid
        out.append((lead + trail + 2.0 * plan.spacing_m) * axis[None, :])
    return out
