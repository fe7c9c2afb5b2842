"""Communication-free safety backstop: an onboard proximity sensor of short range.

Per sensed vehicle j (relative position d = r_j - r_i, relative velocity u = v_j - v_i,
both from the sensor; no communication), the predicted closest approach over the
horizon is rho = |d + tau* u|, tau* = clip(-d.u / |u|^2, 0, horizon) (tau* = 0, i.e. the
current distance, when |u| < u_noise: the wind's velocity jitter at hover, ~0.2 m/s, is
not extrapolated - it would fire in the dense formation). Only if
rho < trigger does the backstop act, with the acceleration that (to second order) would
open the closest approach to the target clearance (> trigger) by tau*:

    delta_a = -n_hat * share * 2 (target - rho) / max(tau*, tau_min)^2,   n_hat = (d + tau* u) / rho

(share = 1/2: reciprocal, each vehicle takes half; a vehicle that does not react - a failed
one - leaves the other with half per step, and the next step's prediction asks again).

(n_hat = u rotated +90 deg for an exact head-on approach: both pass 'on the right').
Contributions are summed and capped at a_max; the result is a half-plane constraint on the
command (:func:`apply_backstop`: the nearest command to the nominal one whose component
along delta_a is at least |delta_a|). With nothing predicted below the trigger the command
is returned unchanged (inactive otherwise).

Against vehicles that do not fly the plan (MFG's 'unplanned': a failed or blown UAV) the
default MFG controller uses :func:`escape_acc` instead: a sampled safety filter that picks
the command nearest to the nominal one which keeps clear of the threat *and* of every other
sensed vehicle over the horizon (a single half-plane push away from one vehicle could push a
UAV into another's path: where two formations cross, at 8 m/s closing speed).

Shapes: own (n, 4); sensed states (m, 4) owned by bank rows owner (m,).
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import numpy as np

from mfg_autopilot.paper.model import cap_norm
from mfg_autopilot.safety import kernels as backstop_kernels
from mfg_autopilot.safety.layers import Layer, counts_by_layer, layer_names
from mfg_autopilot.safety.params import BackstopParams

__all__ = ["Layer", "layer_names", "counts_by_layer", "cannot_brake_short", "behind_row", "backstop_acc", "apply_backstop",
           "escape_acc", "OwnModel", "NO_LAG", "own_response", "cbf_acc", "warm_up"]


def backstop_acc(own: np.ndarray, sensed_states: np.ndarray, owner: np.ndarray, bp: BackstopParams,
                 select: np.ndarray | None = None) -> np.ndarray:
    """The backstop's correction delta_a per bank row, (n, 2) (zero rows where inactive): the module docstring's
    delta_a summed per row and capped at a_max (compiled: backstop_kernels.half_plane_acc, one call instead of ~20
    small numpy ones; the same operations in the same order as the numpy formulation, tests/_backstop_reference.py).
    select (m,) bool, optional: only these entries count, bit for bit as ``backstop_acc(own, sensed_states[select],
    owner[select], bp)`` but without copying the selected entries (at N = 10,000 the sensed entries are ~1.4 million
    per step, and the gap push of a rigid plan selects nearly all of them); a per-entry trigger_m / target_m then has
    one value per entry of sensed_states."""
    n, m = own.shape[0], sensed_states.shape[0]
    if select is not None:
        select = np.ascontiguousarray(select, dtype=np.bool_)
        if select.shape != (m,):
            raise ValueError(f"select must be ({m},), got {select.shape}")
    if m == 0 or (select is not None and not select.any()):
        return np.zeros((n, 2))
    # trigger and target: scalars, or one per sensed entry (HJB_d's guard on heard vehicles: per-row radii)
    trig = np.array(np.broadcast_to(np.asarray(bp.trigger_m, dtype=float), (m,)))
    targ = np.array(np.broadcast_to(np.asarray(bp.target_m, dtype=float), (m,)))
    return backstop_kernels.half_plane_acc(np.ascontiguousarray(own, dtype=float), np.ascontiguousarray(sensed_states, dtype=float),
                                           np.ascontiguousarray(owner, dtype=np.int64), n, float(bp.horizon_s),
                                           float(bp.u_noise_m_s ** 2), trig, targ, float(bp.share),
                                           float(bp.tau_min_s), float(bp.a_max_m_s2),
                                           _NO_SELECT if select is None else select, select is not None)


_NO_SELECT = np.zeros(0, dtype=np.bool_)


def apply_backstop(a_nom: np.ndarray, delta_a: np.ndarray, a_max_m_s2: float) -> tuple[np.ndarray, np.ndarray]:
    """Minimal intervention as a half-plane constraint (a one-constraint safety filter):
    with n = delta_a / |delta_a| and a_req = |delta_a|, the command is the point nearest to
    a_nom with n.a >= a_req - the nominal keeps everything that does not push against the
    backstop, and is unchanged if it already satisfies it. Under the limit a_max the normal
    component is kept and the tangential one shortened; the result is capped at a_max.
    Returns (command (n, 2), active (n,)). Compiled: backstop_kernels.half_plane_filter."""
    return backstop_kernels.half_plane_filter(np.ascontiguousarray(a_nom, dtype=float), np.ascontiguousarray(delta_a, dtype=float),
                                              float(a_max_m_s2), float(a_max_m_s2 ** 2))


class OwnModel(NamedTuple):
    """How the own airframe flies a command, for the escape's prediction of the own vehicle (issue 18; not from the
    paper). ``acc_lag_s`` tau: the first-order lag of the acceleration it flies behind the one commanded (PX4's
    attitude loop: ~0.154 s; ``mock_vehicle.plant.PlantParams.acc_lag_s``); ``inner_kp_per_s2``, ``inner_kd_per_s``:
    the telemetry-rate inner loop that tracks the period's command between control steps (guidance/inner_loop.py; 0,
    0: none), restarted at every control step (``period_s``). tau = 0: the command is flown at once, and the
    prediction is the closed form the escape has always used, whatever the loop (it has no error to correct)."""

    acc_lag_s: float = 0.0
    inner_kp_per_s2: float = 0.0
    inner_kd_per_s: float = 0.0
    period_s: float = 0.5


NO_LAG = OwnModel()


def own_response(t_s: np.ndarray, commit_s: float, model: OwnModel, sub_steps: int = 20) -> tuple[np.ndarray, ...]:
    """(alpha, beta, gamma), each like t_s (sample times from 0): the own vehicle's displacement

        x(t) = alpha(t) a_1 + beta(t) a_2 + gamma(t) a_f0

    from rest (x = v = 0) when it is commanded a_1 until commit_s and a_2 after it, flying a_f0 at t = 0 (per axis:
    the model is linear and the axes decouple; no drag, no saturation). The airframe: tau a_f' = a_c - a_f with
    a_c = a_k + k_p (r_ref - x) + k_d (v_ref - v), the reference (r_ref, v_ref) flying a_k exactly from the state at
    the last control step (every period_s), a_k the command of the period. Integrated exactly between sub-steps
    (matrix exponential of the linear system; the reference's reset at a step is a jump of the state)."""
    from scipy.linalg import expm
    t = np.asarray(t_s, dtype=float)
    tau, kp, kd = float(model.acc_lag_s), float(model.inner_kp_per_s2), float(model.inner_kd_per_s)
    if not tau > 0.0:
        raise ValueError(f"own_response needs a lag > 0 (tau = 0 has the closed form), got {tau!r}")
    # state y = (x, v, a_f, r_ref, v_ref, a_k): a_k constant within a period (an input held as a state)
    M = np.zeros((6, 6))
    M[0, 1] = 1.0
    M[1, 2] = 1.0
    M[2, :] = np.array([-kp, -kd, -1.0, kp, kd, 1.0]) / tau
    M[3, 4] = 1.0
    M[4, 5] = 1.0
    # a grid fine enough to hit the sample times, the commit time and the control steps (their common divisor)
    h = float(t[1] - t[0]) / sub_steps if t.size > 1 else commit_s / sub_steps
    events = {"commit": float(commit_s), "period": float(model.period_s)}
    for name, v in events.items():
        if abs(v / h - round(v / h)) > 1e-6:
            raise ValueError(f"own_response: the {name} time {v} s is not a multiple of the step {h} s")
    Phi = expm(M * h)
    n_end = int(round(t[-1] / h))
    k_commit, k_period = int(round(commit_s / h)), int(round(model.period_s / h))
    out = []
    for a1, a2, af0 in ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)):
        y = np.array([0.0, 0.0, af0, 0.0, 0.0, a1])
        xs = np.empty(n_end + 1)
        for k in range(n_end + 1):
            if k > 0 and k % k_period == 0:
                y[3], y[4] = y[0], y[1]              # the inner loop restarts from the state of the control step
            if k == k_commit:
                y[5] = a2
            xs[k] = y[0]
            y = Phi @ y
        out.append(np.interp(t, np.arange(n_end + 1) * h, xs))
    return tuple(out)


class _EscapeGrid(NamedTuple):
    """The escape's constants for one (horizon, sampling, commit time, a_max, directions): built once."""

    t: np.ndarray               # (T + 1,) sample times, t[0] = 0
    half_t2: np.ndarray         # the own displacement per unit of a command held from t = 0 (0.5 t^2 without a lag)
    alpha: np.ndarray           # (T + 1,) the own displacement alpha(t) a_1 + beta(t) a_2 (+ gamma(t) a_f0)
    beta: np.ndarray
    gamma: np.ndarray           # (T + 1,) per unit of the acceleration flown at t = 0 (0 without a lag)
    t_seg: np.ndarray           # (T,) the segments' end times
    cand_fixed: np.ndarray      # (C - 1, 2) the candidates a_1 after a_nom: 0, then the directions at a_max / 2 and a_max
    keep_right_den: float       # 0.5 t[-1]^2 a_max
    a_max2: float               # a_max^2


@functools.lru_cache(maxsize=16)
def _escape_grid(horizon_s: float, sample_s: float, commit_s: float, a_max: float, directions: int,
                 own_model: OwnModel = NO_LAG) -> _EscapeGrid:
    t = np.arange(0, int(round(horizon_s / sample_s)) + 1) * sample_s
    tc = min(commit_s, t[-1])
    if own_model.acc_lag_s > 0.0:
        alpha, beta, gamma = own_response(t, tc, own_model)
        held = alpha + beta
    else:
        alpha = np.where(t <= tc, 0.5 * t ** 2, tc * (t - 0.5 * tc))
        beta = np.where(t <= tc, 0.0, 0.5 * (t - tc) ** 2)
        held, gamma = 0.5 * t ** 2, np.zeros_like(t)
    dirs = _directions(directions)
    cand_fixed = np.concatenate([np.zeros((1, 2)), 0.5 * a_max * dirs, a_max * dirs])
    g = _EscapeGrid(t, held, alpha, beta, gamma, t[1:].copy(), cand_fixed, float(0.5 * t[-1] ** 2 * a_max),
                    float(a_max ** 2))
    for v in g:
        if isinstance(v, np.ndarray):
            v.flags.writeable = False
    return g


@functools.lru_cache(maxsize=16)
def _escape_args(bp: BackstopParams, commit_s: float, own_model: OwnModel = NO_LAG) -> tuple:
    """backstop_kernels.escape_rows' arguments after the sensed data: the grid and the parameters, once per
    (bp, commit_s, own_model)."""
    g = _escape_grid(bp.horizon_s, bp.escape_sample_s, commit_s, bp.a_max_m_s2, bp.escape_directions, own_model)
    return (g.t, g.half_t2, g.alpha, g.beta, g.t_seg, g.cand_fixed, float(bp.a_max_m_s2), float(bp.escape_sample_s),
            float(bp.u_noise_m_s), float(bp.escape_threat_weight), float(bp.escape_planned_weight), bool(bp.escape_two_phase),
            bool(bp.escape_urgency), float(bp.tau_min_s), float(bp.escape_d_floor_m), float(bp.escape_keep_right),
            g.keep_right_den, float(bp.escape_effort), float(bp.escape_lateral_cost), g.a_max2, float(bp.escape_side_commit),
            bool(bp.escape_trigger_coast), bool(bp.escape_side_over_keep_right), float(bp.escape_hard_fraction))


def _directions(k: int) -> np.ndarray:
    ang = 2.0 * np.pi * np.arange(k) / k
    return np.stack([np.cos(ang), np.sin(ang)], axis=1)


def escape_acc(own: np.ndarray, a_nom: np.ndarray, sensed_states: np.ndarray, owner: np.ndarray, threat: np.ndarray,
               trigger_m: np.ndarray, clear_m: np.ndarray, bp: BackstopParams, commit_s: float,
               side_pref: np.ndarray | None = None, hover: np.ndarray | None = None,
               own_dist_m_s2: np.ndarray | None = None, brake_hyp: np.ndarray | None = None,
               own_model: OwnModel = NO_LAG, own_acc_m_s2: np.ndarray | None = None,
               tube: np.ndarray | None = None, tube_max_m: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Escape manoeuvre against vehicles that do not fly the plan (a sampled, multi-constraint safety filter).

    Each sensed entry e (own row owner[e]) has a clearance clear_m[e]; threat[e] marks the
    unplanned ones (a failed or blown vehicle), which alone can trigger it, with trigger_m[e].
    Prediction over the horizon, sampled every escape_sample_s and checked along the straight
    segments between samples: every sensed vehicle at constant velocity, and a threat also as
    braking to a stop at a_max (a vehicle that has failed into Hold brakes; the sensor gives no
    acceleration, so both hypotheses are kept; planned vehicles fly the plan and get only the
    first). A row is active if its nominal command a_nom, held over the horizon, brings a threat
    closer than its trigger. The own vehicle then flies a candidate a_1 for the commit time
    (one control period: the command actually sent) and a second-phase a_2 after it, chosen
    from {a_nom, 0, -a_1, a_1} (the next control period decides again; holding a_1 for the
    whole horizon would price a short sidestep as a 4 m swerve into the neighbours). Among
    a_1 in {a_nom, 0, escape_directions directions at 1/2 and 1 x a_max} it takes the one minimising

        min over a_2 of  sum_e w_e u_e max(0, clear_e / max(dmin_e, d_floor) - 1)^2  +  escape_effort effort(a_1 - a_nom),

    w_e = escape_threat_weight (threat) or escape_planned_weight: the escape keeps clear of every
    sensed vehicle, not only of the threat; u_e = tau_min / max(t of the approach, tau_min)
    (urgency). Rows that are not active keep a_nom. side_pref (n, 2), optional: per row a unit vector across its track
    (or 0); a candidate a_1 against it adds escape_side_commit max(0, -side_pref . a_1) / a_max to the cost (the side a
    row passes a hovering vehicle on, guidance.controller._escape_side). hover (m,) bool, optional: the threat entries
    that hover (the controller marks those slower than hover_max_speed_m_s, off the plan). With
    bp.escape_trigger_coast such an entry also activates its row if the own vehicle *coasting* (a = 0 over the horizon)
    would bring it below its trigger (the nominal command's momentary tracking correction, held for 2 s, predicts misses
    the UAV does not make); with bp.escape_side_over_keep_right it gets no keep-right term in a row with a side_pref (the
    lane side decides which side it is passed on). Safety first (bp.escape_hard_fraction, nineteenth session): if some
    candidate has a second phase that keeps every sensed entry at least escape_hard_fraction x its clearance away, the
    row takes the cheapest such candidate (its cost over those second phases); otherwise the cheapest by the cost alone.
    own_dist_m_s2 (n, 2), optional: each row's own disturbance (what it flies beyond its command: a gust), held over the
    horizon in every prediction of the own vehicle, the trigger's included (BackstopParams.own_disturbance).
    brake_hyp (m,) bool, optional: the threat entries that get the braking hypothesis; the others are predicted at
    constant velocity only (None: every threat; BackstopParams.escape_brake_hypothesis).
    own_model: how the own airframe flies a command (:class:`OwnModel`: its acceleration lag and the inner loop);
    with a lag the own vehicle's displacement under a_1 then a_2 is alpha a_1 + beta a_2 + gamma a_f0
    (:func:`own_response`), a_f0 = own_acc_m_s2 (n, 2), the acceleration each row flies now (the controller's last
    command; None: 0). Without a lag (the default) the prediction is the closed form 0.5 t^2 a.
    tube (m,) bool, optional: the threat entries whose position t seconds ahead is uncertain by
    min(bp.escape_tube_m_s2 t^2 / 2, tube_max_m) (an unknown acceleration bound: a vehicle failing into Hold). For them
    a track's closest distance d at t counts as d c / (c + that radius) - the clearance c plus the tube - in every read
    of the trigger (c: its trigger) and in every candidate's penalty and safety (c: its clearance;
    kernels._segment_eff_one). None: no tube.
    Returns (command (n, 2), active (n,)).
    """
    n = own.shape[0]
    active = np.zeros(n, dtype=bool)
    a_out = np.array(a_nom, dtype=float, copy=True)
    if sensed_states.shape[0] == 0 or not np.any(threat):
        return a_out, active
    # one compiled call (backstop_kernels.escape_rows): the same operations in the same order as the numpy formulation
    # it replaced (tests/_backstop_reference.py), ~2,700 small numpy calls per escape step for a bank of one
    a_out, active = backstop_kernels.escape_rows(
        np.ascontiguousarray(own, dtype=float), a_out, np.ascontiguousarray(sensed_states, dtype=float),
        np.ascontiguousarray(owner, dtype=np.int64), np.ascontiguousarray(threat, dtype=bool),
        np.ascontiguousarray(trigger_m, dtype=float), np.ascontiguousarray(clear_m, dtype=float),
        *_escape_args(bp, commit_s, own_model),
        np.zeros((n, 2)) if side_pref is None else np.ascontiguousarray(side_pref, dtype=float),
        np.zeros(sensed_states.shape[0], dtype=bool) if hover is None else np.ascontiguousarray(hover, dtype=bool),
        np.zeros((n, 2)) if own_dist_m_s2 is None else np.ascontiguousarray(own_dist_m_s2, dtype=float),
        np.ones(sensed_states.shape[0], dtype=bool) if brake_hyp is None else np.ascontiguousarray(brake_hyp, dtype=bool),
        _escape_grid(bp.horizon_s, bp.escape_sample_s, commit_s, bp.a_max_m_s2, bp.escape_directions, own_model).gamma,
        np.zeros((n, 2)) if own_acc_m_s2 is None else np.ascontiguousarray(own_acc_m_s2, dtype=float),
        float(bp.escape_tube_m_s2), float(tube_max_m),
        np.zeros(sensed_states.shape[0], dtype=bool) if tube is None else np.ascontiguousarray(tube, dtype=bool))
    if not np.any(active):
        return a_out, active
    return cap_norm(a_out, bp.a_max_m_s2), active


def behind_row(own: np.ndarray, sensed_states: np.ndarray, owner: np.ndarray, clear_m: np.ndarray | None = None,
               react_s: float = 0.0) -> np.ndarray:
    """(m,) bool: the sensed entries behind their own row (owner (m,), own (n, 4)): dp . v_i < 0 with dp = r_j - r_i and
    v_i the row's own velocity (BackstopParams.escape_rear_responsible: the UAV behind is the responsible one).

    Of two vehicles i, j closing on each other (dp . (v_j - v_i) < 0) at least one has the other not behind it: if
    dp . v_i < 0 and -dp . v_j < 0, then dp . (v_j - v_i) > 0 and they separate. A row at rest has nothing behind it.
    clear_m (m,), if given: an entry closing along the line of sight at v_c > 0 that comes within clear_m inside
    react_s, |dp| - clear_m <= v_c react_s, is not behind (imminent: the row acts on it whoever is responsible)."""
    own = np.asarray(own, dtype=float)
    q = np.asarray(sensed_states, dtype=float)
    if q.shape[0] == 0:
        return np.zeros(0, dtype=bool)
    rel = q[:, 0:2] - own[owner, 0:2]
    behind = rel[:, 0] * own[owner, 2] + rel[:, 1] * own[owner, 3] < 0.0
    if clear_m is not None and np.any(behind):
        dv = q[:, 2:4] - own[owner, 2:4]
        d = np.hypot(rel[:, 0], rel[:, 1])
        vc = -(rel[:, 0] * dv[:, 0] + rel[:, 1] * dv[:, 1]) / np.maximum(d, 1e-12)
        behind &= ~((vc > 0.0) & (d - np.asarray(clear_m, dtype=float) <= vc * react_s))
    return behind


def cannot_brake_short(own: np.ndarray, sensed_states: np.ndarray, owner: np.ndarray, clear_m: np.ndarray,
                       a_max_m_s2: float, react_s: float) -> np.ndarray:
    """(m,) bool: the sensed entries that their own row (owner (m,), own (n, 4)) cannot stop short of by braking: the row
    closes on the entry along the line of sight at v_c = -(dp . dv) / |dp| > 0 (dp = r_j - r_i, dv = v_j - v_i) and

        v_c^2 / (2 a_max) + v_c react_s >= |dp| - clear_m,

    i.e. keeping on for react_s (one control period: the command is decided now and flown until the next sample) and then
    braking at a_max along the line of sight brings it closer than clear_m (m,). The entry is taken as it is (a hovering
    vehicle: its own motion is what the row senses). This is where a filter that only brakes along each line of sight
    (the crowd's barrier filter, cbf_acc) has no feasible answer left, and a swerve (escape_acc) is needed."""
    own = np.asarray(own, dtype=float)
    q = np.asarray(sensed_states, dtype=float)
    if q.shape[0] == 0:
        return np.zeros(0, dtype=bool)
    dp = q[:, 0:2] - own[owner, 0:2]
    dv = q[:, 2:4] - own[owner, 2:4]
    d = np.hypot(dp[:, 0], dp[:, 1])
    vc = -np.sum(dp * dv, axis=1) / np.maximum(d, 1e-12)
    return (vc > 0.0) & (vc * vc / (2.0 * a_max_m_s2) + vc * react_s >= d - np.asarray(clear_m, dtype=float))


@functools.lru_cache(maxsize=1)
def _cbf_disc() -> np.ndarray:
    """The reciprocal CBF filter's sampled candidates on the unit disc: the centre and 24 directions at 4 radii."""
    th = np.arange(24) * (2.0 * np.pi / 24.0)
    ring = np.stack([np.cos(th), np.sin(th)], axis=1)
    return np.ascontiguousarray(np.concatenate([np.zeros((1, 2))] + [r * ring for r in (0.25, 0.5, 0.75, 1.0)]))


def cbf_acc(own: np.ndarray, a_nom: np.ndarray, sensed_states: np.ndarray, owner: np.ndarray, rows: np.ndarray,
            bp: BackstopParams, safe_m: float, a_max_m_s2: float, share: np.ndarray | None = None,
            own_dist_m_s2: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Reciprocal control-barrier safety filter with acceleration limits (Wang, Ames, Egerstedt, "Safety barrier
    certificates for collision-free multirobot systems", IEEE T-RO 2017), for the bank rows ``rows``.

    Per sensed vehicle j of row i (dp = r_i - r_j, dv = v_i - v_j, from the sensor; d = |dp|, p = dp / d, the opening
    speed rdot = p . dv), the barrier

        h_ij = sqrt(4 alpha (d - D_s)) + rdot    (alpha = crowd_cbf_alpha_m_s2, D_s = safe_m)

    is >= 0 while the pair, both braking at alpha, can stop closing before they are D_s apart. Keeping
    dh/dt >= -gamma h^3 is linear in the accelerations, p . (a_i - a_j) >= B_ij with

        B_ij = -gamma h^3 - |dv|^2 / d + rdot^2 / d - 2 alpha rdot / sqrt(4 alpha (d - D_s)),

    and each vehicle takes its share of it (crowd_cbf_share = 1/2: reciprocal; no communication): p . a_i >= B_ij / 2.
    share (m,), optional, per entry instead (1 for a vehicle that does not take its half: one hovering in Hold).
    own_dist_m_s2 (n, 2), optional: each row's own disturbance d_i, which its command must also make up for, p . (a_i +
    d_i) >= share B_ij (BackstopParams.own_disturbance; the neighbour's is its own share to answer).
    Inside the safe distance (d <= D_s: h is undefined) B_ij is clamped to >= 0 (crowd_cbf_inside_no_approach): the row
    accelerates no closer, p . (a_i + d_i) >= 0, whether the pair is opening or closing.
    The command is the one nearest a_nom with |a| <= a_max_m_s2 that meets every constraint of the row (at most
    crowd_cbf_max_constraints, the most demanding; a constraint with B / 2 <= -a_max holds for every command), or, if
    none does, the one that misses the most violated constraint least. Solved exactly over the candidates where a 2-D
    optimum lies (a_nom's projection on each constraint line, the lines' crossings with the disc and with each other)
    plus a sampled disc (``_cbf_disc``), in one compiled call (``backstop_kernels.cbf_rows``).

    own (n, 4), a_nom (n, 2) (already capped), sensed_states (m, 4) owned by bank rows owner (m,); rows (r,) int.
    Returns (commands (r, 2), active (r,): the command differs from a_nom)."""
    rows = np.ascontiguousarray(rows, dtype=np.int64)
    owner = np.asarray(owner, dtype=np.int64)
    order = np.argsort(owner, kind="stable").astype(np.int64)
    sorted_owner = owner[order]
    starts = np.searchsorted(sorted_owner, rows, side="left").astype(np.int64)
    ends = np.searchsorted(sorted_owner, rows, side="right").astype(np.int64)
    share = np.full(owner.shape[0], float(bp.crowd_cbf_share)) if share is None else np.ascontiguousarray(share, dtype=float)
    return backstop_kernels.cbf_rows(np.ascontiguousarray(own, dtype=float), np.ascontiguousarray(a_nom, dtype=float),
                                     np.ascontiguousarray(sensed_states, dtype=float), order, starts, ends, rows,
                                     float(a_max_m_s2), float(bp.crowd_cbf_alpha_m_s2), float(bp.crowd_cbf_gamma),
                                     float(safe_m), share, int(bp.crowd_cbf_max_constraints),
                                     _cbf_disc(), np.zeros((own.shape[0], 2)) if own_dist_m_s2 is None
                                     else np.ascontiguousarray(own_dist_m_s2, dtype=float),
                                     bool(bp.crowd_cbf_inside_no_approach))


def warm_up() -> None:
    """Load (or, on a cold cache, compile) the kernels, so that the first backstop step does not pay for it.
    Through this module's public wrappers, with cases that reach every kernel (an escape
    that acts, a half-plane push), so the argument types are exactly those of a control step (a kernel
    first called with other types - a read-only or differently laid out array - would compile again,
    seconds inside a control step: tests/test_kernels.py checks that a flight step compiles nothing new)."""
    bp = BackstopParams()
    own = np.array([[0.0, 0.0, 4.0, 0.0]])
    a_nom = np.array([[0.2, -0.1]])
    # a hovering (unplanned) vehicle 2 m ahead and a planned one alongside: the escape acts
    sensed = np.array([[2.0, 0.0, 0.0, 0.0], [0.0, 1.0, 4.0, 0.0]])
    escape_acc(own, a_nom, sensed, np.array([0, 0]), np.array([True, False]), np.array([0.6, 0.0]),
               np.array([0.8, 0.5]), bp, 0.5)
    da = backstop_acc(own, np.array([[0.3, 0.05, 3.0, 0.0]]), np.array([0]), bp)
    apply_backstop(a_nom, da, 2.0)
    # the crowd's barrier filter, acting (a vehicle 1 m ahead, closing)
    cbf_acc(own, a_nom, sensed, np.array([0, 0]), np.array([0]), bp, 0.3, 2.0)
    # the MFG tracking's formation mean (guidance.controller._formation_error), with its call's argument types
    i64 = np.array([0, 0], dtype=np.int64)
    backstop_kernels.slot_claims(i64, sensed, own, np.ones(1, dtype=np.bool_), 1.0, 1.0)
    backstop_kernels.formation_sums(i64, np.array([1, 2], dtype=np.int64), sensed, own, np.zeros((1, 4)),
                           np.array([0, 1, 2], dtype=np.int64), np.array([0, 1, 2], dtype=np.int64), np.zeros((3, 4)),
                           np.zeros(1, dtype=np.int64), 1, 1.0, 1.0, 0.5, 3.0)
    # one entry per sensed vehicle (guidance.controller._distinct), with its call's argument types
    backstop_kernels.distinct_dense(sensed, np.array([1, 1], dtype=np.int64), 2)
    # the MFG braking test's scan (guidance.controller._unplanned_by_braking), with its call's argument types
    for test in (False, True):
        backstop_kernels.braking_scan(i64, np.array([1, 2], dtype=np.int64), sensed.copy(), np.zeros(2, dtype=np.bool_), 1,
                                      np.zeros((3, 2)), np.zeros(3, dtype=np.int64), np.zeros((3, 4)), test, np.zeros((3, 2)), test,
                                      np.zeros((1, 2)), test, 1, 0.5, 1.75)
