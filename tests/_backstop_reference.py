"""Test-only reference: the backstop path as it was at b4ed553 (before the bank-of-one speed-up),
copied verbatim, to check that the new code gives bit-identical results (tests/test_backstop_speed.py).

``Reference(ctrl)`` runs the old ``_DefaultBase._backstop`` / ``DefaultMFGController._unplanned``
on the state of a live controller ``ctrl`` (its preset, plan, own error and n)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from scipy.spatial import cKDTree

from mfg_autopilot.interface import Neighbours, Observation
from mfg_autopilot.paper.model import cap_norm
from mfg_autopilot.safety.params import BackstopParams


def _sensed(obs: Observation) -> Neighbours:
    return obs.sensed if obs.sensed is not None else Neighbours.empty()


def backstop_acc(own: np.ndarray, sensed_states: np.ndarray, owner: np.ndarray, bp: BackstopParams) -> np.ndarray:
    """The backstop's correction delta_a per bank row, (n, 2) (zero rows where inactive)."""
    n = own.shape[0]
    out = np.zeros((n, 2))
    if sensed_states.shape[0] == 0:
        return out
    d = sensed_states[:, 0:2] - own[owner, 0:2]
    u = sensed_states[:, 2:4] - own[owner, 2:4]
    uu = np.einsum("pd,pd->p", u, u)
    tau = np.clip(-np.einsum("pd,pd->p", d, u) / np.maximum(uu, 1e-12), 0.0, bp.horizon_s)
    tau = np.where(uu >= bp.u_noise_m_s ** 2, tau, 0.0)          # wind jitter is not a trend
    c = d + tau[:, None] * u
    rho = np.linalg.norm(c, axis=1)
    act = rho < bp.trigger_m
    if not np.any(act):
        return out
    un = np.sqrt(uu)
    perp = np.stack([-u[:, 1], u[:, 0]], axis=1) / np.maximum(un, 1e-12)[:, None]
    n_hat = np.where((rho > 1e-6)[:, None], c / np.maximum(rho, 1e-12)[:, None], np.where((un > 1e-9)[:, None], perp, np.array([[1.0, 0.0]])))
    mag = np.where(act, bp.share * 2.0 * (bp.target_m - rho) / np.maximum(tau, bp.tau_min_s) ** 2, 0.0)
    f = -mag[:, None] * n_hat
    for dim in range(2):
        out[:, dim] = np.bincount(owner, f[:, dim], n)
    return cap_norm(out, bp.a_max_m_s2)


def apply_backstop(a_nom: np.ndarray, delta_a: np.ndarray, a_max_m_s2: float) -> tuple[np.ndarray, np.ndarray]:
    """Minimal intervention as a half-plane constraint (a one-constraint safety filter):
    with n = delta_a / |delta_a| and a_req = |delta_a|, the command is the point nearest to
    a_nom with n.a >= a_req - the nominal keeps everything that does not push against the
    backstop, and is unchanged if it already satisfies it. Under the limit a_max the normal
    component is kept and the tangential one shortened. Returns (command (n, 2), active (n,))."""
    a_req = np.linalg.norm(delta_a, axis=1)
    active = a_req > 0
    n_hat = delta_a / np.maximum(a_req, 1e-300)[:, None]
    a_n_nom = np.einsum("nd,nd->n", a_nom, n_hat)
    a_n = np.minimum(np.maximum(a_req, a_n_nom), a_max_m_s2)
    tang = a_nom - a_n_nom[:, None] * n_hat
    tang = cap_norm(tang, np.sqrt(np.maximum(a_max_m_s2 ** 2 - a_n ** 2, 0.0)))
    a = np.where(active[:, None], a_n[:, None] * n_hat + tang, a_nom)
    return cap_norm(a, a_max_m_s2), active


def _directions(k: int) -> np.ndarray:
    ang = 2.0 * np.pi * np.arange(k) / k
    return np.stack([np.cos(ang), np.sin(ang)], axis=1)


def _segment_min(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Closest approach along piecewise-linear relative tracks p (m, T + 1, 2) (sample 0 = now):
    per entry the smallest |p| over the T segments (as the collision metric checks each step's
    segment, SPEC 6; samples alone miss up to half a sample of a fast pass) and the index of the
    segment where it occurs. Returns (dmin (m,), segment (m,))."""
    d0 = p[:, :-1, :]
    dd = p[:, 1:, :] - d0
    den = np.einsum("mtd,mtd->mt", dd, dd)
    tau = np.clip(-np.einsum("mtd,mtd->mt", d0, dd) / np.maximum(den, 1e-300), 0.0, 1.0)
    dist = np.linalg.norm(d0 + tau[:, :, None] * dd, axis=2)
    k = np.argmin(dist, axis=1)
    return dist[np.arange(dist.shape[0]), k], k


def escape_acc(own: np.ndarray, a_nom: np.ndarray, sensed_states: np.ndarray, owner: np.ndarray, threat: np.ndarray,
               trigger_m: np.ndarray, clear_m: np.ndarray, bp: BackstopParams, commit_s: float,
               side_pref: np.ndarray | None = None, hover: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
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
    (urgency). Rows that are not active keep a_nom. Returns (command (n, 2), active (n,)).
    """
    n = own.shape[0]
    active = np.zeros(n, dtype=bool)
    a_out = np.array(a_nom, dtype=float, copy=True)
    if sensed_states.shape[0] == 0 or not np.any(threat):
        return a_out, active
    a_max = bp.a_max_m_s2
    t = np.arange(0, int(round(bp.horizon_s / bp.escape_sample_s)) + 1) * bp.escape_sample_s       # (T + 1,), t[0] = 0
    # a threat's braking hypothesis: its velocity w decays at a_max to 0; displacement removed from its coasting track
    ti = np.flatnonzero(threat)
    w = sensed_states[ti, 2:4]
    wn = np.linalg.norm(w, axis=1)
    tb = np.minimum(t[None, :], (wn / a_max)[:, None])                                           # (m_thr, T + 1)
    back = (0.5 * a_max * tb ** 2)[:, :, None] * (w / np.maximum(wn, 1e-12)[:, None])[:, None, :]

    def rel_tracks(ent: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Other vehicles' tracks relative to the own *coasting* vehicle (a = 0), q(t) - r - v t: the
        constant-velocity one for every entry (m, T + 1, 2), and the braking one for the threats among them."""
        d = sensed_states[ent, 0:2] - own[owner[ent], 0:2]
        u = sensed_states[ent, 2:4] - own[owner[ent], 2:4]
        rel = d[:, None, :] + t[None, :, None] * u[:, None, :]
        at = np.searchsorted(ti, ent[threat[ent]])
        return rel, rel[threat[ent]] - back[at]

    # which rows does the nominal command (held over the horizon) put in conflict with a threat
    rel_t, rel_tb = rel_tracks(ti)
    own_nom = (0.5 * t ** 2)[None, :, None] * a_nom[owner[ti]][:, None, :]
    dmin_nom = np.minimum(_segment_min(rel_t - own_nom)[0], _segment_min(rel_tb - own_nom)[0])
    if hover is not None and bp.escape_trigger_coast:   # (tenth session) coasting too, for the hovering entries
        c = hover[ti]
        dmin_nom = np.where(c, np.minimum(dmin_nom, np.minimum(_segment_min(rel_t)[0], _segment_min(rel_tb)[0])), dmin_nom)
    hit = dmin_nom < trigger_m[ti]
    active[np.unique(owner[ti[hit]])] = True
    if not np.any(active):
        return a_out, active
    rows = np.flatnonzero(active)
    pos = np.full(n, -1, dtype=np.int64)
    pos[rows] = np.arange(rows.size)
    ent = np.flatnonzero(active[owner])                      # every sensed entry of the active rows
    e_row = pos[owner[ent]]
    rel, rel_b = rel_tracks(ent)
    thr, clear = threat[ent], clear_m[ent]
    wgt = np.where(thr, bp.escape_threat_weight, bp.escape_planned_weight)
    # 'keep right' (as the plan's repulsion): against each vehicle the nominal command conflicts with, a
    # sideways escape to the left of the approach costs extra, so two escaping vehicles pick opposite sides
    u_s = rel[:, 1, :] - rel[:, 0, :]
    u_s = u_s / bp.escape_sample_s
    un_s = np.linalg.norm(u_s, axis=1)
    left = np.stack([u_s[:, 1], -u_s[:, 0]], axis=1) / np.maximum(un_s, 1e-12)[:, None]         # -u rotated +90 deg
    own_nom_e = (0.5 * t ** 2)[None, :, None] * a_nom[owner[ent]][:, None, :]
    dn = _segment_min(rel - own_nom_e)[0]
    dn[thr] = np.minimum(dn[thr], _segment_min(rel_b - own_nom_e[thr])[0])
    conflict = (dn < clear) & (un_s > bp.u_noise_m_s)
    if hover is not None and side_pref is not None and bp.escape_side_over_keep_right:
        # (eleventh session) in a row with a lane side, no keep-right against a hovering vehicle
        conflict &= ~(hover[ent] & np.any(side_pref[owner[ent]] != 0, axis=1))
    # the own displacement under (a_1 for commit_s, then a_2): alpha(t) a_1 + beta(t) a_2
    tc = min(commit_s, t[-1])
    alpha = np.where(t <= tc, 0.5 * t ** 2, tc * (t - 0.5 * tc))
    beta = np.where(t <= tc, 0.0, 0.5 * (t - tc) ** 2)
    dirs = _directions(bp.escape_directions)
    cand_fixed = np.concatenate([np.zeros((1, 2)), 0.5 * a_max * dirs, a_max * dirs])            # (C - 1, 2)
    # lateral departures from the own track cost escape_lateral_cost x more than along-track ones (braking keeps
    # a UAV in its own lane, which the plan has deconflicted from the other groups' lanes)
    vo = own[rows, 2:4]
    vn = np.linalg.norm(vo, axis=1)
    v_hat = np.where((vn > bp.u_noise_m_s)[:, None], vo / np.maximum(vn, 1e-12)[:, None], 0.0)
    a_nom_r = a_nom[rows]
    best = np.full(rows.size, np.inf)
    best_safe = np.full(rows.size, np.inf)          # (nineteenth session) the cheapest safe candidate's cost
    a_safe = np.zeros((rows.size, 2))
    t_seg = t[1:]
    for c in range(cand_fixed.shape[0] + 1):
        a1 = a_nom_r if c == 0 else np.broadcast_to(cand_fixed[c - 1], (rows.size, 2))
        phase2 = (a_nom_r, np.zeros_like(a_nom_r), -a1, a1) if bp.escape_two_phase else (a1,)
        pen_best = np.full(rows.size, np.inf)
        pen_safe = np.full(rows.size, np.inf)
        for a2 in phase2:
            disp = alpha[None, :, None] * a1[e_row][:, None, :] + beta[None, :, None] * a2[e_row][:, None, :]   # (m', T + 1, 2)
            dmin, k = _segment_min(rel - disp)
            if np.any(thr):
                db, kb = _segment_min(rel_b - disp[thr])
                worse = db < dmin[thr]
                dmin[thr] = np.where(worse, db, dmin[thr])
                k[thr] = np.where(worse, kb, k[thr])
            # urgency: a conflict predicted at t counts tau_min / max(t, tau_min) (one that comes later can still be
            # solved at a later step; an imminent one cannot)
            urg = bp.tau_min_s / np.maximum(t_seg[k], bp.tau_min_s) if bp.escape_urgency else 1.0
            pen = wgt * urg * np.maximum(0.0, clear / np.maximum(dmin, bp.escape_d_floor_m) - 1.0) ** 2
            pen = pen + np.where(conflict, bp.escape_keep_right * np.maximum(0.0, np.einsum("ed,ed->e", left, disp[:, -1, :])) /
                                 (0.5 * t[-1] ** 2 * a_max), 0.0)
            pen_r = np.bincount(e_row, pen, rows.size)
            pen_best = np.minimum(pen_best, pen_r)
            if bp.escape_hard_fraction > 0:
                # (nineteenth session) safe: every entry predicted at least hard_fraction x its clearance away
                unsafe = np.bincount(e_row, dmin < bp.escape_hard_fraction * clear, rows.size) > 0
                pen_safe = np.where(unsafe, pen_safe, np.minimum(pen_safe, pen_r))
        da_c = a1 - a_nom_r
        along = np.einsum("rd,rd->r", da_c, v_hat)
        effort = (along ** 2 + bp.escape_lateral_cost * (np.einsum("rd,rd->r", da_c, da_c) - along ** 2)) / a_max ** 2
        eff = bp.escape_effort * effort
        cost = pen_best + eff
        cost_s = pen_safe + eff
        if side_pref is not None:
            # (ninth session) the side the row passes a hovering vehicle on (escape_side_commit)
            side_r = side_pref[rows]
            side_c = bp.escape_side_commit * np.maximum(0.0, -(side_r[:, 0] * a1[:, 0] + side_r[:, 1] * a1[:, 1])) / a_max
            cost = cost + side_c
            cost_s = cost_s + side_c
        better = cost < best
        best = np.where(better, cost, best)
        a_out[rows[better]] = a1[better]
        take = np.isfinite(pen_safe) & (cost_s < best_safe)
        best_safe = np.where(take, cost_s, best_safe)
        a_safe[take] = a1[take]
    # a row with a safe candidate takes the cheapest of those
    has = np.isfinite(best_safe)
    a_out[rows[has]] = a_safe[has]
    return cap_norm(a_out, a_max), active


class Reference:
    """The old controller methods, bound to a live controller's state (read only, except the
    k-d tree cache, which is this object's own)."""

    def __init__(self, ctrl) -> None:
        self.c = ctrl
        self._plan_tree = None
        self.backstop_active = None

    def __getattr__(self, name):
        return getattr(self.c, name)

    @property
    def _own_err(self):
        return self.c._own_err

    @property
    def n(self):
        return self.c.n

    def _spacing_m(self):
        return self.c._spacing_m() if self.c.mode == "mfg" else float("inf")

    def _unplanned(self, sensed_states, ids=None):
        if self.c.mode != "mfg":
            return np.zeros(sensed_states.shape[0], dtype=bool)
        return self._unplanned_mfg(sensed_states, ids)

    @staticmethod
    def _not_heard(sensed: Neighbours, heard: Neighbours | None) -> Neighbours:
        """The sensed vehicles a row did not also hear this step (HJB_d's repulsion already
        acts on those; the backstop covers what communication does not). Matched by id."""
        if heard is None or heard.states.shape[0] == 0 or sensed.states.shape[0] == 0 or sensed.ids is None or heard.ids is None:
            return sensed
        big = np.int64(1) << 32
        sk = sensed.owner.astype(np.int64) * big + sensed.ids
        hk = np.sort(heard.owner.astype(np.int64) * big + heard.ids)
        at = np.minimum(np.searchsorted(hk, sk), hk.size - 1)
        keep = hk[at] != sk          # = ~np.isin(sk, hk), by binary search (np.isin's hash-based unique is far slower here)
        return Neighbours(sensed.states[keep], sensed.owner[keep], sensed.ids[keep])

    def _plan_distance(self, q: np.ndarray) -> np.ndarray:
        """(m,) distance of states q to the nearest plan particle in the metric
        |dr|^2 + (plan_mismatch_s |dv|)^2; the particles' k-d tree is built once per plan step."""
        ps = self.preset.backstop.plan_mismatch_s
        w = np.array([1.0, 1.0, ps, ps])
        if self._plan_tree is None or self._plan_tree[0] != self.plan.k:
            self._plan_tree = (self.plan.k, cKDTree(self.plan.states * w))
        d, _ = self._plan_tree[1].query(q * w, k=1)
        return d

    def _beyond_plan(self, q: np.ndarray, threshold_m: float, hint: np.ndarray | None = None) -> np.ndarray:
        """(m,) bool: _plan_distance(q) > threshold_m, exactly. hint (m,): a plan particle per state (its
        own, if known): a state clearly within the threshold of it (1e-9 relative margin, far above the
        rounding of either distance) is within it of the nearest particle too and needs no tree query."""
        out = np.zeros(q.shape[0], dtype=bool)
        todo = np.arange(q.shape[0])
        if hint is not None and q.shape[0] > 0 and 0 <= hint.min() and hint.max() < self.plan.N:
            ps = self.preset.backstop.plan_mismatch_s
            dx = q - self.plan.states[hint]
            d2 = dx[:, 0] ** 2 + dx[:, 1] ** 2 + ps * ps * (dx[:, 2] ** 2 + dx[:, 3] ** 2)
            todo = np.flatnonzero(~(d2 <= (threshold_m * (1.0 - 1e-9)) ** 2))
        if todo.size:
            out[todo] = self._plan_distance(q[todo]) > threshold_m
        return out

    def _unplanned_mfg(self, sensed_states: np.ndarray, ids: np.ndarray | None = None) -> np.ndarray:
        """Sensed vehicles farther than plan_mismatch_m from every plan particle, in the state
        metric |dr|^2 + (plan_mismatch_s |dv|)^2 (the plan -
        the same on every UAV - says where everyone should be; no communication needed)."""
        if sensed_states.shape[0] == 0:
            return np.zeros(0, dtype=bool)
        q = sensed_states
        if ids is not None and len(ids) == q.shape[0]:
            # the same vehicle is sensed by many rows: query each distinct state once (the same distance),
            # after checking that every row of an id carries the same state (else query them all)
            # (distinct ids ascending and each row's rank among them, as np.unique gives them, in O(m + max id)
            # instead of a sort; the representative row of an id is its last one - all carry the same state)
            ids = np.asarray(ids, dtype=np.int64)
            if ids.min() >= 0 and ids.max() < 4 * ids.size + 1024:
                present = np.zeros(int(ids.max()) + 1, dtype=bool)
                present[ids] = True
                rep = np.empty(present.size, dtype=np.int64)
                rep[ids] = np.arange(ids.size)
                first = rep[present]
                inv = (np.cumsum(present) - 1)[ids]
            else:
                _, first, inv = np.unique(ids, return_index=True, return_inverse=True)
                inv = inv.reshape(-1)
            if np.array_equal(q[first][inv], q):
                return self._beyond_plan(q[first], self.preset.backstop.plan_mismatch_m, ids[first])[inv]
            return self._beyond_plan(q, self.preset.backstop.plan_mismatch_m, ids)
        return self._beyond_plan(q, self.preset.backstop.plan_mismatch_m)

    def _backstop(self, own: np.ndarray, a_nom: np.ndarray, obs: Observation) -> np.ndarray:
        bp, a_max = self.preset.backstop, self.preset.learner.acc_max_m_s2
        if not bp.enabled:
            return cap_norm(a_nom, a_max)
        sn = self._not_heard(_sensed(obs), obs.neighbours)
        unplanned = self._unplanned(sn.states, sn.ids)
        planned = ~unplanned              # on the plan itself (not only up to the common mode)
        if getattr(getattr(self, "plan", None), "kind", "interacting") in ("turn", "translation", "groups") \
                and not bp.planned_response_rigid:
            planned[:] = False            # the policy of the production code (a rigid or scheduled plan: issue 18)
        if np.any(unplanned) and self._own_err is not None and bp.common_mode:
            # common mode is not a threat: a vehicle that is off the plan the way the own vehicle is (a gust
            # blows both) is checked again against the plan shifted by the own deviation (the own row's s - s_plan);
            # only for rows that are off their own particle themselves (else the shift only eats the detection margin:
            # measured, a UAV 0.1 m off its particle cleared a vehicle braking in Hold right in front of it)
            ps = bp.plan_mismatch_s
            own_dev = np.linalg.norm(self._own_err * np.array([1.0, 1.0, ps, ps]), axis=1)
            idx = np.flatnonzero(unplanned & (own_dev[sn.owner] > bp.common_mode_min_own_dev_m))
            unplanned[idx] = self._unplanned(sn.states[idx] - self._own_err[sn.owner[idx]])
        if self._own_err is not None:
            # the planned vehicles' response assumes both fly the plan to within centimetres; a UAV blown
            # further off its own particle, or a neighbour off the plan by the common mode, is left to the
            # tracking (measured: in a gust this response pushed UAVs of the 0.5 m dense formation into each other)
            off = np.linalg.norm(self._own_err[:, 0:2], axis=1) > bp.planned_max_own_dev_m
            planned &= ~off[sn.owner]
        da = backstop_acc(own, sn.states[planned], sn.owner[planned], bp)
        esc = np.zeros(self.n, dtype=bool)
        if np.any(unplanned):
            # the unplanned response's trigger and clearance, fitted to the slot spacing
            sp = self._spacing_m()
            u_trig, u_clear = min(bp.unplanned_trigger_m, 0.5 * sp), min(bp.unplanned_target_m, 0.6 * sp)
            # the escape is a backstop for a few off-plan vehicles; a row that senses mostly off-plan vehicles (the
            # swarm has lost its plan) gets the single half-plane push instead (measured: with every UAV off the
            # plan, escaping from all neighbours at once swerved UAVs into each other in the 0.5 m formation)
            crowded = np.ones(self.n, dtype=bool)
            if bp.escape:
                n_unpl = np.bincount(sn.owner[unplanned], minlength=self.n)
                crowded = n_unpl > bp.escape_max_unplanned_fraction * np.bincount(sn.owner, minlength=self.n)
            threat = unplanned & ~crowded[sn.owner]
            push = unplanned & crowded[sn.owner]
            # the rest (neither in the planned response nor unplanned: a neighbour cleared as common mode, or any
            # neighbour of a row off its own particle) trigger the escape only below the planned trigger
            gap = ~planned & ~unplanned & bp.escape_gap & ~crowded[sn.owner]
            if np.any(threat):
                # escape manoeuvre for the rows an unplanned vehicle threatens (backstop.escape_acc);
                # the other rows keep the planned vehicles' half-plane response below
                trig = np.where(threat, u_trig, np.where(gap, bp.trigger_m, 0.0))
                threat = threat | gap
                clear = np.where(unplanned, u_clear, min(bp.escape_planned_clear_m, bp.escape_planned_fraction * sp))
                a_esc, esc = escape_acc(own, cap_norm(a_nom, a_max), sn.states, sn.owner, threat, trig, clear, bp,
                                        self.preset.dt_s)
            if np.any(push):
                bu = replace(bp, trigger_m=u_trig, target_m=u_clear, share=bp.unplanned_share)
                da = cap_norm(da + backstop_acc(own, sn.states[push], sn.owner[push], bu), bp.a_max_m_s2)
        a, act = apply_backstop(cap_norm(a_nom, a_max), da, a_max)
        if np.any(esc):
            a, act = np.where(esc[:, None], a_esc, a), act | esc
        self.backstop_active = act
        return a

