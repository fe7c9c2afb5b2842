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
axis first (:func:`slide_out_waypoints`); for groups that start as parallel bands, a common prelude spreading
them apart, then sliding along the bands out of the start region (:func:`spread_slide_waypoints`); spreading out
from the swarm's centroid first (:func:`expand_waypoints`); the prelude, then each group's shortest path around
every other group's parked places (:func:`routed_waypoints`: around their enclosing rectangles, then around their
hulls), list-scheduled if the search finds nothing
(:func:`sequential_schedule`). Everything is deterministic (groups by index, i.e. by site coordinates; bounded
search), so every UAV computes the same plan from the t = 0 exchange.

The plan either certifies a clearance (every pair of particles of different groups, for all t, at least
``clearance_m`` apart; pairs within a group at their start distance) or fails: e.g. two groups each landing on the
other's start area, which neither order separates; :func:`group_plan_for` then returns None and the controller
keeps the interacting plan (no guarantee, and the flight's metrics say so: ``plan``). Why the routed paths
complete otherwise: docs/default_controller.md, "Why routed completes".

Shapes: states (N, 4) [x_m, y_m, vx_m_s, vy_m_s]; accelerations (N, 2).
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial import cKDTree

from mfg_autopilot.guidance.planner import min_spacing_m
from mfg_autopilot.guidance.rigid_plan import TimedPlan, _duration, trapezoid
from mfg_autopilot.paper.params import CostParams

__all__ = ["GroupPlan", "group_plan_for", "plan_min_separation", "schedule_groups", "slide_out_waypoints", "expand_waypoints",
           "spread_slide_waypoints", "separating_axis"]


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
        self.pre_m, self.pre_s = np.zeros((self.G, 2)), 0.0
        self.blend = False
        self.set_waypoints([np.zeros((0, 2))] * self.G)
        self.start_s = np.zeros(self.G) if start_s is None else np.asarray(start_s, dtype=float).reshape(self.G)
        self.T = float(np.max(self.start_s + self.dur_g)) if self.G else 0.0
        self.spacing_m = float(min(min_spacing_m(self.slots_m), min_spacing_m(self.r0)))
        self.radius_m = 0.5 * self.spacing_m
        self.clearance_m = float("nan")
        self.route = "straight"                          # which paths (group_plan_for's stages)
        self.dt_s, self.cost = float(dt_s), cost
        self.v0 = S0[:, 2:4].mean(axis=0) if self.N else np.zeros(2)
        self.tau = float(wind_tau_s)
        self.k = 0
        self.rep_active = np.zeros(self.N, dtype=bool)
        self._cache: dict[int, np.ndarray] | None = None     # TimedPlan._states_at_step

    def set_waypoints(self, via_m: list[np.ndarray], prelude_m: np.ndarray | None = None,
                      blend: bool | None = None) -> None:
        """Each group's path: straight legs through its waypoints (offsets of its centroid from the start, (k, 2) each;
        none: one straight leg to the site), every leg a rest-to-rest trapezoid, flown back to back from the group's
        start time. ``prelude_m`` (G, 2): a first leg that every group flies *at once*, from t = 0, on one common time
        profile (each group's offset a fixed multiple of it), before any scheduled start: the schedule then starts at
        ``pre_s``, its end (:func:`spread_slide_waypoints`). ``blend`` (kept if None): each leg starts while the one
        before it brakes, where the path turns by at most 60 deg (:func:`_blend_overlap`): the group no longer stops at
        such a waypoint and cuts its corner a little; speed and acceleration stay within v_max and a_max."""
        if blend is not None:
            self.blend = bool(blend)
        self.via_m = [np.asarray(v, dtype=float).reshape(-1, 2) for v in via_m]
        self.pre_m = np.zeros((self.G, 2)) if prelude_m is None else np.asarray(prelude_m, dtype=float).reshape(self.G, 2)
        self._pre_len = float(np.max(np.linalg.norm(self.pre_m, axis=1))) if self.G else 0.0
        self.pre_s = _duration(self._pre_len, self.v_max, self.a_max)
        self.legs: list[list[tuple[np.ndarray, float, float]]] = []      # per group: (start offset, direction * length, duration)
        for g in range(self.G):
            pts = np.concatenate([self.pre_m[g][None, :], self.via_m[g], self.d_g[g][None, :]])
            legs = []
            for a, b in zip(pts[:-1], pts[1:]):
                length = float(np.linalg.norm(b - a))
                if length > 0.0:
                    legs.append((a, b - a, _duration(length, self.v_max, self.a_max)))
            self.legs.append(legs)
        self.leg_t0: list[list[float]] = []      # per group: each leg's start time after the group's start
        for legs in self.legs:
            t0 = [0.0]
            for prev, nxt in zip(legs[:-1], legs[1:]):
                t0.append(t0[-1] + prev[2] - (_blend_overlap(prev, nxt, self.v_max, self.a_max) if self.blend else 0.0))
            self.leg_t0.append(t0)
        self.dur_g = np.array([sum(leg[2] for leg in legs) if not self.blend else (t0[-1] + legs[-1][2] if legs else 0.0)
                               for legs, t0 in zip(self.legs, self.leg_t0)])
        if hasattr(self, "start_s"):
            self.start_s = np.maximum(self.start_s, self.pre_s)
            self.T = float(np.max(self.start_s + self.dur_g)) if self.G else 0.0

    def motion(self, g: int, t: float, t_start: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Offset, velocity and acceleration (2,) each of group g's centroid at time t when its scheduled legs start at
        t_start (>= pre_s): the common prelude until pre_s, then :meth:`group_motion`."""
        if t < self.pre_s:
            sp, sv, sa = trapezoid(self._pre_len, self.v_max, self.a_max, t)
            u = self.pre_m[g] / self._pre_len
            return sp * u, sv * u, sa * u
        return self.group_motion(g, t - t_start)

    def group_motion(self, g: int, tau: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Offset, velocity and acceleration (2,) each of group g's centroid tau seconds after its start (after the
        prelude, if any)."""
        zero = np.zeros(2)
        if tau <= 0.0 or not self.legs[g]:
            return (self.pre_m[g].copy() if tau <= 0.0 else self.d_g[g].copy()), zero, zero
        if self.blend:
            # the legs' rest-to-rest moves superposed from their start times (a leg ends its braking while the
            # next one accelerates)
            if tau >= self.dur_g[g]:
                return self.d_g[g].copy(), zero, zero
            off, vel, acc = self.legs[g][0][0].copy(), np.zeros(2), np.zeros(2)
            for (_, vec, dur), t0 in zip(self.legs[g], self.leg_t0[g]):
                t = tau - t0
                if t <= 0.0:
                    break
                if t >= dur:
                    off += vec
                    continue
                length = float(np.linalg.norm(vec))
                sp, sv, sa = trapezoid(length, self.v_max, self.a_max, t)
                u = vec / length
                off, vel, acc = off + sp * u, vel + sv * u, acc + sa * u
            return off, vel, acc
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
        return np.array([self.motion(g, t, float(self.start_s[g]))[0] for g in range(self.G)]).reshape(-1, 2)

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
        m = [self.motion(g, t, float(self.start_s[g])) for g in range(self.G)]
        off, gv, ga = (np.array([x[i] for x in m]).reshape(-1, 2) for i in range(3))
        w, wd, wdd = self._offset(t)
        pos = self.r0 + off[self.group] + w[None, :]
        vel = gv[self.group] + wd[None, :]
        acc = ga[self.group] + wdd[None, :]
        return np.concatenate([pos, vel], axis=1), acc


def _blend_overlap(leg_a: tuple, leg_b: tuple, v_max: float, a_max: float) -> float:
    """How long leg_b may start before leg_a ends (GroupPlan.set_waypoints' ``blend``): leg_a's braking and leg_b's
    acceleration phases overlap by at most the shorter of the two (the summed speed then never exceeds either leg's
    top speed, so not v_max), and only where the path turns by at most 60 deg (the summed acceleration, a_max times
    |u_b - u_a| = 2 a_max sin(turn / 2), then stays within a_max); 0 otherwise."""
    (_, va, _), (_, vb, _) = leg_a, leg_b
    la, lb = float(np.linalg.norm(va)), float(np.linalg.norm(vb))
    if la <= 0.0 or lb <= 0.0 or float(va @ vb) < 0.5 * la * lb:
        return 0.0
    ramp = lambda length: min(v_max, math.sqrt(length * a_max)) / a_max      # noqa: E731  trapezoid's t_acc
    return min(ramp(la), ramp(lb))


def _pair_min_separation(plan: GroupPlan, ga: int, gb: int, start_s: np.ndarray, cutoff_m: float,
                         min_step_s: float = 0.02, lookahead_s: float = 1.0) -> tuple[float, tuple[int, int, float] | None]:
    """Whether groups ga and gb, started at start_s[ga] and start_s[gb], ever come closer than cutoff_m: (d, where).

    Sampled with a step that cannot miss an approach: at a sample where the two groups are d >= cutoff + 2 v_max
    min_step apart (the distance of their convex hulls, a lower bound; where that is below the guard, the nearest pair:
    k-d tree of gb's start layout queried with ga's shifted points), no pair can get
    closer than cutoff before (d - cutoff) / (2 v_max) seconds (2 v_max bounds any relative speed: the common offset
    cancels), which is the next step. A sample closer than cutoff + 2 v_max min_step ends the check as a conflict
    (conservative by at most 2 v_max min_step). Before either group moves, and after both stopped, nothing changes.
    Returns (smallest sampled distance, None) if no conflict, else (that distance, (i, j, t)), i in ga, j in gb."""
    import shapely
    ia, ib = np.flatnonzero(plan.group == ga), np.flatnonzero(plan.group == gb)
    trees = plan.__dict__.setdefault("_trees", {})
    if gb not in trees:
        trees[gb] = cKDTree(plan.r0[ib])
    tree = trees[gb]
    hulls = plan.__dict__.setdefault("_hulls", {})
    for g, idx in ((ga, ia), (gb, ib)):
        if g not in hulls:
            hulls[g] = shapely.MultiPoint(plan.r0[idx]).convex_hull
    hull_a, hull_b = hulls[ga], hulls[gb]
    v_rel = 2.0 * plan.v_max
    guard = cutoff_m + v_rel * min_step_s
    ta, tb = float(start_s[ga]), float(start_s[gb])
    t = 0.0 if plan.pre_s > 0.0 else min(ta, tb)
    t_end = max(ta + plan.dur_g[ga], tb + plan.dur_g[gb])
    best = float("inf")
    while True:
        shift = plan.motion(ga, t, ta)[0] - plan.motion(gb, t, tb)[0]
        # the convex hulls' distance bounds every pair's from below and costs little: the points are queried only
        # when the hulls come within the guard
        dk = float(shapely.distance(shapely.transform(hull_a, lambda xy: xy + shift), hull_b))
        if dk < guard:
            # points farther than the bound are not resolved (the tree prunes them): all of them beyond it is a
            # distance of at least the bound
            bound = guard + v_rel * lookahead_s
            d, j = tree.query(plan.r0[ia] + shift[None, :], k=1, distance_upper_bound=bound)
            k = int(np.argmin(d))
            dk = min(float(d[k]), bound)
            if dk < guard:
                return dk, (int(ia[k]), int(ib[int(j[k])]), t)
        best = min(best, dk)
        if t >= t_end:
            return best, None
        t = min(t + max((dk - cutoff_m) / v_rel, min_step_s), t_end)


def _candidate_group_pairs(plan: GroupPlan, cutoff_m: float) -> list[tuple[int, int]]:
    """Pairs of groups whose swept areas (bounding box of the start and end layouts: a translation sweeps inside
    it) come within cutoff_m of each other: only those can ever conflict."""
    lo, hi = np.full((plan.G, 2), np.inf), np.full((plan.G, 2), -np.inf)
    layouts = [plan.r0, plan.slots_m, plan.r0 + plan.pre_m[plan.group]]
    k_max = max((len(v) for v in plan.via_m), default=0)
    for k in range(k_max):                     # every waypoint layout (a group without one: its start again)
        off = np.array([v[k] if len(v) > k else plan.pre_m[g] for g, v in enumerate(plan.via_m)])
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
    grid = plan.pre_s + np.arange(0.0, budget + 0.5 * h, h)      # scheduled legs start after the common prelude
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
            st = np.full(plan.G, plan.pre_s)
            st[a], st[b] = plan.pre_s + max(-tau, 0.0), plan.pre_s + max(tau, 0.0)
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
    start -= start.min() - plan.pre_s
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
    need = clearance_fraction * plan.spacing_m
    stages = (("straight", None), ("slide_out", slide_out_waypoints), ("spread_slide", spread_slide_waypoints),
              ("expand", expand_waypoints), ("routed", lambda p: routed_waypoints(p, need, rectangles=True)),
              ("routed_hulls", lambda p: routed_waypoints(p, need)))
    routed: list[GroupPlan] = []
    for name, via in stages:
        out = None
        if via is None:
            out = schedule_groups(plan, need, **schedule_kw)
        else:
            route = via(plan)
            if route is None:
                continue
            via_m, prelude = route if isinstance(route, tuple) else (route, None)
            plan.route = name
            # the legs blended at their shallow turns first (faster; the space-time check decides), else stopping at
            # every waypoint
            for blend in (True, False):
                plan.set_waypoints(via_m, prelude, blend=blend)
                out = schedule_groups(plan, need, **schedule_kw)
                if out is None and name.startswith("routed"):
                    out = sequential_schedule(plan, need)
                if out is not None:
                    break
        if out is not None and name.startswith("routed"):
            routed.append(out)            # both routings tried: the one that arrives first flies
        elif out is not None:
            return out
    return min(routed, key=lambda p: p.T) if routed else None


def separating_axis(plan: GroupPlan, coarse: int = 720) -> tuple[np.ndarray, np.ndarray] | None:
    """(n, order): a unit direction along which the groups' start points lie in disjoint, ordered intervals (groups
    that start as parallel bands), the groups sorted along it; None if there is none. The direction maximises the
    smallest gap between consecutive intervals: a scan of ``coarse`` directions over the groups' convex hull vertices,
    refined by a bounded scalar search around the best (the gap may be centimetres: bands cut from random points)."""
    memo = plan.__dict__.setdefault("_separating_axis", {})     # spread_slide and both routings ask for it
    if coarse not in memo:
        memo[coarse] = _separating_axis(plan, coarse)
    return memo[coarse]


def _separating_axis(plan: GroupPlan, coarse: int) -> tuple[np.ndarray, np.ndarray] | None:
    from scipy.optimize import minimize_scalar
    from scipy.spatial import ConvexHull, QhullError

    verts, lab = [], []
    for g in range(plan.G):
        pts = plan.r0[plan.group == g]
        if pts.shape[0] >= 3:
            try:
                pts = pts[ConvexHull(pts).vertices]
            except QhullError:          # collinear: every point is a hull point
                pass
        verts.append(pts)
        lab.append(np.full(pts.shape[0], g))
    V, L = np.concatenate(verts), np.concatenate(lab)

    def margin(theta: float) -> tuple[float, np.ndarray]:
        proj = V @ np.array([math.cos(theta), math.sin(theta)])
        lo = np.full(plan.G, np.inf)
        hi = np.full(plan.G, -np.inf)
        np.minimum.at(lo, L, proj)
        np.maximum.at(hi, L, proj)
        order = np.argsort(lo + hi, kind="stable")
        return float(np.min(lo[order[1:]] - hi[order[:-1]])), order

    thetas = np.arange(coarse) * (math.pi / coarse)
    scores = [margin(float(t))[0] for t in thetas]
    k = int(np.argmax(scores))
    h = math.pi / coarse
    res = minimize_scalar(lambda t: -margin(t)[0], bounds=(thetas[k] - h, thetas[k] + h), method="bounded",
                          options={"xatol": 1e-7})
    theta = float(res.x) if -res.fun > scores[k] else float(thetas[k])
    m, order = margin(theta)
    if not m > 0.0:
        return None
    return np.array([math.cos(theta), math.sin(theta)]), order


def spread_slide_waypoints(plan: GroupPlan, gap_factor: float = 2.0) -> tuple[list[np.ndarray], np.ndarray] | None:
    """For groups that start as parallel bands (:func:`separating_axis`: normal n, tangent t): a common prelude that
    spreads the bands apart along n until neighbouring bands are at least ``gap_factor`` x the spacing apart, then one
    waypoint per group: slide along +-t (towards the site's side) until clear of the whole start region, then straight to
    the site. None if the groups are not bands.

    Why it is safe while flown (the schedule checks it anyway): in the prelude every band moves along n on one common
    time profile, by amounts increasing with its rank, so two bands only move apart along the direction that already
    separates them (every pairwise distance grows); in the slide, bands moving along t keep their n-projections, so two
    bands stay at least their n-gap (>= ``gap_factor`` x spacing) apart however they slide. What is left to the schedule
    is the last legs, which start outside the start region (interlocked bands: each crossing the other's start area,
    which no waiting can order, are taken apart here)."""
    sep = separating_axis(plan)
    if sep is None:
        return None
    n, order = sep
    tan = np.array([-n[1], n[0]])
    proj = plan.r0 @ n
    lo = np.array([proj[plan.group == g].min() for g in range(plan.G)])
    hi = np.array([proj[plan.group == g].max() for g in range(plan.G)])
    need = gap_factor * plan.spacing_m
    shift = np.zeros(plan.G)
    for k in range(1, plan.G):
        gap = lo[order[k]] - hi[order[k - 1]]
        shift[order[k]] = shift[order[k - 1]] + max(0.0, need - gap)
    shift -= np.median(shift)
    pre = shift[:, None] * n[None, :]
    pt = plan.r0 @ tan
    t_lo, t_hi = float(pt.min()), float(pt.max())
    via = []
    for g in range(plan.G):
        own = pt[plan.group == g]
        side = 1.0 if float(plan.d_g[g] @ tan) >= 0.0 else -1.0
        slide = (t_hi + need - own.min()) if side > 0 else (own.max() - t_lo + need)
        via.append((pre[g] + side * slide * tan)[None, :])
    return via, pre


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


def _c_obstacle(parked: np.ndarray, shape: np.ndarray, clearance_m: float, rectangle: bool = False):
    """A polygon containing the centroid positions at which a group of start offsets ``shape`` (k, 2) comes within
    clearance_m of the parked points (m, 2): those lie in the convex hull of their Minkowski difference grown by
    clearance_m (``rectangle``: the hull's smallest enclosing rectangle, grown by clearance_m with mitred corners, which
    contains it)."""
    import shapely
    from scipy.spatial import ConvexHull, QhullError

    def hull(p: np.ndarray) -> np.ndarray:
        if p.shape[0] < 3:
            return p
        try:
            return p[ConvexHull(p).vertices]
        except QhullError:
            return p
    a, b = hull(parked), hull(-shape)
    s = (a[:, None, :] + b[None, :, :]).reshape(-1, 2)
    if rectangle:
        # the hull's smallest enclosing rectangle, grown with mitred corners: it contains the grown hull, and a path
        # around it turns at a few corners (each a stop of the rest-to-rest legs) instead of at every vertex of a hull
        return shapely.MultiPoint(s).minimum_rotated_rectangle.buffer(clearance_m, join_style="mitre")
    return shapely.MultiPoint(s).convex_hull.buffer(clearance_m, quad_segs=2)


def _visibility_route(x0: np.ndarray, x1: np.ndarray, obstacles: list, margin_m: float) -> np.ndarray | None:
    """The shortest polyline from x0 to x1 that crosses no obstacle (shapely polygons), through vertices of the
    obstacles grown by margin_m (a visibility graph, edges checked lazily by Dijkstra): its inner points (k, 2), or
    None if there is none."""
    import heapq

    import shapely
    obstacles = [o for o in obstacles if not (o.contains(shapely.Point(x0)) or o.contains(shapely.Point(x1)))]
    if not obstacles:
        return np.zeros((0, 2))
    union = shapely.union_all(obstacles)
    nodes = [np.asarray(x0, float), np.asarray(x1, float)]
    for o in obstacles:
        ring = np.asarray(o.buffer(margin_m, join_style="mitre").exterior.coords)[:-1]
        nodes.extend(ring)
    P = np.array(nodes)
    free = ~shapely.contains_xy(union, P[:, 0], P[:, 1])
    free[0] = free[1] = True
    shapely.prepare(union)
    dist = np.full(P.shape[0], np.inf)
    prev = np.full(P.shape[0], -1)
    dist[0] = 0.0
    done = np.zeros(P.shape[0], dtype=bool)
    heap = [(0.0, 0)]
    while heap:
        d, u = heapq.heappop(heap)
        if done[u]:
            continue
        done[u] = True
        if u == 1:
            break
        cand = np.flatnonzero(free & ~done)
        lines = shapely.linestrings(np.stack([np.broadcast_to(P[u], (cand.size, 2)), P[cand]], axis=1))
        ok = ~shapely.intersects(union, lines)
        for v in cand[ok]:
            nd = d + float(np.linalg.norm(P[v] - P[u]))
            if nd < dist[v]:
                dist[v], prev[v] = nd, u
                heapq.heappush(heap, (nd, int(v)))
    if not np.isfinite(dist[1]):
        return None
    path, v = [], int(prev[1])
    while v > 0:
        path.append(P[v])
        v = int(prev[v])
    return np.array(path[::-1]).reshape(-1, 2)


def routed_waypoints(plan: GroupPlan, clearance_m: float, gap_factor: float = 2.0,
                     rectangles: bool = False) -> tuple[list[np.ndarray], np.ndarray] | None:
    """Every group's path routed around every other group's parked places: for bands, the common spreading prelude of
    :func:`spread_slide_waypoints` first; then each group's shortest path (visibility graph) from there to its site
    that keeps it ``clearance_m`` (+ a margin) from every other group's start (after the prelude) and from every other
    group's slot block (``rectangles``: each obstacle its enclosing rectangle, larger but with few corners, so fewer
    stops). A place the group cannot avoid (its own site overlaps another group's start, or its start
    another's site) is left to the order of the schedule.

    Why it completes: a group flying such a path alone meets nobody (the others wait at their starts or sit at their
    sites), so flying the groups one after another is conflict-free (:func:`sequential_schedule`), and the schedule
    search may only do better. None if no such path exists for some group."""
    spread = spread_slide_waypoints(plan, gap_factor)
    pre = spread[1] if spread is not None else np.zeros((plan.G, 2))
    cen = np.array([plan.r0[plan.group == g].mean(axis=0) for g in range(plan.G)])
    margin = 0.25 * plan.spacing_m
    via = []
    for g in range(plan.G):
        shape = plan.r0[plan.group == g] - cen[g]
        obs = []
        for h in range(plan.G):
            if h != g:
                obs.append(_c_obstacle(plan.r0[plan.group == h] + pre[h], shape, clearance_m + margin, rectangles))
                obs.append(_c_obstacle(plan.slots_m[plan.group == h], shape, clearance_m + margin, rectangles))
        path = _visibility_route(cen[g] + pre[g], cen[g] + plan.d_g[g], obs, margin)
        if path is None:
            return None
        via.append(path - cen[g])
    return via, pre


def sequential_schedule(plan: GroupPlan, clearance_m: float, delay_step_s: float = 2.0) -> GroupPlan | None:
    """The groups one after another, each starting as early as it keeps clear of those before it (at the latest when
    they have all stopped), in an order that every pair allows
    (a before b: a's whole path clear of b waiting at its start, b's clear of a at its site; checked by
    :func:`_pair_min_separation`), the first allowed group by index first; checked once more as a whole. None if
    some pair allows neither order, or the pairs' orders form a cycle."""
    before = np.ones((plan.G, plan.G), dtype=bool)
    for a in range(plan.G):
        for b in range(a + 1, plan.G):
            st = np.full(plan.G, plan.pre_s)
            st[b] = plan.pre_s + plan.dur_g[a]
            before[a, b] = _pair_min_separation(plan, a, b, st, clearance_m)[1] is None
            st[a], st[b] = plan.pre_s + plan.dur_g[b], plan.pre_s
            before[b, a] = _pair_min_separation(plan, a, b, st, clearance_m)[1] is None
    left, order = list(range(plan.G)), []
    while left:
        g = next((g for g in left if all(before[g, h] for h in left if h != g)), None)
        if g is None:
            return None
        order.append(g)
        left.remove(g)
    # list scheduling in that order: each group at the earliest time on a grid of delay_step_s at which it keeps
    # clear of every group placed before it (one exists: right after all of them have stopped)
    pairs = set(_candidate_group_pairs(plan, clearance_m))
    start = np.full(plan.G, plan.pre_s)
    placed: list[int] = []
    for g in order:
        t_last = max((start[a] + plan.dur_g[a] for a in placed), default=plan.pre_s)
        t = plan.pre_s
        while True:
            if t >= t_last:
                t = t_last
            st = start.copy()
            st[g] = t
            if all(_pair_min_separation(plan, a, g, st, clearance_m)[1] is None
                   for a in placed if (min(a, g), max(a, g)) in pairs):
                break
            if t >= t_last:          # cannot happen if the order's pair checks are right
                return None
            t += delay_step_s
        start[g] = t
        placed.append(g)
    cand = plan.with_schedule(start)
    if plan_min_separation(cand, clearance_m)[1] is not None:
        return None
    cand.clearance_m = float(min(clearance_m, plan.spacing_m))
    return cand
