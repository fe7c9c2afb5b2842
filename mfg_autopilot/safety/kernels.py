"""Compiled (numba) candidate evaluation of the escape manoeuvre (``backstop.escape_acc``).

The numpy formulation loops over (1 + 2 x escape_directions) first-phase candidates x 4
second-phase ones and makes ~20 small numpy calls each: ~2,700 calls per escape step for a
bank of one (~25 ms CPU with 3-10 sensed vehicles). :func:`escape_candidates` does the same
loop in one compiled call.

Bit-identical to the numpy code it replaces (``tests/test_backstop_speed.py`` checks it with
``np.array_equal`` against a verbatim copy of the old code): every quantity is computed with
the same floating-point operations in the same order - a 2-vector dot product as
x0 y0 + x1 y1 (what ``np.einsum`` and ``np.linalg.norm`` give for a trailing axis of 2), a
square as x x, sums per row in entry order from 0.0 (``np.bincount``), NaN propagated as
``np.maximum`` / ``np.minimum`` / ``np.clip`` / ``np.argmin`` do - and no fast-math (no
contraction into fused multiply-adds, no reassociation). Single-threaded; compiled code is
cached on disk (``cache=True``); :func:`warm_up` loads or compiles it before a control loop starts.

Shapes as in ``escape_acc``: m' sensed entries of the active rows, T + 1 samples, r active rows.

:func:`cbf_rows` (the crowd's barrier filter, ``backstop.cbf_acc``) replaced no numpy code: it is checked against its
constraints written out again and against the optimum on a fine grid (``tests/test_crowd_cbf.py``).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

__all__ = ["half_plane_acc", "half_plane_filter", "escape_rows", "escape_candidates", "orca_rows", "orca_select",
           "slot_claims", "formation_sums", "braking_scan", "distinct_dense", "cbf_rows"]


@njit(cache=True)
def _max(a, b):
    """np.maximum (NaN propagates)."""
    if a != a:
        return a
    if b != b:
        return b
    return a if a >= b else b


@njit(cache=True)
def _min(a, b):
    """np.minimum (NaN propagates)."""
    if a != a:
        return a
    if b != b:
        return b
    return a if a <= b else b


@njit(cache=True)
def _clip01(x):
    """np.clip(x, 0.0, 1.0) (NaN propagates)."""
    if x != x:
        return x
    y = x if x > 0.0 else 0.0
    return y if y < 1.0 else 1.0


@njit(cache=True)
def _segment_min_one(p, e, alpha, beta, a1x, a1y, a2x, a2y):
    """backstop._segment_min for one entry e of the track p (., T + 1, 2) minus the own displacement
    alpha(t) a_1 + beta(t) a_2: (dmin, segment). A command a held over the horizon is alpha = beta =
    half_t2 (0.5 t^2), a_1 = a, a_2 = 0 (the + 0.0 terms change no distance). _segment_eff_one without a tube (its
    times are not read then: alpha stands in for them)."""
    return _segment_eff_one(p, e, alpha, beta, a1x, a1y, a2x, a2y, 1.0, 0.0, 0.0, alpha)


@njit(cache=True)
def _segment_eff_one(p, e, alpha, beta, a1x, a1y, a2x, a2y, scale, g, g_max, t_seg):
    """_segment_min_one with a tube (backstop.escape_acc's ``tube``): the entry's position t seconds ahead is uncertain
    by grow(t) = min(g t^2 / 2, g_max) (g: its unknown acceleration bound), and segment s's closest distance d is read
    as d_eff = d scale / (scale + grow(t_seg[s])) (the radius at the segment's end: the larger), so that the penalty's
    scale / d_eff = (scale + grow) / d asks for the clearance ``scale`` plus the tube. (min d_eff, its segment); g = 0
    is the plain closest distance, bit for bit (t_seg is not read)."""
    T = p.shape[1] - 1
    best = 0.0
    kbest = 0
    px0 = p[e, 0, 0] - (alpha[0] * a1x + beta[0] * a2x)
    py0 = p[e, 0, 1] - (alpha[0] * a1y + beta[0] * a2y)
    for s in range(T):
        px1 = p[e, s + 1, 0] - (alpha[s + 1] * a1x + beta[s + 1] * a2x)
        py1 = p[e, s + 1, 1] - (alpha[s + 1] * a1y + beta[s + 1] * a2y)
        ddx = px1 - px0
        ddy = py1 - py0
        den = ddx * ddx + ddy * ddy
        tau = _clip01(-(px0 * ddx + py0 * ddy) / _max(den, 1e-300))
        qx = px0 + tau * ddx
        qy = py0 + tau * ddy
        dist = math.sqrt(qx * qx + qy * qy)
        if g > 0.0:
            grow = _min(0.5 * g * t_seg[s] * t_seg[s], g_max)
            if grow > 0.0:
                dist = dist * scale / (scale + grow)
        if s == 0:
            best = dist
            kbest = 0
            if dist != dist:
                return best, kbest
        elif dist != dist:
            return dist, s
        elif dist < best:
            best = dist
            kbest = s
        px0 = px1
        py0 = py1
    return best, kbest


@njit(cache=True)
def escape_candidates(rel, rel_b, b_index, e_row, wgt, clear, conflict, left, alpha, beta, t_seg, cand_fixed, a_nom_r,
                      v_hat, two_phase, urgency, tau_min_s, d_floor_m, keep_right, keep_right_den, effort_w, lateral_cost,
                      a_max2, side_r, side_w, a_max, hard_fraction, tube, tube_max):
    """The escape's choice of first-phase command per active row: (a_1 (r, 2), chosen (r,) bool).

    rel (m', T + 1, 2): constant-velocity tracks relative to the own coasting vehicle; rel_b (m_b, T + 1, 2) the
    braking ones, entry e's at b_index[e] (-1: not a threat, or a threat without the braking hypothesis); e_row (m',)
    the entry's active row; wgt, clear (m',);
    conflict (m',) bool and left (m', 2): the keep-right term; alpha, beta (T + 1,): the own displacement
    alpha a_1 + beta a_2; t_seg (T,) the segments' end times; cand_fixed (C - 1, 2): the candidates after a_nom;
    a_nom_r, v_hat (r, 2). keep_right_den = 0.5 t[-1]^2 a_max, a_max2 = a_max^2 (as the numpy code computes them).
    side_r (r, 2): the side the row passes a hovering vehicle on (a unit vector across its track, or 0);
    a candidate against it costs side_w max(0, -side_r . a_1) / a_max (guidance.controller._escape_side).
    chosen[r] is False where no candidate had a finite cost below inf (the row keeps a_nom).
    tube (m',): each entry's tube growth g (0: none; kernels._segment_eff_one with tube_max, its clearance the scale).
    hard_fraction > 0: safety first - an (a_1, a_2) is *safe* if every entry's predicted closest approach is at least
    hard_fraction x its clearance. If some a_1 has a safe a_2, the row takes the cheapest such a_1, its cost taken over
    its safe second phases only; if none has, the cheapest a_1 by the cost alone, as with hard_fraction = 0 (a least
    violation rule instead - every a_1 ranked by the violation first - carried UAVs across a crowded crossing: measured,
    docs/default_controller.md)."""
    m = rel.shape[0]
    r = a_nom_r.shape[0]
    T1 = rel.shape[1]
    n_c = cand_fixed.shape[0] + 1
    n_p = 4 if two_phase else 1
    best = np.full(r, np.inf)
    a_out = np.empty((r, 2))
    chosen = np.zeros(r, dtype=np.bool_)
    a1 = np.empty((r, 2))
    a2 = np.empty((r, 2))
    pen_best = np.empty(r)
    acc = np.empty(r)
    pen_safe = np.empty(r)
    safe = np.empty(r, dtype=np.bool_)
    best_safe = np.full(r, np.inf)
    a_safe = np.empty((r, 2))
    for c in range(n_c):
        for i in range(r):
            if c == 0:
                a1[i, 0] = a_nom_r[i, 0]
                a1[i, 1] = a_nom_r[i, 1]
            else:
                a1[i, 0] = cand_fixed[c - 1, 0]
                a1[i, 1] = cand_fixed[c - 1, 1]
            pen_best[i] = np.inf
            pen_safe[i] = np.inf
        for ph in range(n_p):
            for i in range(r):
                if n_p == 1 or ph == 3:
                    a2[i, 0] = a1[i, 0]
                    a2[i, 1] = a1[i, 1]
                elif ph == 0:
                    a2[i, 0] = a_nom_r[i, 0]
                    a2[i, 1] = a_nom_r[i, 1]
                elif ph == 1:
                    a2[i, 0] = 0.0
                    a2[i, 1] = 0.0
                else:
                    a2[i, 0] = -a1[i, 0]
                    a2[i, 1] = -a1[i, 1]
                acc[i] = 0.0
                safe[i] = True
            for e in range(m):
                i = e_row[e]
                # (tube[e] = 0: the plain closest distance, bit for bit)
                dmin, k = _segment_eff_one(rel, e, alpha, beta, a1[i, 0], a1[i, 1], a2[i, 0], a2[i, 1], clear[e],
                                           tube[e], tube_max, t_seg)
                j = b_index[e]
                if j >= 0:
                    db, kb = _segment_eff_one(rel_b, j, alpha, beta, a1[i, 0], a1[i, 1], a2[i, 0], a2[i, 1], clear[e],
                                              tube[e], tube_max, t_seg)
                    if db < dmin:
                        dmin = db
                        k = kb
                urg = tau_min_s / _max(t_seg[k], tau_min_s) if urgency else 1.0
                x = _max(0.0, clear[e] / _max(dmin, d_floor_m) - 1.0)
                pen = wgt[e] * urg * (x * x)
                if hard_fraction > 0.0 and dmin < hard_fraction * clear[e]:
                    safe[i] = False
                if conflict[e]:
                    dx = alpha[T1 - 1] * a1[i, 0] + beta[T1 - 1] * a2[i, 0]
                    dy = alpha[T1 - 1] * a1[i, 1] + beta[T1 - 1] * a2[i, 1]
                    pen = pen + keep_right * _max(0.0, left[e, 0] * dx + left[e, 1] * dy) / keep_right_den
                else:
                    pen = pen + 0.0
                acc[i] += pen
            for i in range(r):
                pen_best[i] = _min(pen_best[i], acc[i])
                if hard_fraction > 0.0 and safe[i]:
                    pen_safe[i] = _min(pen_safe[i], acc[i])
        for i in range(r):
            dax = a1[i, 0] - a_nom_r[i, 0]
            day = a1[i, 1] - a_nom_r[i, 1]
            along = dax * v_hat[i, 0] + day * v_hat[i, 1]
            effort = (along * along + lateral_cost * ((dax * dax + day * day) - along * along)) / a_max2
            side_c = side_w * _max(0.0, -(side_r[i, 0] * a1[i, 0] + side_r[i, 1] * a1[i, 1])) / a_max
            cost = pen_best[i] + effort_w * effort
            cost = cost + side_c
            if cost < best[i]:
                best[i] = cost
                a_out[i, 0] = a1[i, 0]
                a_out[i, 1] = a1[i, 1]
                chosen[i] = True
            if pen_safe[i] < np.inf:
                cost_s = pen_safe[i] + effort_w * effort
                cost_s = cost_s + side_c
                if cost_s < best_safe[i]:
                    best_safe[i] = cost_s
                    a_safe[i, 0] = a1[i, 0]
                    a_safe[i, 1] = a1[i, 1]
    for i in range(r):
        if best_safe[i] < np.inf:         # some candidate had a safe second phase
            a_out[i, 0] = a_safe[i, 0]
            a_out[i, 1] = a_safe[i, 1]
            chosen[i] = True
    return a_out, chosen


@njit(cache=True)
def _tracks(own, sensed_states, owner, ent, t, b_of, back, rel, rel_b, dist, gamma, acc0):
    """Tracks of the entries ent relative to the own coasting vehicle into rel (len(ent), T + 1, 2), d + t u, and the
    braking ones of the threats among them into rel_b (rel minus back[b_of[entry]]), in entry order. dist (n, 2): each
    row's own disturbance, held over the horizon: the own vehicle drifts 0.5 t^2 dist besides (0: coasting alone).
    gamma (T + 1,) and acc0 (n, 2): the own vehicle also moves gamma(t) acc0 with the acceleration it flies now (an
    airframe's lag: backstop.OwnModel; gamma 0 without one)."""
    T1 = t.shape[0]
    nb = 0
    for q in range(ent.shape[0]):
        e = ent[q]
        o = owner[e]
        dx = sensed_states[e, 0] - own[o, 0]
        dy = sensed_states[e, 1] - own[o, 1]
        ux = sensed_states[e, 2] - own[o, 2]
        uy = sensed_states[e, 3] - own[o, 3]
        gx = dist[o, 0]
        gy = dist[o, 1]
        fx = acc0[o, 0]
        fy = acc0[o, 1]
        for s in range(T1):
            rel[q, s, 0] = dx + t[s] * ux - 0.5 * (t[s] * t[s]) * gx - gamma[s] * fx
            rel[q, s, 1] = dy + t[s] * uy - 0.5 * (t[s] * t[s]) * gy - gamma[s] * fy
        j = b_of[e]
        if j >= 0:
            for s in range(T1):
                rel_b[nb, s, 0] = rel[q, s, 0] - back[j, s, 0]
                rel_b[nb, s, 1] = rel[q, s, 1] - back[j, s, 1]
            nb += 1
    return nb


@njit(cache=True)
def escape_rows(own, a_nom, sensed_states, owner, threat, trigger_m, clear_m, t, half_t2, alpha, beta, t_seg, cand_fixed,
                a_max, sample_s, u_noise_m_s, threat_weight, planned_weight, two_phase, urgency, tau_min_s, d_floor_m,
                keep_right, keep_right_den, effort_w, lateral_cost, a_max2, side_w, trigger_coast, side_over_keep_right,
                hard_fraction, side_pref, hover, dist, brake_hyp, gamma, acc0, tube_g, tube_max, tube_mask):
    """backstop.escape_acc before its final cap: (command (n, 2), active (n,)), for at least one sensed entry and at
    least one threat. Same operations, in the same order, as the numpy code (module docstring). hover (m,) bool: the
    hovering threat entries; with trigger_coast a row is also active if coasting (a = 0 over the horizon) brings such an
    entry below its trigger; with side_over_keep_right such an entry has no keep-right term in a row with a side. dist
    (n, 2): each row's own disturbance (the acceleration beyond its command it flies: a gust), in every prediction.
    brake_hyp (m,) bool: the threats that may also brake to a stop (the others' braking track is their constant-velocity
    one, so the minimum over both hypotheses is that one's). half_t2, alpha, beta, gamma (T + 1,) and acc0 (n, 2): the
    own vehicle's displacement half_t2 a (a held) or alpha a_1 + beta a_2, plus gamma acc0 (the acceleration it flies
    now; backstop.OwnModel). tube_g, tube_max and tube_mask (m,) bool: the threat entries read with a tube
    (_segment_eff_one) in the trigger and in the choice."""
    n = own.shape[0]
    m = sensed_states.shape[0]
    T1 = t.shape[0]
    a_out = a_nom.copy()
    active = np.zeros(n, dtype=np.bool_)
    # the threats' braking hypothesis: velocity w decays at a_max; back[j] the displacement it removes
    b_of = np.full(m, -1, dtype=np.int64)
    n_thr = 0
    for e in range(m):
        if threat[e]:
            b_of[e] = n_thr
            n_thr += 1
    ti = np.empty(n_thr, dtype=np.int64)
    back = np.empty((n_thr, T1, 2))
    for e in range(m):
        j = b_of[e]
        if j < 0:
            continue
        ti[j] = e
        if not brake_hyp[e]:
            for s in range(T1):
                back[j, s, 0] = 0.0
                back[j, s, 1] = 0.0
            continue
        wx = sensed_states[e, 2]
        wy = sensed_states[e, 3]
        wn = math.sqrt(wx * wx + wy * wy)
        hx = wx / _max(wn, 1e-12)
        hy = wy / _max(wn, 1e-12)
        ts = wn / a_max
        for s in range(T1):
            tb = _min(t[s], ts)
            c = 0.5 * a_max * (tb * tb)
            back[j, s, 0] = c * hx
            back[j, s, 1] = c * hy
    # rows whose nominal command (held) brings a threat below its trigger
    rel_t = np.empty((n_thr, T1, 2))
    rel_tb = np.empty((n_thr, T1, 2))
    _tracks(own, sensed_states, owner, ti, t, b_of, back, rel_t, rel_tb, dist, gamma, acc0)
    for j in range(n_thr):
        o = owner[ti[j]]
        # (a threat without the braking hypothesis has its braking track equal to its constant-velocity one: skipped)
        bh = brake_hyp[ti[j]]
        # a tube entry's tracks are read with the tube (the trigger plus its radius); g = 0: the plain distance
        tg = trigger_m[ti[j]]
        g = tube_g if tube_mask[ti[j]] else 0.0
        dn, _ = _segment_eff_one(rel_t, j, half_t2, half_t2, a_nom[o, 0], a_nom[o, 1], 0.0, 0.0, tg, g, tube_max, t_seg)
        if bh:
            d2, _ = _segment_eff_one(rel_tb, j, half_t2, half_t2, a_nom[o, 0], a_nom[o, 1], 0.0, 0.0, tg, g, tube_max,
                                     t_seg)
            dn = _min(dn, d2)
        if trigger_coast and hover[ti[j]]:
            d3, _ = _segment_eff_one(rel_t, j, half_t2, half_t2, 0.0, 0.0, 0.0, 0.0, tg, g, tube_max, t_seg)
            dn = _min(dn, d3)
            if bh:
                d4, _ = _segment_eff_one(rel_tb, j, half_t2, half_t2, 0.0, 0.0, 0.0, 0.0, tg, g, tube_max, t_seg)
                dn = _min(dn, d4)
        if dn < trigger_m[ti[j]]:
            active[o] = True
    r = 0
    pos = np.full(n, -1, dtype=np.int64)
    for i in range(n):
        if active[i]:
            pos[i] = r
            r += 1
    if r == 0:
        return a_out, active
    rows = np.empty(r, dtype=np.int64)
    for i in range(n):
        if active[i]:
            rows[pos[i]] = i
    n_ent = 0
    n_bt = 0
    for e in range(m):
        if active[owner[e]]:
            n_ent += 1
            if threat[e]:
                n_bt += 1
    ent = np.empty(n_ent, dtype=np.int64)
    q = 0
    for e in range(m):
        if active[owner[e]]:
            ent[q] = e
            q += 1
    rel = np.empty((n_ent, T1, 2))
    rel_b = np.empty((n_bt, T1, 2))
    _tracks(own, sensed_states, owner, ent, t, b_of, back, rel, rel_b, dist, gamma, acc0)
    e_row = np.empty(n_ent, dtype=np.int64)
    tube = np.zeros(n_ent)
    b_index = np.full(n_ent, -1, dtype=np.int64)
    wgt = np.empty(n_ent)
    clear = np.empty(n_ent)
    conflict = np.zeros(n_ent, dtype=np.bool_)
    left = np.empty((n_ent, 2))
    nb = 0
    for q in range(n_ent):
        e = ent[q]
        o = owner[e]
        e_row[q] = pos[o]
        clear[q] = clear_m[e]
        if threat[e] and tube_mask[e]:
            tube[q] = tube_g
        wgt[q] = threat_weight if threat[e] else planned_weight
        # 'keep right': the approach's velocity from the first segment, -u rotated +90 deg
        usx = rel[q, 1, 0] - rel[q, 0, 0]
        usy = rel[q, 1, 1] - rel[q, 0, 1]
        usx = usx / sample_s
        usy = usy / sample_s
        un = math.sqrt(usx * usx + usy * usy)
        left[q, 0] = usy / _max(un, 1e-12)
        left[q, 1] = -usx / _max(un, 1e-12)
        dn, _ = _segment_min_one(rel, q, half_t2, half_t2, a_nom[o, 0], a_nom[o, 1], 0.0, 0.0)
        if threat[e]:
            if brake_hyp[e]:            # else its braking track is its constant-velocity one: b_index -1, not evaluated
                b_index[q] = nb
                db, _ = _segment_min_one(rel_b, nb, half_t2, half_t2, a_nom[o, 0], a_nom[o, 1], 0.0, 0.0)
                dn = _min(dn, db)
            nb += 1
        conflict[q] = (dn < clear[q]) and (un > u_noise_m_s)
        if side_over_keep_right and hover[e] and (side_pref[o, 0] != 0.0 or side_pref[o, 1] != 0.0):
            conflict[q] = False
    a_nom_r = np.empty((r, 2))
    v_hat = np.empty((r, 2))
    side_r = np.empty((r, 2))
    for k in range(r):
        i = rows[k]
        a_nom_r[k, 0] = a_nom[i, 0]
        a_nom_r[k, 1] = a_nom[i, 1]
        side_r[k, 0] = side_pref[i, 0]
        side_r[k, 1] = side_pref[i, 1]
        vx = own[i, 2]
        vy = own[i, 3]
        vn = math.sqrt(vx * vx + vy * vy)
        if vn > u_noise_m_s:
            v_hat[k, 0] = vx / _max(vn, 1e-12)
            v_hat[k, 1] = vy / _max(vn, 1e-12)
        else:
            v_hat[k, 0] = 0.0
            v_hat[k, 1] = 0.0
    a_best, chosen = escape_candidates(rel, rel_b, b_index, e_row, wgt, clear, conflict, left, alpha, beta, t_seg, cand_fixed,
                                       a_nom_r, v_hat, two_phase, urgency, tau_min_s, d_floor_m, keep_right, keep_right_den,
                                       effort_w, lateral_cost, a_max2, side_r, side_w, a_max, hard_fraction, tube,
                                       tube_max)
    for k in range(r):
        if chosen[k]:
            a_out[rows[k], 0] = a_best[k, 0]
            a_out[rows[k], 1] = a_best[k, 1]
    return a_out, active


@njit(cache=True)
def _cap_row(ax, ay, limit):
    """planner.cap_norm for one row: a * min(1, limit / max(|a|, 1e-300))."""
    f = _min(1.0, limit / _max(math.sqrt(ax * ax + ay * ay), 1e-300))
    return ax * f, ay * f


@njit(cache=True)
def half_plane_acc(own, sensed_states, owner, n, horizon_s, u_noise2, trigger_m, target_m, share, tau_min_s, a_max,
                   select, has_select):
    """backstop.backstop_acc (its docstring): the correction delta_a (n, 2). u_noise2 = u_noise_m_s ** 2 as Python computes it;
    trigger_m, target_m per sensed entry (m,). With has_select, only the entries p with select[p] (m,) count: the same
    numbers as passing sensed_states[select] (the sums run in the same order), without the copy."""
    out = np.zeros((n, 2))
    m = sensed_states.shape[0]
    any_act = False
    for p in range(m):
        if has_select and not select[p]:
            continue
        o = owner[p]
        dx = sensed_states[p, 0] - own[o, 0]
        dy = sensed_states[p, 1] - own[o, 1]
        ux = sensed_states[p, 2] - own[o, 2]
        uy = sensed_states[p, 3] - own[o, 3]
        uu = ux * ux + uy * uy
        tau = -(dx * ux + dy * uy) / _max(uu, 1e-12)
        if tau == tau:                                   # np.clip(tau, 0, horizon_s)
            tau = tau if tau > 0.0 else 0.0
            tau = tau if tau < horizon_s else horizon_s
        if not uu >= u_noise2:
            tau = 0.0
        cx = dx + tau * ux
        cy = dy + tau * uy
        rho = math.sqrt(cx * cx + cy * cy)
        act = rho < trigger_m[p]
        any_act = any_act or act
        un = math.sqrt(uu)
        if rho > 1e-6:
            nx = cx / _max(rho, 1e-12)
            ny = cy / _max(rho, 1e-12)
        elif un > 1e-9:
            nx = -uy / _max(un, 1e-12)
            ny = ux / _max(un, 1e-12)
        else:
            nx = 1.0
            ny = 0.0
        mag = 0.0
        if act:
            tm = _max(tau, tau_min_s)
            mag = share * 2.0 * (target_m[p] - rho) / (tm * tm)
        out[o, 0] += -mag * nx
        out[o, 1] += -mag * ny
    if not any_act:
        return np.zeros((n, 2))
    for i in range(n):
        out[i, 0], out[i, 1] = _cap_row(out[i, 0], out[i, 1], a_max)
    return out


@njit(cache=True)
def half_plane_filter(a_nom, delta_a, a_max, a_max2):
    """backstop.apply_backstop (its docstring): (command (n, 2), active (n,)). a_max2 = a_max ** 2 as Python computes it."""
    n = a_nom.shape[0]
    a = np.empty((n, 2))
    active = np.zeros(n, dtype=np.bool_)
    for i in range(n):
        dx = delta_a[i, 0]
        dy = delta_a[i, 1]
        a_req = math.sqrt(dx * dx + dy * dy)
        ax = a_nom[i, 0]
        ay = a_nom[i, 1]
        if a_req > 0:
            active[i] = True
            nx = dx / _max(a_req, 1e-300)
            ny = dy / _max(a_req, 1e-300)
            a_n_nom = ax * nx + ay * ny
            a_n = _min(_max(a_req, a_n_nom), a_max)
            tx = ax - a_n_nom * nx
            ty = ay - a_n_nom * ny
            tx, ty = _cap_row(tx, ty, math.sqrt(_max(a_max2 - a_n * a_n, 0.0)))
            ax = a_n * nx + tx
            ay = a_n * ny + ty
        a[i, 0], a[i, 1] = _cap_row(ax, ay, a_max)
    return a, active



# --- ORCA (safety/orca.py): RVO2's Agent::computeNewVelocity for every row of a bank in one call ------------------------
#
# A line-by-line port of RVO2 2.x (src/Agent.cc: the agent ORCA lines, linearProgram1/2/3; src/Vector2.cc) without
# obstacles, in RVO2's own arithmetic: float32 throughout (its Vector2 holds floats), every literal a float32, a vector
# divided by a scalar as RVO2 does it (times 1 / s), no fused multiply-add. So a row gives RVO2's float32 result, not a
# float64 approximation of it (tests/test_orca.py measures the agreement with pyrvo).
# A line is a row of a (k, 4) float32 array: point x, point y, direction x, direction y.

_F0 = np.float32(0.0)
_F05 = np.float32(0.5)
_F1 = np.float32(1.0)
_RVO_EPSILON = np.float32(1e-5)


@njit(cache=True)
def _lp1(lines, line_no, radius, opt_x, opt_y, direction_opt, res_x, res_y):
    """RVO2 linearProgram1: (ok, result x, result y); on failure the result passed in."""
    px = lines[line_no, 0]
    py = lines[line_no, 1]
    dx = lines[line_no, 2]
    dy = lines[line_no, 3]
    dot = px * dx + py * dy
    disc = dot * dot + radius * radius - (px * px + py * py)
    if disc < _F0:
        return False, res_x, res_y                 # the max-speed circle invalidates the line
    sq = np.sqrt(disc)
    t_left = -dot - sq
    t_right = -dot + sq
    for i in range(line_no):
        denom = dx * lines[i, 3] - dy * lines[i, 2]
        numer = lines[i, 2] * (py - lines[i, 1]) - lines[i, 3] * (px - lines[i, 0])
        if abs(denom) <= _RVO_EPSILON:
            if numer < _F0:                        # (almost) parallel lines
                return False, res_x, res_y
            continue
        t = numer / denom
        if denom >= _F0:
            t_right = t if t < t_right else t_right     # std::min(t_right, t)
        else:
            t_left = t if t_left < t else t_left        # std::max(t_left, t)
        if t_left > t_right:
            return False, res_x, res_y
    if direction_opt:
        if opt_x * dx + opt_y * dy > _F0:
            return True, px + t_right * dx, py + t_right * dy
        return True, px + t_left * dx, py + t_left * dy
    t = dx * (opt_x - px) + dy * (opt_y - py)
    if t < t_left:
        return True, px + t_left * dx, py + t_left * dy
    if t > t_right:
        return True, px + t_right * dx, py + t_right * dy
    return True, px + t * dx, py + t * dy


@njit(cache=True)
def _lp2(lines, n_lines, radius, opt_x, opt_y, direction_opt):
    """RVO2 linearProgram2: (index of the first line that failed or n_lines, result x, result y)."""
    if direction_opt:
        rx = opt_x * radius
        ry = opt_y * radius
    elif opt_x * opt_x + opt_y * opt_y > radius * radius:
        inv = _F1 / np.sqrt(opt_x * opt_x + opt_y * opt_y)
        rx = (opt_x * inv) * radius
        ry = (opt_y * inv) * radius
    else:
        rx = opt_x
        ry = opt_y
    for i in range(n_lines):
        if lines[i, 2] * (lines[i, 1] - ry) - lines[i, 3] * (lines[i, 0] - rx) > _F0:
            ok, nx, ny = _lp1(lines, i, radius, opt_x, opt_y, direction_opt, rx, ry)
            if not ok:
                return i, rx, ry
            rx = nx
            ry = ny
    return n_lines, rx, ry


@njit(cache=True)
def _lp3(lines, n_lines, begin_line, radius, rx, ry, proj):
    """RVO2 linearProgram3 (no obstacle lines): the velocity that least violates the lines; proj is scratch (>= n_lines, 4)."""
    distance = _F0
    for i in range(begin_line, n_lines):
        pix = lines[i, 0]
        piy = lines[i, 1]
        dix = lines[i, 2]
        diy = lines[i, 3]
        if dix * (piy - ry) - diy * (pix - rx) > distance:
            n_proj = 0
            for j in range(i):
                pjx = lines[j, 0]
                pjy = lines[j, 1]
                djx = lines[j, 2]
                djy = lines[j, 3]
                determinant = dix * djy - diy * djx
                if abs(determinant) <= _RVO_EPSILON:
                    if dix * djx + diy * djy > _F0:
                        continue                   # parallel, same direction
                    qx = _F05 * (pix + pjx)
                    qy = _F05 * (piy + pjy)
                else:
                    s = (djx * (piy - pjy) - djy * (pix - pjx)) / determinant
                    qx = pix + s * dix
                    qy = piy + s * diy
                ex = djx - dix
                ey = djy - diy
                inv = _F1 / np.sqrt(ex * ex + ey * ey)
                proj[n_proj, 0] = qx
                proj[n_proj, 1] = qy
                proj[n_proj, 2] = ex * inv
                proj[n_proj, 3] = ey * inv
                n_proj += 1
            fail, nx, ny = _lp2(proj, n_proj, radius, -diy, dix, True)
            if fail >= n_proj:                     # else: floating-point failure, RVO2 keeps the result
                rx = nx
                ry = ny
            distance = dix * (piy - ry) - diy * (pix - rx)
    return rx, ry


@njit(cache=True)
def orca_rows(rel, vel, bounds, own_v, v_pref, radius_m, time_horizon_s, time_step_s, max_speed_m_s):
    """(ORCA's new velocity (r, 2), infeasible (r,): linearProgram3 ran) of r rows, each computed as RVO2's
    Agent::computeNewVelocity (float32) for an agent at the origin with velocity own_v[k] and preferred velocity v_pref[k] (r, 2), radius, time horizon, max speed of the
    arguments, and the neighbours bounds[k]:bounds[k + 1] of rel, vel (m, 2) (positions relative to the own agent,
    velocities; each neighbour's radius radius_m). The neighbours are taken nearest first by their float32 squared
    distance (RVO2's insertion order; ties in the given order)."""
    r = own_v.shape[0]
    out = np.empty((r, 2))
    infeasible = np.zeros(r, dtype=np.bool_)
    k_max = 1
    for k in range(r):
        k_max = max(k_max, bounds[k + 1] - bounds[k])
    lines = np.empty((k_max, 4), dtype=np.float32)
    proj = np.empty((k_max, 4), dtype=np.float32)
    order = np.empty(k_max, dtype=np.int64)
    dist = np.empty(k_max, dtype=np.float32)
    radius = np.float32(radius_m)
    max_speed = np.float32(max_speed_m_s)
    inv_th = _F1 / np.float32(time_horizon_s)
    inv_ts = _F1 / np.float32(time_step_s)
    cr = radius + radius
    cr_sq = cr * cr
    for k in range(r):
        lo = bounds[k]
        n = bounds[k + 1] - lo
        vx = np.float32(own_v[k, 0])
        vy = np.float32(own_v[k, 1])
        # RVO2's agentNeighbors_: sorted by insertion on distSq (strict <: stable)
        for q in range(n):
            px = np.float32(rel[lo + q, 0])
            py = np.float32(rel[lo + q, 1])
            d2 = px * px + py * py
            i = q
            while i > 0 and d2 < dist[i - 1]:
                dist[i] = dist[i - 1]
                order[i] = order[i - 1]
                i -= 1
            dist[i] = d2
            order[i] = lo + q
        for q in range(n):
            e = order[q]
            px = np.float32(rel[e, 0])
            py = np.float32(rel[e, 1])
            rvx = vx - np.float32(vel[e, 0])
            rvy = vy - np.float32(vel[e, 1])
            dist_sq = px * px + py * py
            if dist_sq > cr_sq:
                # no collision: w from the cut-off centre to the relative velocity
                wx = rvx - inv_th * px
                wy = rvy - inv_th * py
                w_len_sq = wx * wx + wy * wy
                dot = wx * px + wy * py
                if dot < _F0 and dot * dot > cr_sq * w_len_sq:
                    # project on the cut-off circle
                    w_len = np.sqrt(w_len_sq)
                    inv = _F1 / w_len
                    uwx = wx * inv
                    uwy = wy * inv
                    dirx = uwy
                    diry = -uwx
                    s = cr * inv_th - w_len
                    ux = s * uwx
                    uy = s * uwy
                else:
                    # project on the legs
                    leg = np.sqrt(dist_sq - cr_sq)
                    inv = _F1 / dist_sq
                    if px * wy - py * wx > _F0:           # left leg
                        dirx = (px * leg - py * cr) * inv
                        diry = (px * cr + py * leg) * inv
                    else:                                 # right leg
                        dirx = -((px * leg + py * cr) * inv)
                        diry = -(((-px) * cr + py * leg) * inv)
                    dp = rvx * dirx + rvy * diry
                    ux = dp * dirx - rvx
                    uy = dp * diry - rvy
            else:
                # collision: project on the cut-off circle of time time_step
                wx = rvx - inv_ts * px
                wy = rvy - inv_ts * py
                w_len = np.sqrt(wx * wx + wy * wy)
                inv = _F1 / w_len
                uwx = wx * inv
                uwy = wy * inv
                dirx = uwy
                diry = -uwx
                s = cr * inv_ts - w_len
                ux = s * uwx
                uy = s * uwy
            lines[q, 0] = vx + _F05 * ux
            lines[q, 1] = vy + _F05 * uy
            lines[q, 2] = dirx
            lines[q, 3] = diry
        fail, rx, ry = _lp2(lines, n, max_speed, np.float32(v_pref[k, 0]), np.float32(v_pref[k, 1]), False)
        if fail < n:
            infeasible[k] = True
            rx, ry = _lp3(lines, n, fail, max_speed, rx, ry, proj)
        out[k, 0] = rx
        out[k, 1] = ry
    return out, infeasible


@njit(cache=True)
def orca_select(own, sensed_states, owner, ids, n, nd2, max_neighbours):
    """orca.select_neighbours (its docstring) in one pass: indices into the sensed entries (m,) of each row's neighbours,
    rows ascending, within a row by (d2, id, entry index) ascending, at most max_neighbours per row, d2 < nd2 the float64
    squared distance dx dx + dy dy (as numpy's d ** 2 sums). ids (m,) int64 (zeros where the ids are unknown)."""
    m = sensed_states.shape[0]
    cnt = np.zeros(n + 1, dtype=np.int64)
    d2 = np.empty(m)
    for e in range(m):
        o = owner[e]
        dx = sensed_states[e, 0] - own[o, 0]
        dy = sensed_states[e, 1] - own[o, 1]
        d2[e] = dx * dx + dy * dy
        if d2[e] < nd2:
            cnt[o + 1] += 1
    for i in range(n):
        cnt[i + 1] += cnt[i]
    cand = np.empty(cnt[n], dtype=np.int64)              # candidates grouped by row, entry order within a row
    fill = cnt[:n].copy()
    for e in range(m):
        if d2[e] < nd2:
            o = owner[e]
            cand[fill[o]] = e
            fill[o] += 1
    out = np.empty(cnt[n], dtype=np.int64)
    n_out = 0
    for i in range(n):
        lo = cnt[i]
        hi = cnt[i + 1]
        k = 0                                            # out[n_out:n_out + k]: the row's best so far, sorted
        for q in range(lo, hi):
            e = cand[q]
            if k == max_neighbours:
                last = out[n_out + k - 1]
                if not (d2[e] < d2[last] or (d2[e] == d2[last] and ids[e] < ids[last])):
                    continue                             # not better than the worst kept (index order: e is later)
                k -= 1
            j = k
            while j > 0:
                prev = out[n_out + j - 1]
                if d2[e] < d2[prev] or (d2[e] == d2[prev] and ids[e] < ids[prev]):
                    out[n_out + j] = prev
                    j -= 1
                else:
                    break
            out[n_out + j] = e
            k += 1
        n_out += k
    return out[:n_out].copy()


@njit(cache=True)
def slot_claims(owner, states, own_p, parked, ps2, thr2):
    """(m,) bool: the MFG backstop's own-slot claim (``guidance.controller._backstop_rows``): entry p's sensed state
    (states (m, 4)) is within the claim radius of its owner row's own particle own_p (n, 4), that particle parked
    (parked (n,)), in the plan metric |dr|^2 + ps2 |dv|^2 < thr2 (the numpy formulation's numbers, in its order)."""
    m = states.shape[0]
    out = np.zeros(m, dtype=np.bool_)
    for p in range(m):
        o = owner[p]
        if not parked[o]:
            continue
        d0 = states[p, 0] - own_p[o, 0]
        d1 = states[p, 1] - own_p[o, 1]
        d2 = states[p, 2] - own_p[o, 2]
        d3 = states[p, 3] - own_p[o, 3]
        out[p] = (d0 * d0 + d1 * d1) + ps2 * (d2 * d2 + d3 * d3) < thr2
    return out


@njit(cache=True)
def formation_sums(owner, ids, states, own_states, own_err, sid, spart, plan_states, own_index, n, r_max, out_m, ps, pre_r):
    """The sums behind the MFG tracking's formation mean (``guidance.controller._formation_error``), in one pass over
    the m sensed entries (owner (m,), ids (m,), states (m, 4)): an entry counts for its owner row if its id is a plan
    particle j (sid sorted, spart the particle of each), j's plan position is within r_max of the owner's own particle
    (own_index), and its deviation from j differs from the owner's own deviation own_err by at most out_m in the plan
    metric |dr|^2 + (ps |dv|)^2; entries farther than pre_r from the owner's observed position (own_states) are
    skipped first (they cannot count: docstring of the caller). Returns (sums (n, 4) of states - plan_states[j] per
    row, from 0.0 in entry order as np.bincount gives them; counts (n,) of entries that counted)."""
    sums = np.zeros((n, 4))
    cnt = np.zeros(n, dtype=np.int64)
    m = owner.shape[0]
    n_sid = sid.shape[0]
    r2, o2, p2 = r_max * r_max, out_m * out_m, pre_r * pre_r
    for k in range(m):
        i = owner[k]
        dx0 = states[k, 0] - own_states[i, 0]
        dy0 = states[k, 1] - own_states[i, 1]
        if not (dx0 * dx0 + dy0 * dy0 <= p2):
            continue
        at = np.searchsorted(sid, ids[k])
        if at >= n_sid:
            at = n_sid - 1
        if sid[at] != ids[k]:
            continue
        j = spart[at]
        q = own_index[i]
        drx = plan_states[j, 0] - plan_states[q, 0]
        dry = plan_states[j, 1] - plan_states[q, 1]
        if not (drx * drx + dry * dry <= r2):
            continue
        d0 = states[k, 0] - plan_states[j, 0] - own_err[i, 0]
        d1 = states[k, 1] - plan_states[j, 1] - own_err[i, 1]
        d2 = states[k, 2] - plan_states[j, 2] - own_err[i, 2]
        d3 = states[k, 3] - plan_states[j, 3] - own_err[i, 3]
        if not (d0 ** 2 + d1 ** 2 + ps * ps * (d2 ** 2 + d3 ** 2) <= o2):
            continue
        cnt[i] += 1
        for c in range(4):
            sums[i, c] += states[k, c] - plan_states[j, c]
    return sums, cnt


@njit(cache=True)
def braking_scan(owner, part, states, unplanned, n, seen_v, seen_k, full, has_full, a_plan, do_test, own_ref,
                 has_own_ref, step, dt, brake_min):
    """The per-entry part of the MFG braking test (guidance.controller.DefaultMFGController._unplanned_by_braking and
    braking_off_plan) in one pass, with the same floating-point operations in the same order.

    Entries e (m sensed (row, vehicle) pairs: owner, plan particle part (-1: not in the plan), states (m, 4),
    unplanned (m,)): a candidate is an entry on the plan whose row senses no unplanned vehicle yet, with a previous
    velocity sample - seen_v[part] if seen_k[part] == step - 1, else full[part, 2:4] when has_full. Its deviation
    acceleration a_dev = (v - v_prev) / dt - a_plan[part] brakes along v_prev by more than brake_min (and, when
    has_own_ref, by more than brake_min relative to the observing row's own_ref (n, 2): the common mode, see
    DefaultMFGController._unplanned_by_braking). Returns
    (entries (k,), their states shifted by one more period of a_dev (k, 4)); then records every planned entry's
    velocity as seen at ``step`` (seen_v, seen_k updated in place). do_test False: only the recording."""
    m = owner.shape[0]
    idx = np.empty(m, dtype=np.int64)
    sh = np.empty((m, 4))
    k = 0
    if do_test:
        quiet = np.ones(n, dtype=np.bool_)
        for e in range(m):
            if unplanned[e]:
                quiet[owner[e]] = False
        c2 = 0.5 * dt * dt
        for e in range(m):
            p = part[e]
            if p < 0 or unplanned[e] or not quiet[owner[e]]:
                continue
            if seen_k[p] == step - 1:
                vp0, vp1 = seen_v[p, 0], seen_v[p, 1]
            elif has_full:
                vp0, vp1 = full[p, 2], full[p, 3]
            else:
                continue
            ad0 = (states[e, 2] - vp0) / dt - a_plan[p, 0]
            ad1 = (states[e, 3] - vp1) / dt - a_plan[p, 1]
            speed = math.sqrt(vp0 * vp0 + vp1 * vp1)
            den = max(speed, 1e-9)
            if not ((ad0 * vp0 + ad1 * vp1) / den < -brake_min and speed > brake_min * dt):
                continue
            if has_own_ref:
                o = owner[e]
                r0 = ad0 - own_ref[o, 0]
                r1 = ad1 - own_ref[o, 1]
                if not ((r0 * vp0 + r1 * vp1) / den < -brake_min):
                    continue
            idx[k] = e
            sh[k, 0] = states[e, 0] + c2 * ad0
            sh[k, 1] = states[e, 1] + c2 * ad1
            sh[k, 2] = states[e, 2] + dt * ad0
            sh[k, 3] = states[e, 3] + dt * ad1
            k += 1
    for e in range(m):
        p = part[e]
        if p >= 0:
            seen_v[p, 0] = states[e, 2]
            seen_v[p, 1] = states[e, 3]
            seen_k[p] = step
    return idx[:k].copy(), sh[:k].copy()


@njit(cache=True)
def distinct_dense(q, ids, size):
    """guidance.controller.DefaultMFGController._distinct for small non-negative ids (every id < size), in two passes
    without a sort: (first (u,), inv (m,), ok). first: one entry per distinct id, ids ascending (its first entry);
    inv: each entry's rank among the distinct ids (q[first][inv] is q when ok); ok False when two entries of one id
    carry different states (compared value by value with ==, so a NaN differs from itself, as np.array_equal); then
    first and inv are empty."""
    m = ids.shape[0]
    rep = np.full(size, -1, dtype=np.int64)
    u = 0
    for e in range(m):
        i = ids[e]
        r = rep[i]
        for c in range(q.shape[1]):
            # an id's first entry is checked for NaN (np.array_equal: NaN != NaN), the others against it
            if (r < 0 and q[e, c] != q[e, c]) or (r >= 0 and not (q[e, c] == q[r, c])):
                return np.empty(0, dtype=np.int64), np.empty(0, dtype=np.int64), False
        if r < 0:
            rep[i] = e
            u += 1
    first = np.empty(u, dtype=np.int64)
    rank = np.empty(size, dtype=np.int64)
    u = 0
    for i in range(size):
        if rep[i] >= 0:
            first[u] = rep[i]
            rank[i] = u
            u += 1
    inv = np.empty(m, dtype=np.int64)
    for e in range(m):
        inv[e] = rank[ids[e]]
    return first, inv, True


@njit(cache=True)
def _cbf_violation(cx, cy, phx, phy, rhs, K):
    """max_k (rhs_k - ph_k . c): how far the command c misses the most violated constraint (<= 0: all hold)."""
    v = -np.inf
    for k in range(K):
        w = rhs[k] - (phx[k] * cx + phy[k] * cy)
        if w > v:
            v = w
    return v


@njit(cache=True)
def _cbf_consider(cx, cy, ax, ay, phx, phy, rhs, K, lim2, best):
    """Keep the candidate c in best (violation, squared distance to a_nom, c) if it is within the disc and misses the
    most violated constraint by less (to 1e-9), or by as little and is nearer a_nom."""
    if not cx * cx + cy * cy <= lim2:
        return
    v = _cbf_violation(cx, cy, phx, phy, rhs, K)
    if v < 1e-9:
        v = 0.0
    d = (cx - ax) * (cx - ax) + (cy - ay) * (cy - ay)
    if v < best[0] - 1e-9 or (v <= best[0] + 1e-9 and d < best[1]):
        best[0] = v
        best[1] = d
        best[2] = cx
        best[3] = cy


@njit(cache=True)
def _cbf_circle(nx, ny, c, a_max, ax, ay, phx, phy, rhs, K, lim2, best):
    """Consider the two points where the line n . a = c (|n| = 1) crosses the circle |a| = a_max."""
    t2 = a_max * a_max - c * c
    if t2 < 0.0:
        return
    t = math.sqrt(t2)
    _cbf_consider(c * nx - t * ny, c * ny + t * nx, ax, ay, phx, phy, rhs, K, lim2, best)
    _cbf_consider(c * nx + t * ny, c * ny - t * nx, ax, ay, phx, phy, rhs, K, lim2, best)


@njit(cache=True)
def cbf_rows(own, a_nom, sensed_states, order, starts, ends, rows, a_max, alpha, gamma, ds, share, k_max, disc, own_dist,
             inside_no_approach):
    """backstop.cbf_acc (its docstring): the filtered command per row of ``rows`` and whether it differs from a_nom.
    order / starts / ends: the sensed entries of row rows[q] are order[starts[q]:ends[q]]; share (m,): each entry's
    share of its constraint; disc (S, 2): unit-disc samples; own_dist (n, 2): each row's own disturbance, which the
    command's share must also make up for (ph . (a + dist) >= rhs); inside_no_approach: inside ds the constraint's
    B is at least 0 (BackstopParams.crowd_cbf_inside_no_approach)."""
    r = rows.shape[0]
    out = np.empty((r, 2))
    active = np.zeros(r, dtype=np.bool_)
    phx = np.empty(k_max)
    phy = np.empty(k_max)
    rhs = np.empty(k_max)
    best = np.empty(4)                  # violation, squared distance to a_nom, command
    for q in range(r):
        i = rows[q]
        ax = a_nom[i, 0]
        ay = a_nom[i, 1]
        out[q, 0] = ax
        out[q, 1] = ay
        # the constraints that can bind (rhs > -a_max: ph . a >= rhs holds for every |a| <= a_max otherwise),
        # the k_max most demanding of them (largest rhs) if there are more
        K = 0
        for p in range(starts[q], ends[q]):
            e = order[p]
            dx = own[i, 0] - sensed_states[e, 0]
            dy = own[i, 1] - sensed_states[e, 1]
            vx = own[i, 2] - sensed_states[e, 2]
            vy = own[i, 3] - sensed_states[e, 3]
            dist = math.sqrt(dx * dx + dy * dy)
            if dist < 1e-6:
                dist = 1e-6
            nx = dx / dist
            ny = dy / dist
            rdot = nx * vx + ny * vy
            gap = dist - ds
            inside = gap < 1e-6
            if inside:
                gap = 1e-6
            root = math.sqrt(4.0 * alpha * gap)
            h = root + rdot
            b = -gamma * h * h * h - (vx * vx + vy * vy) / dist + rdot * rdot / dist - 2.0 * alpha * rdot / root
            if inside and inside_no_approach and b < 0.0:
                b = 0.0             # h is undefined inside ds: accelerate no closer, opening or not
            b = share[e] * b - (nx * own_dist[i, 0] + ny * own_dist[i, 1])
            if not b > -a_max:
                continue
            if K < k_max:
                phx[K] = nx
                phy[K] = ny
                rhs[K] = b
                K += 1
            else:
                lo = 0
                for k in range(1, K):
                    if rhs[k] < rhs[lo]:
                        lo = k
                if b > rhs[lo]:
                    phx[lo] = nx
                    phy[lo] = ny
                    rhs[lo] = b
        if K == 0 or _cbf_violation(ax, ay, phx, phy, rhs, K) <= 0.0:
            continue
        active[q] = True
        lim2 = a_max * a_max * (1.0 + 1e-9)
        best[0] = np.inf
        best[1] = np.inf
        # candidates, where a 2-D optimum lies: for the nearest command meeting every constraint, a_nom's projection on
        # each constraint line, the lines' crossings with the disc |a| = a_max and with each other; for the least
        # violating one when none does (min over the disc of max_k rhs_k - ph_k . a), a_max ph_k, the disc crossings
        # of the lines where two violations are equal, and the points where three are; then a sampled disc
        for k in range(K):
            w = rhs[k] - (phx[k] * ax + phy[k] * ay)
            if w < 0.0:
                w = 0.0
            _cbf_consider(ax + w * phx[k], ay + w * phy[k], ax, ay, phx, phy, rhs, K, lim2, best)
            _cbf_circle(phx[k], phy[k], rhs[k], a_max, ax, ay, phx, phy, rhs, K, lim2, best)
            _cbf_consider(a_max * phx[k], a_max * phy[k], ax, ay, phx, phy, rhs, K, lim2, best)
            for l in range(k + 1, K):
                det = phx[k] * phy[l] - phy[k] * phx[l]
                if abs(det) > 1e-12:
                    _cbf_consider((rhs[k] * phy[l] - phy[k] * rhs[l]) / det, (phx[k] * rhs[l] - rhs[k] * phx[l]) / det,
                                  ax, ay, phx, phy, rhs, K, lim2, best)
                ex = phx[k] - phx[l]
                ey = phy[k] - phy[l]
                en = math.sqrt(ex * ex + ey * ey)
                if en > 1e-12:
                    _cbf_circle(ex / en, ey / en, (rhs[k] - rhs[l]) / en, a_max, ax, ay, phx, phy, rhs, K, lim2, best)
                    for m in range(l + 1, K):
                        fx = phx[k] - phx[m]
                        fy = phy[k] - phy[m]
                        det3 = ex * fy - ey * fx
                        if abs(det3) > 1e-12:
                            g1 = rhs[k] - rhs[l]
                            g2 = rhs[k] - rhs[m]
                            _cbf_consider((g1 * fy - ey * g2) / det3, (ex * g2 - g1 * fx) / det3, ax, ay, phx, phy, rhs, K,
                                          lim2, best)
        for c in range(disc.shape[0]):
            _cbf_consider(a_max * disc[c, 0], a_max * disc[c, 1], ax, ay, phx, phy, rhs, K, lim2, best)
        bx = best[2]
        by = best[3]
        out[q, 0] = bx
        out[q, 1] = by
    return out, active
