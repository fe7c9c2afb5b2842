"""A mean-field plan that is conflict-free by construction: the whole swarm as one rigid body.

A rigid motion keeps every pairwise distance. When the swarm's target layout is an isometry of its
start layout, the plan that moves every particle by that isometry along a smooth profile keeps
every pair exactly as far apart as it started, for the whole flight (issue 18; docs/default_controller.md,
"Separation by construction"). Two isometries are recognised from the t = 0 exchange (every UAV
computes the same answer from the same inputs):

- **translation**: one group (every UAV shares a site): slot_j = site + (r_j(0) - centroid), the
  swarm translates along the straight line from its centroid to the site (``paper``, ``dense``);
- **half turn**: several groups whose sites satisfy site_g + centroid_g = 2 c for one centre c
  (``crossing``, ``swap4``, ``circle``): with the slot rule slot_j = site_g - (r_j(0) - centroid_g)
  the target layout is the start layout turned by pi about c, and the swarm turns about c
  (counter-clockwise).

Otherwise :func:`rigid_plan_for` returns None and the controller keeps the interacting plan
(``planner.MeanFieldPlan``).

Kinematics: position r_j(t) = c + R(theta(t)) (r_j(0) - c) + w(t) for the turn, r_j(0) + s(t) u + w(t)
for the translation; theta and s follow trapezoidal profiles limited by v_max and a_kin_max at the
particle farthest from c; w(t) = v0 t exp(-t / tau) is a *common* offset that starts at the swarm's mean
exchanged velocity v0 (the wind's) and returns to 0 (a common offset keeps the plan rigid). Each
vehicle's own start velocity beyond v0 is left to the tracking controller (a version that put it into
the plan, decaying, let pairs of particles approach and measured worse: 5 collided pairs in `dense`
N = 300 against 0). The action of particle j is the kinematic acceleration plus the model's wind drag,
a_j = a_kin,j + c0 (v_j - v_o) (eq. 9), held over the control period like ``MeanFieldPlan``'s.

Spread in cruise (``cruise_spacing_m``): the translation scales about its centroid, r_j(0) + s u + w + lambda(t)
(r_j(0) - c0); the half turn scales each group about its own centroid, c + R(theta) ((cen_g - c) + (1 + lambda(t))
e_j) + w, e_j = r_j(0) - cen_g, where a disc certificate at t = 0 shows the groups keep one spacing apart
(``_init_group_offsets``). lambda rises on a rest-to-rest profile from t = 0 and returns to 0 by T: distances inside
a group only grow, then return (docs/default_controller.md, "Room behind every UAV").

Shapes: states (N, 4) [x_m, y_m, vx_m_s, vy_m_s]; accelerations (N, 2).
"""

from __future__ import annotations

import math

import numpy as np

from mfg_autopilot.guidance.planner import min_spacing_m
from mfg_autopilot.paper.params import CostParams

__all__ = ["TimedPlan", "RigidPlan", "rigid_plan_for", "trapezoid"]


def trapezoid(distance: float, v_max: float, a_max: float, t: float) -> tuple[float, float, float]:
    """(position, velocity, acceleration) at time t of a rest-to-rest move over ``distance`` with speed
    and acceleration limits (triangular when the distance is too short to reach v_max)."""
    if distance <= 0.0:
        return 0.0, 0.0, 0.0
    v = min(v_max, math.sqrt(distance * a_max))
    t_acc = v / a_max
    t_cruise = (distance - v * t_acc) / v
    t_end = 2.0 * t_acc + t_cruise
    if t <= 0.0:
        return 0.0, 0.0, 0.0
    if t < t_acc:
        return 0.5 * a_max * t * t, a_max * t, a_max
    if t < t_acc + t_cruise:
        return 0.5 * v * t_acc + v * (t - t_acc), v, 0.0
    if t < t_end:
        tr = t_end - t
        return distance - 0.5 * a_max * tr * tr, a_max * tr, -a_max
    return distance, 0.0, 0.0


def _duration(distance: float, v_max: float, a_max: float) -> float:
    if distance <= 0.0:
        return 0.0
    v = min(v_max, math.sqrt(distance * a_max))
    return 2.0 * v / a_max + (distance - v * v / a_max) / v


def _distance_within(duration_s: float, v_max: float, a_max: float) -> float:
    """The longest rest-to-rest move (``trapezoid``) that takes at most duration_s: the inverse of _duration."""
    if duration_s <= 0.0:
        return 0.0
    if duration_s <= 2.0 * v_max / a_max:                  # triangular: d = a (T/2)^2
        return a_max * (0.5 * duration_s) ** 2
    return v_max * (duration_s - v_max / a_max)            # cruise at v_max: T = d / v + v / a


class TimedPlan:
    """What a plan given in closed form of time shares (``RigidPlan``, ``group_plan.GroupPlan``): the common offset
    w(t) of the swarm's mean start velocity, the state at step k (computed once per step), the command and the step
    counter. A subclass sets r0-independent fields ``v0`` (2,), ``tau``, ``dt_s``, ``cost``, ``k`` = 0,
    ``_cache`` = None and defines ``at(t) -> (states (N, 4), kinematic acceleration (N, 2))``."""

    def _offset(self, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The common offset w(t), its rate and acceleration, (2,) each: the swarm's mean start velocity v0
        (the wind's), decaying with tau (common to every particle: the plan stays rigid)."""
        tau = self.tau
        e = math.exp(-t / tau)
        return self.v0 * t * e, self.v0 * (1.0 - t / tau) * e, self.v0 * (t / tau - 2.0) / tau * e

    def at(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        raise NotImplementedError

    def _states_at_step(self, k: int) -> np.ndarray:
        """Plan states at step k (N, 4), computed once: the step before's k + 1 is this step's k."""
        cache = self._cache if self._cache is not None else {}
        if k not in cache:
            cache = {j: v for j, v in cache.items() if j >= k - 1}
            cache[k] = self.at(k * self.dt_s)[0]
            self._cache = cache
        return cache[k]

    def _now(self) -> tuple[np.ndarray, np.ndarray]:
        """(states at step k, the kinematic acceleration held over [t_k, t_k+1]: (v(t_k+1) - v(t_k)) / dt)."""
        s, s1 = self._states_at_step(self.k), self._states_at_step(self.k + 1)
        return s, (s1[:, 2:4] - s[:, 2:4]) / self.dt_s

    @property
    def states(self) -> np.ndarray:
        """Plan states at step k, (N, 4)."""
        return self._states_at_step(self.k)

    def action(self) -> np.ndarray:
        """The plan's command at step k (N, 2), held over [t_k, t_k+1] (the autopilot's zero-order hold): the mean
        kinematic acceleration over that step (the instantaneous one at t_k would miss every phase change inside a
        step: at t = 0 a trapezoid's acceleration is 0, its velocity at t_1 a_max dt) plus the model's wind drag
        c0 (v - v_o) at the step's mean velocity, so that eq. 9 without noise follows the plan's samples to second
        order."""
        s, s1 = self._states_at_step(self.k), self._states_at_step(self.k + 1)
        v, v1 = s[:, 2:4], s1[:, 2:4]
        return (v1 - v) / self.dt_s + self.cost.c0_per_s * (0.5 * (v + v1) - self.cost.v_o[None, :])

    def advance(self) -> None:
        self.k += 1


class RigidPlan(TimedPlan):
    """The rigid-motion plan (module docstring). Same face as ``MeanFieldPlan``: ``states`` at step k,
    ``action()``, ``advance()``, ``slots_m``, ``group``, ``sites_m``, ``spacing_m``, ``N``, ``k``."""

    kind: str

    def __init__(self, S0: np.ndarray, sites_m: np.ndarray, group: np.ndarray, slots_m: np.ndarray, kind: str,
                 centre_m: np.ndarray, dt_s: float, cost: CostParams, v_max_m_s: float, a_kin_max_m_s2: float,
                 wind_tau_s: float = 4.0, cruise_spacing_m: float = 0.0, spread_v_max_m_s: float = 3.0) -> None:
        self.N = S0.shape[0]
        self.kind = kind
        self.r0 = S0[:, 0:2].copy()
        self.sites_m, self.group, self.slots_m = sites_m, group, slots_m
        self.spacing_m = float(min(min_spacing_m(self.slots_m), min_spacing_m(self.r0)))
        self.radius_m = 0.5 * self.spacing_m
        self.c = np.asarray(centre_m, dtype=float)
        self.dt_s, self.cost = float(dt_s), cost
        self.v0 = S0[:, 2:4].mean(axis=0) if self.N else np.zeros(2)
        self.spread_D_m, self.T_spread, self.cruise_scale = 0.0, 0.0, 1.0      # no spread (a translation may set one)
        self.tau = float(wind_tau_s)

        if kind == "turn":
            lam_c = self._init_group_offsets(cruise_spacing_m)
            d = self.r0 - self.c[None, :]
            # the farthest particle from c over the flight: |d + lambda e| is convex in lambda, so at lambda 0 or lambda_c
            rho = float(np.max(np.maximum(np.linalg.norm(d, axis=1), np.linalg.norm(d + lam_c * self.e_grp, axis=1)))) \
                if self.N else 0.0
            rho = max(rho, 1e-9)
            # |a| of the farthest particle <= a_kin: tangential alpha rho and centripetal omega^2 rho at most a_kin / 2 each
            self.w_max = min(v_max_m_s / rho, math.sqrt(0.5 * a_kin_max_m_s2 / rho))
            self.al_max = 0.5 * a_kin_max_m_s2 / rho
            self.T = _duration(math.pi, self.w_max, self.al_max)
            self._init_turn_spread(lam_c, spread_v_max_m_s, a_kin_max_m_s2)
        else:
            d = self.c - self.r0.mean(axis=0)                 # translation: c is the target of the centroid
            self.dist = float(np.linalg.norm(d))
            self.u = d / self.dist if self.dist > 0 else np.zeros(2)
            self.v_max, self.a_max = v_max_m_s, a_kin_max_m_s2
            self.T = _duration(self.dist, v_max_m_s, a_kin_max_m_s2)
            self._init_spread(cruise_spacing_m, spread_v_max_m_s, a_kin_max_m_s2)
        self.k = 0
        self.rep_active = np.zeros(self.N, dtype=bool)
        self._cache: dict[int, np.ndarray] | None = None     # TimedPlan._states_at_step

    def _init_spread(self, cruise_spacing_m: float, v_max: float, a_max: float) -> None:
        """The translation's spread (docs/default_controller.md, "The pad spreads in cruise"): the scale lambda(t) = 1 + e(t) / rho about
        the centroid (rho: the farthest particle's distance from it), e a rest-to-rest move of D = (lambda_c - 1) rho
        out (v_max, a_max at that particle) from t = 0 and the same move back ending at T; lambda_c =
        cruise_spacing_m / spacing, lowered until both moves fit in T (1: no spread)."""
        self.cen0 = self.r0.mean(axis=0) if self.N else np.zeros(2)
        rho = float(np.max(np.linalg.norm(self.r0 - self.cen0[None, :], axis=1))) if self.N else 0.0
        want = max(0.0, cruise_spacing_m / self.spacing_m - 1.0) * rho if np.isfinite(self.spacing_m) and self.spacing_m > 0 else 0.0
        self._set_spread(rho, want, v_max, a_max)

    def _set_spread(self, rho: float, want_m: float, v_max: float, a_max: float) -> None:
        """The spread's profile, shared by the translation and the half turn: the particle farthest from its centre
        (rho) moves D = want_m out (v_max, a_max) from t = 0 and back ending at T, D lowered until both moves fit in T
        (0: no spread). Sets spread_rho_m, spread_D_m, its limits, T_spread and cruise_scale = 1 + D / rho."""
        D = min(want_m, _distance_within(0.5 * self.T, v_max, a_max))
        if not (rho > 0.0 and D > 1e-9):
            D = 0.0
        self.spread_rho_m, self.spread_D_m = rho, D
        self.spread_v_max, self.spread_a_max = v_max, a_max
        self.T_spread = _duration(D, v_max, a_max)
        self.cruise_scale = 1.0 + D / rho if D > 0.0 else 1.0

    def _init_group_offsets(self, cruise_spacing_m: float) -> float:
        """The half turn's spread (docs/default_controller.md, "Room behind every UAV"): each group scales
        about its own centroid, r_j = c + R(theta) ((cen_g - c) + (1 + lambda) e_j), e_j = r_j(0) - cen_g. Inside a
        group every distance is (1 + lambda) times its start value; between two groups the relative layout does not
        turn (both turn by the same R(theta)), so a pair's distance |cen_a - cen_b + (1 + lambda)(e_i - e_k)| is a
        static function of lambda. Certificate, checked here: every pair of groups' discs of radius (1 + lambda_c)
        rho_g about their centroids stay one spacing apart, |cen_a - cen_b| - (1 + lambda_c)(rho_a + rho_b) >=
        spacing; lambda_c (from cruise_spacing_m / spacing) is lowered until it holds (0: no spread). Sets ``e_grp``
        (N, 2); returns lambda_c."""
        g = self.group
        ng = int(g.max()) + 1 if self.N else 0
        cnt = np.bincount(g, minlength=ng).astype(float)
        cen = np.stack([np.bincount(g, self.r0[:, k], ng) for k in range(2)], axis=1) / np.maximum(cnt, 1.0)[:, None]
        self.e_grp = self.r0 - cen[g] if self.N else np.zeros((0, 2))
        sp = self.spacing_m
        if not (np.isfinite(sp) and sp > 0.0 and cruise_spacing_m > sp and self.N):
            return 0.0
        rho_g = np.zeros(ng)
        np.maximum.at(rho_g, g, np.linalg.norm(self.e_grp, axis=1))
        if rho_g.max() <= 0.0:                             # single-vehicle groups (circle): nothing to spread
            return 0.0
        scale = cruise_spacing_m / sp
        a, b = np.triu_indices(ng, 1)
        reach = rho_g[a] + rho_g[b]
        dcen = np.linalg.norm(cen[a] - cen[b], axis=1)
        ok = reach > 0.0
        if np.any(ok):
            scale = min(scale, float(np.min((dcen[ok] - sp) / reach[ok])))
        return max(0.0, scale - 1.0)

    def _init_turn_spread(self, lam_c: float, v_max: float, a_max: float) -> None:
        """The half turn's spread profile: lambda rises to lambda_c on a rest-to-rest move of the particle farthest
        from its group's centroid (D = lambda_c rho, v_max, a_max), holds, and closes ending with the turn at T; lowered
        until both moves fit in T (as the translation's ``_init_spread``)."""
        rho = float(np.max(np.linalg.norm(self.e_grp, axis=1))) if self.N else 0.0
        self._set_spread(rho, lam_c * rho, v_max, a_max)

    @property
    def spacing_now_m(self) -> float:
        """The particles' smallest distance at step k: the start/slot spacing times the spread's scale (the translation's;
        the half turn's inside each group - between groups its certificate keeps only the start spacing)."""
        return self.spacing_m * (1.0 + self._scale(self.k * self.dt_s)[0])

    @property
    def spacing_reach_m(self) -> float:
        """The larger of spacing_now_m at step k and at step k + 1 (a caller between two steps sees either)."""
        lam = max(self._scale(self.k * self.dt_s)[0], self._scale((self.k + 1) * self.dt_s)[0])
        return self.spacing_m * (1.0 + lam)

    def _scale(self, t: float) -> tuple[float, float, float]:
        """(lambda - 1, its rate, its acceleration) at time t (translation plans; 0 without a spread)."""
        D = self.spread_D_m
        if D <= 0.0:
            return 0.0, 0.0, 0.0
        if t <= 0.5 * self.T:                              # the move out is over by T_spread <= T / 2 (to rounding)
            e, ed, edd = trapezoid(D, self.spread_v_max, self.spread_a_max, t)
        else:
            e, ed, edd = trapezoid(D, self.spread_v_max, self.spread_a_max, t - (self.T - self.T_spread))
            e, ed, edd = D - e, -ed, -edd
        r = self.spread_rho_m
        return e / r, ed / r, edd / r

    def at(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """Every particle's state (N, 4) and kinematic acceleration (N, 2) at time t."""
        w, wd, wdd = self._offset(t)
        if self.kind == "turn":
            th, om, al = trapezoid(math.pi, self.w_max, self.al_max, t)
            cs, sn = math.cos(th), math.sin(th)
            rot = lambda x: np.stack([cs * x[:, 0] - sn * x[:, 1], sn * x[:, 0] + cs * x[:, 1]], axis=1)   # noqa: E731
            lam, lam_d, lam_dd = self._scale(t)
            d = self.r0 - self.c[None, :]
            if lam != 0.0 or lam_d != 0.0 or lam_dd != 0.0:
                d = d + lam * self.e_grp                   # q = d + lambda e (each group scaled about its centroid)
            rd = rot(d)                                    # R(theta) q
            jrd = np.stack([-rd[:, 1], rd[:, 0]], axis=1)  # J R(theta) q
            pos = self.c[None, :] + rd + w[None, :]
            vel = om * jrd + wd[None, :]
            acc = al * jrd - om * om * rd + wdd[None, :]
            if lam_d != 0.0 or lam_dd != 0.0:              # + R lambda' e, + 2 omega lambda' J R e + lambda'' R e
                re = rot(self.e_grp)
                jre = np.stack([-re[:, 1], re[:, 0]], axis=1)
                vel += lam_d * re
                acc += 2.0 * om * lam_d * jre + lam_dd * re
        else:
            s, sd, sdd = trapezoid(self.dist, self.v_max, self.a_max, t)
            pos = self.r0 + (s * self.u + w)[None, :]
            vel = np.broadcast_to(sd * self.u + wd, (self.N, 2)).copy()
            acc = np.broadcast_to(sdd * self.u + wdd, (self.N, 2)).copy()
            lam, lam_d, lam_dd = self._scale(t)
            if lam_d != 0.0 or lam != 0.0 or lam_dd != 0.0:
                d = self.r0 - self.cen0[None, :]
                pos += lam * d
                vel += lam_d * d
                acc += lam_dd * d
        return np.concatenate([pos, vel], axis=1), acc


def rigid_plan_for(S0: np.ndarray, sites_m: np.ndarray, dt_s: float, cost: CostParams, v_max_m_s: float,
                   a_kin_max_m_s2: float, rel_tol: float = 1e-9, translation: bool = False,
                   cruise_spacing_m: float = 0.0) -> RigidPlan | None:
    """The rigid plan of the t = 0 exchange if the target layout is an isometry of the start layout
    (module docstring), else None. S0 (N, 4), sites_m (N, 2). A single group (a translation) gets one
    only with ``translation``: the default controller keeps its interacting plan there, which measured
    better in ``dense`` at N = 100 (0 collided pairs against 2; docs/default_controller.md)."""
    S0 = np.asarray(S0, dtype=float)
    sites = np.asarray(sites_m, dtype=float).reshape(-1, 2)
    n = S0.shape[0]
    if n == 0:
        return None
    _, group = np.unique(sites, axis=0, return_inverse=True)
    group = group.reshape(-1)
    ng = int(group.max()) + 1
    cnt = np.bincount(group, minlength=ng).astype(float)
    r0 = S0[:, 0:2]
    cen = np.stack([np.bincount(group, r0[:, d], ng) for d in range(2)], axis=1) / cnt[:, None]
    site_g = np.zeros((ng, 2))
    site_g[group] = sites
    scale = max(1.0, float(np.max(np.abs(r0))), float(np.max(np.abs(sites))))
    if ng == 1:
        if not translation:
            return None
        slots = sites + r0 - cen[group]
        return RigidPlan(S0, sites, group, slots, "translation", site_g[0], dt_s, cost, v_max_m_s, a_kin_max_m_s2,
                         cruise_spacing_m=cruise_spacing_m)
    two_c = site_g + cen
    if np.max(np.abs(two_c - two_c[0][None, :])) <= rel_tol * scale * 1e3:
        c = 0.5 * two_c[0]
        slots = 2.0 * c[None, :] - r0                        # = site_g - (r_j(0) - centroid_g): the half turn
        return RigidPlan(S0, sites, group, slots, "turn", c, dt_s, cost, v_max_m_s, a_kin_max_m_s2,
                         cruise_spacing_m=cruise_spacing_m)
    return None
