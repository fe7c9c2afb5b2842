"""The ``default`` preset: the product controller for both modes (issue 7).

MFG (``DefaultMFGController``), per UAV, with no communication after t = 0:
  1. t = 0 exchange: the N states and sites -> slots and the interacting mean-field plan
     (:class:`~mfg_autopilot.guidance.planner.MeanFieldPlan`; identical on every UAV).
  2. each step: own plan particle s_plan (N particles advanced once per control period),
     tracking error e = s - s_plan (leashed), the HJB value model psi = w_H^T sigma_H(e)
     (w_H(0) = the Riccati value of the tracking cost, then Algorithm 3/4's online NGD
     update against phi_G(s, m_hat) weighted by the FPK model),
     a = a_plan + a* with a* = -(1/(2 c3)) B^T grad psi (eq. 8, erratum 1 sign), capped;
  3. the proximity backstop (:mod:`~mfg_autopilot.safety.backstop`) with priority.
HJB_d (``DefaultHJBController``): slots from the first step's heard states, the same goal
term and closest-approach repulsion against the neighbours actually heard each step
(priority saturation), and the same backstop.

A bank row's output depends only on its own observation, what it heard/sensed, and the
t = 0 exchange; the plan is computed once per bank from the exchanged states only.
Parameters: :mod:`~mfg_autopilot.guidance.params`. Design and measurements:
``docs/default_controller.md``.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from scipy.spatial import cKDTree

from mfg_autopilot.guidance.detour import detour_offset, detour_onset, detour_side
from mfg_autopilot.guidance.disturbance import disturbance_residual_m_s2, shrink_m_s2
from mfg_autopilot.guidance.params import DefaultPreset
from mfg_autopilot.guidance.planner import MeanFieldPlan, combine_priority, goal_acc, repulsion_from_neighbours
from mfg_autopilot.guidance.group_plan import GroupPlan, group_plan_for
from mfg_autopilot.guidance.rigid_plan import RigidPlan, rigid_plan_for
from mfg_autopilot.interface import HeardSummary, Neighbours, Observation, StepInfo
from mfg_autopilot.paper import kernels
from mfg_autopilot.paper.features import make_sigma_F, make_sigma_H
from mfg_autopilot.paper.learners import hjb_update
from mfg_autopilot.paper.meanfield import fit_initial_fpk_weights
from mfg_autopilot.paper.model import cap_norm, lqr_value_weights, nominal_drift, optimal_action
from mfg_autopilot.paper.params import Preset
from mfg_autopilot.safety import backstop
from mfg_autopilot.safety.backstop import (Layer, apply_backstop, backstop_acc, behind_row, cannot_brake_short, cbf_acc,
                                          escape_acc)
from mfg_autopilot.safety.kernels import braking_scan, distinct_dense, formation_sums, slot_claims

__all__ = ["DefaultMFGController", "DefaultHJBController"]


def _sensed(obs: Observation) -> Neighbours:
    return obs.sensed if obs.sensed is not None else Neighbours.empty()


def _dense_ids(ids: np.ndarray) -> bool:
    """Vehicle ids (int64, non-empty) small and non-negative enough to index a table of max id + 1 entries (the
    simulator's 0..N-1): a gather then replaces a sort or a binary search."""
    return bool(ids.min() >= 0 and ids.max() < 4 * ids.size + 1024)


def _kernel_arg(a: np.ndarray, dtype) -> np.ndarray:
    """a as a writable C-contiguous array of dtype (a copy only if it is not one): the types the compiled kernels were
    warmed up with (a read-only or strided array would compile a new specialisation inside a control step)."""
    a = np.ascontiguousarray(a, dtype=dtype)
    return a if a.flags.writeable else a.copy()


def nearest_per_row(rows: np.ndarray, d_m: np.ndarray) -> np.ndarray:
    """Indices of each row's nearest entry: rows (m,) the row of each entry, d_m (m, 2) its offset from that row's
    vehicle; sorted by (row, squared distance), each row's first (ties: the earlier entry)."""
    order = np.lexsort((d_m[:, 0] ** 2 + d_m[:, 1] ** 2, rows))
    return order[np.r_[True, rows[order][1:] != rows[order][:-1]]]


def braking_off_plan(q: np.ndarray, v_prev: np.ndarray, a_plan: np.ndarray, dt_s: float, brake_min_m_s2: float,
                     beyond, a_own: np.ndarray | None = None) -> np.ndarray:
    """(m,) bool: sensed states q (m, 4) that brake against their plan particle by more than brake_min_m_s2 and
    that one more control period of that braking takes beyond the plan.

    The acceleration is the sensed velocity change since the previous control step, (q_v - v_prev) / dt_s (the
    sensor gives no acceleration); a_plan (m, 2) is the own plan particle's over the same step, a_dev the
    difference. Braking: the component of a_dev along the previous velocity v_prev is below -brake_min_m_s2 (a
    vehicle that fails into Hold brakes along its velocity at up to a_max; lateral accelerations - an escape, a
    gust across the track - are not this test's). The state shifted by what a_dev adds in one period,
    q + (a_dev dt^2 / 2, a_dev dt), is passed to beyond(states, rows) (-> (k,) bool: farther than the mismatch
    threshold from the plan; rows: the indices into q). a_own (m, 2), if given: the observing row's own a_dev
    (its own velocity change against its own particle's, known onboard); the braking must then exceed
    brake_min_m_s2 relative to it too (a gust decelerates the observer and its neighbours alike: common mode).
    A vehicle braking in Hold in a moving plan (~2 m/s^2 against its particle) is flagged one control period
    before its state alone leaves the plan; a vehicle braking back towards the plan (a blown UAV recovering) is
    not, unless it is far off already."""
    a_dev = (q[:, 2:4] - v_prev) / dt_s - a_plan
    speed = np.sqrt(v_prev[:, 0] ** 2 + v_prev[:, 1] ** 2)
    along = (a_dev[:, 0] * v_prev[:, 0] + a_dev[:, 1] * v_prev[:, 1]) / np.maximum(speed, 1e-9)
    brakes = (along < -brake_min_m_s2) & (speed > brake_min_m_s2 * dt_s)
    if a_own is not None:
        rel = a_dev - a_own
        brakes &= (rel[:, 0] * v_prev[:, 0] + rel[:, 1] * v_prev[:, 1]) / np.maximum(speed, 1e-9) < -brake_min_m_s2
    big = np.flatnonzero(brakes)
    out = np.zeros(q.shape[0], dtype=bool)
    if big.size:
        ad = a_dev[big]
        shifted = q[big] + np.concatenate([0.5 * dt_s * dt_s * ad, dt_s * ad], axis=1)
        out[big] = beyond(shifted, big)
    return out


class _DefaultBase:
    def __init__(self, preset: Preset, destination_site_m: np.ndarray) -> None:
        if not isinstance(preset, DefaultPreset):
            raise ValueError(f"the default controllers need a DefaultPreset, got {type(preset).__name__}")
        self.preset = preset
        self.destination_site_m = np.asarray(destination_site_m, dtype=float).reshape(-1, 2)
        self._dest = self.destination_site_m.copy()
        bp = preset.backstop
        self.sensor_range_m = bp.sensor_range_m if bp.enabled else None
        self.backstop_active = np.zeros(self.n, dtype=bool)
        self.backstop_layer = np.zeros(self.n, dtype=np.uint8)     # safety.backstop.Layer bits per row, this step
        self.backstop_steps = np.zeros(self.n, dtype=np.int64)
        self._own_err: np.ndarray | None = None     # MFG: each row's deviation from its plan particle, s - s_plan (n, 4)
        # MFG: each row's own disturbance estimate this step (n, 2), guidance/disturbance.py; None before the observer has
        # two samples (and in HJB_d)
        self._own_dist: np.ndarray | None = None
        # MFG: the rows whose plan is deflected around a failed vehicle this step (mask (n,), its position (n, 2), the
        # onset (n,), the clearance, the side (n,)): _detour; None when no row senses one
        self._detour_state: tuple[np.ndarray, np.ndarray, np.ndarray, float, np.ndarray] | None = None
        # _distinct_sensed's answer for the sensed arrays of the current act() (cleared at its start and after the
        # backstop): (states, ids, (first, inv) or None)
        self._distinct_memo: tuple[np.ndarray, np.ndarray, tuple[np.ndarray, np.ndarray] | None] | None = None
        if bp.enabled:
            backstop.warm_up()              # load the compiled backstop now, not in the first control step (both modes)

    @property
    def n(self) -> int:
        return self.destination_site_m.shape[0]

    @property
    def destinations_m(self) -> np.ndarray:
        """(n, 2) each row's slot (its site before the slots are known)."""
        return self._dest

    def _spacing_m(self) -> float:
        return float("inf")

    # sensor quantisation (ADSB_VEHICLE: 1e-7 deg ~ 1.1 cm per axis, 1 cm/s and 0.01 deg of the velocity) is
    # covered by these margins in sensed_cutoff_m
    _SENSED_POS_MARGIN_M = 0.05
    _SENSED_VEL_MARGIN_M_S = 0.02

    def sensed_cutoff_m(self, states: np.ndarray, sensed_states: np.ndarray | None = None
                        ) -> tuple[float, np.ndarray] | None:
        """For a bank holding every vehicle (observed states (N, 4)): the reach (base_m, extra_m (N,)):
        a vehicle j sensed by row i can change i's action only if |r_j - r_i| <= base + extra_i + extra_j,
        so a simulator may deliver only those (None: all within the sensor range). The backstop acts only
        on a predicted closest approach rho below its trigger (at most max(trigger_m, unplanned_trigger_m)),
        and rho >= |d| - horizon |u| with |u| <= |v_i - c| + |v_j - c| (c: the median velocity), plus the
        sensor's quantisation margins."""
        bp = self.preset.backstop
        if not bp.enabled or states.shape[0] == 0:
            return None
        v = states[:, 2:4]
        c = np.median(v, axis=0)
        base = max(bp.trigger_m, bp.unplanned_trigger_m) + self._SENSED_POS_MARGIN_M + 2.0 * bp.horizon_s * self._SENSED_VEL_MARGIN_M_S
        return base, bp.horizon_s * np.linalg.norm(v - c[None, :], axis=1)

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

    def _unplanned(self, sensed_states: np.ndarray, ids: np.ndarray | None = None) -> np.ndarray:
        """(m,) bool: sensed vehicles the controller did not expect (HJB_d: none known)."""
        return np.zeros(sensed_states.shape[0], dtype=bool)

    def _lost(self, states: np.ndarray, ids: np.ndarray | None) -> np.ndarray:
        """(m,) bool: sensed vehicles lost to the plan (MFG; HJB_d: none known)."""
        return np.zeros(states.shape[0], dtype=bool)

    def _unplanned_by_braking(self, sn: Neighbours, step: int, unplanned: np.ndarray, own: np.ndarray) -> np.ndarray:
        """(m,) bool: sensed vehicles flagged by their braking against the plan (MFG; HJB_d: none); unplanned (m,):
        the entries already off the plan; own (n, 4): the rows' own states."""
        return np.zeros(sn.states.shape[0], dtype=bool)

    def _seen_snapshot(self) -> tuple[np.ndarray, np.ndarray] | None:
        """A copy of the velocities the braking test last recorded per plan particle and their steps, taken before it
        records this step's (_entry_prev_v reads it), or None (HJB_d: not kept; MFG: nothing recorded yet)."""
        return None

    def _entry_prev_v(self, sn: Neighbours, step: int,
                      seen: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray] | None:
        """Each sensed entry's velocity at the previous sample and whether it is known ((m, 2), (m,) bool), from
        ``seen`` (_seen_snapshot's), or None (no ids)."""
        return None

    def _braking_measured(self, sn: Neighbours, prev_v: tuple[np.ndarray, np.ndarray],
                          own_dist: np.ndarray | None) -> np.ndarray:
        """(m,) bool: the sensed entries seen at the previous sample that braked along their previous velocity by more
        than escape_brake_hypothesis_min_m_s2 beyond the observing row's own disturbance (own_dist (n, 2), the common
        mode; None: none known) since then. prev_v: _entry_prev_v's. The escape predicts these braking to a stop
        (BackstopParams.escape_brake_hypothesis "measured", with the hovering ones and those not seen before) and,
        off the plan, takes them as hovering (escape_braking_as_hover)."""
        pv, known = prev_v
        acc = (sn.states[:, 2:4] - pv) / self.preset.dt_s
        if own_dist is not None:
            acc = acc - own_dist[sn.owner]
        speed = np.maximum(np.linalg.norm(pv, axis=1), 1e-9)
        along = (acc[:, 0] * pv[:, 0] + acc[:, 1] * pv[:, 1]) / speed
        return known & (along < -self.preset.backstop.escape_brake_hypothesis_min_m_s2)

    def _cbf_share(self, sn: Neighbours, rows: np.ndarray) -> np.ndarray | None:
        """(m,) each sensed entry's share of its barrier constraint (backstop.cbf_acc), or None: crowd_cbf_share for
        every one (HJB_d; MFG gives all of it against a vehicle hovering in the plan's stream)."""
        return None

    def _hover_latched(self, sn: Neighbours, step: int, unplanned: np.ndarray, hover: np.ndarray) -> np.ndarray:
        """(m,) bool: ``hover`` and the off-plan (``unplanned``) entries that hovered within the last hover_latch_s and
        are slower than hover_latch_max_speed_m_s (MFG, by id; HJB_d: ``hover``, nothing is off its plan)."""
        return hover

    def _in_stream(self, states: np.ndarray) -> np.ndarray:
        """(m,) bool: the sensed entries where the plan flies (MFG: the nearest particle faster than
        unplanned_flow_min_m_s; HJB_d: nowhere known)."""
        return np.zeros(states.shape[0], dtype=bool)

    def _unplanned_reach(self, states: np.ndarray, unplanned: np.ndarray, trig_m: float,
                         clear_m: float) -> tuple[np.ndarray, np.ndarray]:
        """(m,) the escape's trigger and clearance per sensed entry (read where ``unplanned``): trig_m, clear_m for
        every one (HJB_d; MFG narrows them for an off-plan vehicle that moves with the plan's flow)."""
        m = states.shape[0]
        return np.full(m, trig_m), np.full(m, clear_m)

    def _yielding(self, sn: Neighbours, covered: np.ndarray) -> np.ndarray:
        """(m,) bool: sensed entries the observing row yields to (MFG; HJB_d: none). covered (m,): the entries that
        already get a response."""
        return np.zeros(sn.states.shape[0], dtype=bool)

    def _on_detour(self, sn: Neighbours, unplanned: np.ndarray) -> np.ndarray:
        """(m,) bool: entries (among ``unplanned``) that fly the plan as deflected around a failed vehicle (MFG;
        HJB_d: none, it has no plan to deflect)."""
        return np.zeros(sn.states.shape[0], dtype=bool)

    def _own_airframe(self, step: int) -> dict:
        """escape_acc's own-airframe arguments: its model of the own airframe (own_model: TrackingParams.acc_lag_s and
        the inner loop's gains) and the acceleration each row flies now (own_acc_m_s2: its last command, sent one step
        ago; None if there was none). {} without a lag: the closed-form prediction."""
        tp = getattr(self.preset, "tracking", None)
        if tp is None or not tp.acc_lag_s > 0.0:
            return {}
        kp, kd = (tp.inner_kp_per_s2, tp.inner_kd_per_s) if tp.inner_loop else (0.0, 0.0)
        model = backstop.OwnModel(float(tp.acc_lag_s), float(kp), float(kd), float(self.preset.dt_s))
        prev = getattr(self, "_own_a_prev", None)
        return {"own_model": model, "own_acc_m_s2": prev[1] if prev is not None and prev[0] == step - 1 else None}

    def _escape_side(self, own: np.ndarray, sn: Neighbours, hover_threat: np.ndarray,
                     at_m: np.ndarray | None = None) -> np.ndarray | None:
        """(n, 2) the side each row passes a hovering vehicle off the plan on (MFG; HJB_d: None, nothing is off it);
        at_m (m, 2), optional: where each entry is taken to be (None: where it is sensed)."""
        return None

    def _gap_pairs(self, sn: Neighbours, covered: np.ndarray) -> np.ndarray:
        """(m,) bool: sensed entries that get the gap push (MFG; HJB_d: none, its guard covers the heard vehicles).
        covered (m,): the entries that already get a response."""
        return np.zeros(sn.states.shape[0], dtype=bool)

    def _rear_responsible(self) -> bool:
        """Whether the escape leaves a vehicle behind the row to that vehicle (BackstopParams.escape_rear_responsible;
        MFG only: HJB_d's escape is flown as it was measured)."""
        return False

    def _backstop(self, own: np.ndarray, a_nom: np.ndarray, obs: Observation) -> np.ndarray:
        try:
            return self._backstop_rows(own, a_nom, obs)
        finally:
            self._distinct_memo = None      # the arrays it keyed on belong to this step

    def _backstop_rows(self, own: np.ndarray, a_nom: np.ndarray, obs: Observation) -> np.ndarray:
        bp, a_max = self.preset.backstop, self.preset.learner.acc_max_m_s2
        if not bp.enabled:
            self.backstop_layer = np.zeros(self.n, dtype=np.uint8)
            return cap_norm(a_nom, a_max)
        # the own disturbance the escape and the barrier filter predict the own vehicle with (BackstopParams.own_disturbance)
        od = (shrink_m_s2(self._own_dist, bp.own_disturbance_deadband_m_s2)
              if bp.own_disturbance and self._own_dist is not None else None)
        sn = self._not_heard(_sensed(obs), obs.neighbours)
        # the sensed vehicles' velocities one sample ago (the escape's braking hypothesis), kept before the braking test
        # records this step's
        seen = self._seen_snapshot() if bp.escape_brake_hypothesis == "measured" else None
        unplanned = self._unplanned(sn.states, sn.ids)
        by_braking = self._unplanned_by_braking(sn, obs.step, unplanned, own)
        unplanned |= by_braking
        if self._detour_state is not None and np.any(unplanned):
            # a neighbour that flies the plan deflected around a lost vehicle (_detour) is on the plan of a row that
            # senses that vehicle: the same deflection of the neighbour's own particle (by its id), which every such
            # row computes alike
            unplanned &= ~self._on_detour(sn, unplanned)
        planned = ~unplanned              # on the plan itself (not only up to the common mode)
        if isinstance(getattr(self, "plan", None), (RigidPlan, GroupPlan)) and not bp.planned_response_rigid:
            # a rigid plan keeps every planned pair at its start distance by construction: the tracking alone holds
            # them apart, and a response to their small transients only squeezes rows between neighbours (measured:
            # dense N = 1000, 2 collided pairs with it, 0 without; docs/default_controller.md)
            planned[:] = False
        if np.any(unplanned) and self._own_err is not None and bp.common_mode:
            # common mode is not a threat: a vehicle that is off the plan the way the own vehicle is (a gust
            # blows both) is checked again against the plan shifted by the own deviation (the own row's s - s_plan);
            # only for rows that are off their own particle themselves (else the shift only eats the detection margin:
            # measured, a UAV 0.1 m off its particle cleared a vehicle braking in Hold right in front of it)
            ps = bp.plan_mismatch_s
            own_dev = np.linalg.norm(self._own_err * np.array([1.0, 1.0, ps, ps]), axis=1)
            idx = np.flatnonzero(unplanned & (own_dev[sn.owner] > bp.common_mode_min_own_dev_m))
            unplanned[idx] = (self._unplanned(sn.states[idx] - self._own_err[sn.owner[idx]])
                              | self._lost(sn.states[idx], None if sn.ids is None else sn.ids[idx])
                              | (by_braking[idx] & bp.common_mode_keeps_braking))
        plan = getattr(self, "plan", None)
        if plan is not None and sn.states.shape[0] and bp.own_slot_claim:
            # a sensed vehicle on the own particle's place is not on the plan whatever particle it is near: the own
            # vehicle is that particle (measured: a UAV failed in Hold on a group mate's slot was taken as that
            # slot's particle, and the mate settled 0.06-0.2 m from it; merge N = 300, seed 4)
            # only where the own particle is (nearly) parked: in flight, a gust blows neighbours across the own place
            # (measured: dense --gust N = 144 seed 2, 5 pairs with the rule in flight, 0 without)
            own_p = plan.states[self.own_index]
            parked = own_p[:, 2] ** 2 + own_p[:, 3] ** 2 < bp.own_slot_claim_max_speed_m_s ** 2
            if np.any(parked):
                # |dr|^2 + (plan_mismatch_s |dv|)^2 below the claim radius, entry by entry (compiled: at N = 10,000 a
                # parked swarm's rows have ~10^6 entries)
                ps = bp.plan_mismatch_s
                claim = np.flatnonzero(slot_claims(_kernel_arg(sn.owner, np.int64), _kernel_arg(sn.states, np.float64),
                                                   _kernel_arg(own_p, np.float64), parked, ps * ps,
                                                   min(bp.plan_mismatch_m, 0.5 * self._spacing_m()) ** 2))
                unplanned[claim] = True
                planned[claim] = False
        if self._own_err is not None:
            # the planned vehicles' response assumes both fly the plan to within centimetres; a UAV blown
            # further off its own particle, or a neighbour off the plan by the common mode, is left to the
            # tracking (measured: in a gust this response pushed UAVs of the 0.5 m dense formation into each other)
            off = np.linalg.norm(self._own_err[:, 0:2], axis=1) > bp.planned_max_own_dev_m
            planned &= ~off[sn.owner]
        da = backstop_acc(own, sn.states, sn.owner, bp, select=planned)
        # which layer's push is in each row's half-plane constraint (safety.backstop.Layer; attribution only)
        half = np.where(np.any(da != 0.0, axis=1), np.uint8(Layer.PLANNED), np.uint8(0))
        esc = np.zeros(self.n, dtype=bool)
        crowd_rows = np.zeros(0, dtype=np.int64)
        # a UAV off its own particle yields to a vehicle on its own that neither response covers (_yielding)
        yl = self._yielding(sn, planned | unplanned) if bp.escape and bp.escape_yield else np.zeros_like(unplanned)
        if np.any(unplanned) or np.any(yl):
            # the unplanned response's trigger and clearance, fitted to the slot spacing
            sp = self._spacing_m()
            u_trig, u_clear = min(bp.unplanned_trigger_m, 0.5 * sp), min(bp.unplanned_target_m, 0.6 * sp)
            e_trig, e_clear = self._unplanned_reach(sn.states, unplanned, u_trig, u_clear)
            # the sensed vehicles' velocities one sample ago, by entry (the braking hypothesis, escape_braking_as_hover)
            prev_v = self._entry_prev_v(sn, obs.step, seen) if seen is not None else None
            braked = self._braking_measured(sn, prev_v, self._own_dist) if prev_v is not None else None
            # a hovering vehicle off the plan (failed in Hold, drifting): the rules of BackstopParams.hover_max_speed_m_s
            hover = unplanned & (sn.states[:, 2] ** 2 + sn.states[:, 3] ** 2 < bp.hover_max_speed_m_s ** 2)
            # ... or hovered lately and is still off the plan (BackstopParams.hover_latch_s)
            hover = self._hover_latched(sn, obs.step, unplanned, hover)
            # ... and one braking to its stop (BackstopParams.escape_braking_as_hover): the full reach (not the flow's),
            # and, below, the hovering one's clearance, lane side (at its braking stop point) and coast trigger
            stopping = np.zeros_like(hover)
            side_at = None
            if bp.escape_braking_as_hover and braked is not None:
                stopping = unplanned & ~hover & braked
                if np.any(stopping):
                    e_trig[stopping], e_clear[stopping] = u_trig, u_clear
                    side_at = sn.states[:, 0:2].copy()
                    v = sn.states[stopping, 2:4]
                    side_at[stopping] += v * (np.hypot(v[:, 0], v[:, 1]) / (2.0 * a_max))[:, None]
            sp_now = self._spacing_now_m()
            if bp.unplanned_hover_clear_now:
                # its clearance by the spacing flown now
                hc = hover | stopping
                e_clear[hc] = np.maximum(e_clear[hc], min(bp.unplanned_target_m, 0.6 * sp_now))
            if bp.unplanned_hover_trigger_now:
                # and its trigger
                e_trig[hover] = np.maximum(e_trig[hover], min(bp.unplanned_trigger_m, 0.5 * sp_now))
            # the escape is a backstop for a few off-plan vehicles; a row that senses mostly off-plan vehicles (the
            # swarm has lost its plan) gets the single half-plane push instead (measured: with every UAV off the
            # plan, escaping from all neighbours at once swerved UAVs into each other in the 0.5 m formation)
            crowded = np.ones(self.n, dtype=bool)
            if bp.escape:
                n_unpl = np.bincount(sn.owner[unplanned], minlength=self.n)
                crowded = n_unpl > bp.escape_max_unplanned_fraction * np.bincount(sn.owner, minlength=self.n)
            threat = unplanned & ~crowded[sn.owner]
            if bp.escape_hover_in_crowd and np.any(hover):
                # a vehicle hovering off the plan where the plan flies (failed into Hold in the stream) stays a threat to
                # a crowded row as well: passing it is the escape's swerve, which the crowd's filter (braking along each
                # line of sight, among many constraints) did not make (paper --gust, vehicle 10 failing at 20.15 s, N =
                # 300 seed 76: UAV 48's row, crowded by the gust, met it at 0.052 m; BackstopParams.escape_hover_in_crowd)
                h = np.flatnonzero(hover)
                h = h[self._in_stream(sn.states[h])]
                if h.size:
                    # only a row at stream speed that braking cannot stop short of it (a row slow at its departure, next
                    # to neighbours as slow, brakes: crossing --gust N = 137 seed 117)
                    r = sn.owner[h]
                    vmin = bp.escape_hover_in_crowd_min_speed_m_s
                    keep = own[r, 2] ** 2 + own[r, 3] ** 2 > vmin * vmin
                    if bp.escape_hover_in_crowd_brake_gate:
                        keep &= cannot_brake_short(own, sn.states[h], r, e_clear[h], a_max, self.preset.dt_s)
                    h = h[keep]
                threat[h] = True
            push = unplanned & crowded[sn.owner]
            yl &= ~crowded[sn.owner]
            # the rest (neither in the planned response nor unplanned: a neighbour cleared as common mode, or any
            # neighbour of a row off its own particle) trigger the escape only below the planned trigger
            gap = ~planned & ~unplanned & ~yl & bp.escape_gap & ~crowded[sn.owner]
            if np.any(threat) or np.any(yl):
                # escape manoeuvre for the rows an unplanned vehicle threatens, or that yield (backstop.escape_acc);
                # the other rows keep the planned vehicles' half-plane response below
                y_trig, y_clear = min(bp.escape_yield_trigger_m, 0.5 * sp), min(bp.escape_yield_clear_m, 0.6 * sp)
                trig = np.where(threat, e_trig, np.where(yl, y_trig, np.where(gap, bp.trigger_m, 0.0)))
                clear = np.where(unplanned, e_clear,
                                 np.where(yl, y_clear, min(bp.escape_planned_clear_m, bp.escape_planned_fraction * sp)))
                # against a hovering threat coasting also wakes the escape (BackstopParams.escape_trigger_coast), and
                # the lane side replaces keep-right (escape_side_over_keep_right)
                hover_threat = threat & (hover | stopping)
                # which threats may also be braking to a stop (BackstopParams.escape_brake_hypothesis; None: every one)
                bh = hover | ~prev_v[1] | braked if prev_v is not None else None
                if self._rear_responsible():
                    # the UAV behind is the responsible one (BackstopParams.escape_rear_responsible): no escape for a
                    # vehicle behind the row, unless it hovers or brakes into its Hold, or would come within its
                    # clearance inside one control period (imminent: the one behind may be crowded, its barrier filter
                    # taking only its half)
                    # (tested only where it can drop an entry)
                    behind = np.zeros_like(threat)
                    idx = np.flatnonzero(threat | gap)
                    behind[idx] = behind_row(own, sn.states[idx], sn.owner[idx], clear[idx], self.preset.dt_s)
                    threat = threat & ~(behind & ~(hover | stopping))
                    gap = gap & ~behind
                threat = threat | gap | yl
                # the own airframe's lag, when it has one (safety.backstop.OwnModel)
                airframe = self._own_airframe(obs.step)
                # a tube around the tracks of a hovering / braking threat that still moves where the plan flies (a
                # vehicle failing into Hold: BackstopParams.escape_tube_m_s2), as wide as the room between the lanes
                tube = None
                if bp.escape_tube_m_s2 > 0.0 and sp_now >= bp.escape_tube_min_spacing_m and np.any(hover_threat):
                    h = np.flatnonzero(hover_threat)
                    vt = bp.escape_tube_min_speed_m_s
                    h = h[sn.states[h, 2] ** 2 + sn.states[h, 3] ** 2 >= vt * vt]
                    tube = np.zeros_like(threat)
                    tube[h] = self._in_stream(sn.states[h])
                a_esc, esc = escape_acc(own, cap_norm(a_nom, a_max), sn.states, sn.owner, threat, trig, clear, bp,
                                        self.preset.dt_s, self._escape_side(own, sn, hover_threat, side_at), hover_threat, od, brake_hyp=bh,
                                        tube=tube, tube_max_m=bp.escape_tube_spacing_fraction * sp_now, **airframe)
            if np.any(push) and bp.crowd_cbf:
                # a crowded row gets the reciprocal barrier filter over everything it senses instead (below): the
                # summed push left UAVs that chased their particles through a blown crowd to cross each other
                # (crossing --gust N = 137, 3 of 30 seeds collided; BackstopParams.crowd_cbf)
                crowd_rows = np.flatnonzero(np.bincount(sn.owner[push], minlength=self.n))
            elif np.any(push):
                # with the escape's reach per entry: a crowded row (most of its neighbours blown off the plan) pushed
                # with the large reach (0.6 / 0.8 m) against neighbours that move with the flow was shoved about in
                # the 1.41 m lattice, fell behind the block and stalled in the stream (swap4 --gust N = 10,000 seed 7,
                # UAV 5822: 4 m off its particle in 3 s, then hit from behind)
                if bp.push_flow_reach:
                    bu = replace(bp, trigger_m=e_trig, target_m=e_clear, share=bp.unplanned_share)
                else:
                    bu = replace(bp, trigger_m=u_trig, target_m=u_clear, share=bp.unplanned_share)
                d_push = backstop_acc(own, sn.states, sn.owner, bu, select=push)
                half |= np.where(np.any(d_push != 0.0, axis=1), np.uint8(Layer.PUSH), np.uint8(0))
                da = cap_norm(da + d_push, bp.a_max_m_s2)
        gp = self._gap_pairs(sn, planned | unplanned | yl)
        if np.any(gp):
            sp_now = self._spacing_now_m()
            bg = replace(bp, trigger_m=bp.gap_push_trigger_fraction * sp_now, target_m=bp.gap_push_target_fraction * sp_now,
                         share=bp.gap_push_share, horizon_s=bp.gap_push_horizon_s)
            d_gap = backstop_acc(own, sn.states, sn.owner, bg, select=gp)
            half |= np.where(np.any(d_gap != 0.0, axis=1), np.uint8(Layer.GAP), np.uint8(0))
            da = cap_norm(da + d_gap, bp.a_max_m_s2)
        a, act = apply_backstop(cap_norm(a_nom, a_max), da, a_max)
        layer = np.where(act, half, np.uint8(0))
        if np.any(esc):
            a, act = np.where(esc[:, None], a_esc, a), act | esc
            layer[esc] = Layer.ESCAPE
            crowd_rows = crowd_rows[~esc[crowd_rows]]       # a crowded row that escapes a hovering vehicle (above)
        if crowd_rows.size:
            # (a crowded row never escapes: threat, yield and gap entries all exclude crowded rows)
            a[crowd_rows], act[crowd_rows] = cbf_acc(own, cap_norm(a_nom, a_max), sn.states, sn.owner, crowd_rows, bp,
                                                     bp.crowd_cbf_safe_fraction * self._spacing_m(), a_max,
                                                     self._cbf_share(sn, crowd_rows), od)
            layer[crowd_rows] = np.where(act[crowd_rows], np.uint8(Layer.CROWD_CBF), np.uint8(0))
        if bp.crowd_cbf and bp.cbf_last_layer and np.any(unplanned):
            # (an option, off: BackstopParams.cbf_last_layer) the same filter as the last layer of every other row that
            # senses a vehicle off the plan (not hovering) and does not escape, over the command the responses above
            # made, against every sensed vehicle, with the reciprocal half (calm flights, where nothing is off the plan,
            # are the same flights): a crowded row's constraint assumes its neighbour takes the other half, and a
            # neighbour that was not crowded took none (crossing --gust with a failure, N = 1,000 seed 77: UAVs 63 / 87
            # closed at 1.7 m/s while one switched between escape, filter and push). Not against a vehicle that hovers
            # off the plan: passing it is the escape's (a swerve; the filter only brakes along the line of sight, and
            # braking at it in a gust met it: paper N = 1,000 seed 76)
            # (hover: the off-plan entries slower than hover_max_speed_m_s, from the block above, which every flight
            # with an off-plan entry enters)
            rest = (np.bincount(sn.owner[unplanned & ~hover], minlength=self.n) > 0) & ~esc
            rest[crowd_rows] = False
            rows = np.flatnonzero(rest)
            if rows.size:
                keep = np.flatnonzero(~hover)
                a_f, act_f = cbf_acc(own, a, sn.states[keep], sn.owner[keep], rows, bp,
                                     bp.crowd_cbf_safe_fraction * self._spacing_m(), a_max, None, od)
                a[rows] = a_f
                act[rows] |= act_f
                layer[rows] |= np.where(act_f, np.uint8(Layer.LAST_CBF), np.uint8(0))
        self.backstop_active = act
        self.backstop_layer = layer
        self.backstop_steps += act
        return a


class DefaultMFGController(_DefaultBase):
    """MFG with the self-consistent mean-field plan, tracked by the HJB value model."""

    mode = "mfg"
    uses_t0_exchange = True

    def __init__(self, preset: Preset, destination_site_m: np.ndarray) -> None:
        super().__init__(preset, destination_site_m)
        p = self.preset
        self.track_preset = Preset(name="default-tracking", cost=p.tracking_cost, learner=p.learner, dt_s=p.dt_s)
        self.sigma_H = make_sigma_H(p.learner.state_scale)
        self.w_H = np.tile(lqr_value_weights(self.sigma_H, p.tracking_cost), (self.n, 1))
        self.sigma_F = make_sigma_F(p.learner.fpk_scale)
        self.w_F = np.zeros((self.n, self.sigma_F.M))
        self._GGt = p.cost.V_o @ p.cost.V_o.T
        kernels.warm_up()                   # load the compiled kernels now, not in the first control step
        self.plan: MeanFieldPlan | RigidPlan | None = None
        self._plan_tree: tuple[int, cKDTree] | None = None      # (plan step, k-d tree of its particles), _plan_distance
        self._flow_tree: tuple[int, cKDTree] | None = None      # (plan step, k-d tree of its positions), _unplanned_reach
        self._side_mem: tuple[np.ndarray, np.ndarray] | None = None     # (threat id, side (n, 2)) per row: _escape_side
        ps = p.backstop.plan_mismatch_s
        self._plan_metric_w = np.array([1.0, 1.0, ps, ps])      # _plan_distance's metric weights
        self.own_index = np.zeros(self.n, dtype=np.int64)
        self._plan_ids: tuple[np.ndarray, np.ndarray] | None = None     # (sorted ids, their plan particles): exchange_t0
        self._id_table: np.ndarray | None = None    # id -> plan particle (-1: none) for small non-negative ids: exchange_t0
        self._index_particles: np.ndarray | None = None     # _particles_of(arange(N)), sensed_cutoff_m's lost test
        self._box_bound: float | None = None        # _box_grad_bound's constant
        self._prepared: tuple | None = None     # (plan step, a_plan_all, centroid, centroid rate): prepare()
        self._pending: tuple | None = None      # act()'s FPK-update arguments for finish() (() for none); None: no act() open
        # the braking test (BackstopParams.plan_mismatch_brake_m_s2): per plan particle (= per vehicle id), the
        # velocity last sensed and its step; the plan's particle velocities by step; the simulator's full observed
        # states by step (sensed_cutoff_m), the previous sample of a vehicle the reach-limited delivery left out
        self._seen_v: np.ndarray | None = None
        self._seen_k: np.ndarray | None = None
        self._hover_k: np.ndarray | None = None     # per plan particle: the last step it hovered off the plan
        self._own_v_prev: tuple[int, np.ndarray] | None = None      # (step, the rows' own velocities then)
        self._own_a_prev: tuple[int, np.ndarray] | None = None      # (step, the rows' commands then): act()
        self._plan_s_hist: dict[int, np.ndarray] = {}
        self._ref_pos: tuple[int, np.ndarray] | None = None     # (plan step, each row's reference position): act()
        self._detour_mem: tuple[np.ndarray, np.ndarray] | None = None   # (lost vehicle id, side) per row: _detour
        self._cutoff_hist: dict[int, np.ndarray] = {}

    def exchange_t0(self, states, ids, own_index, sites_m) -> None:
        """The one exchange: every row gets the same plan from the same (N, 4) states."""
        p = self.preset
        S0 = np.asarray(states, dtype=float)
        self.own_index = np.asarray(own_index, dtype=np.int64).reshape(self.n)
        self._plan_ids, self._index_particles = None, None    # vehicle id -> its plan particle (the exchange's order)
        self._id_table = None
        if ids is not None:
            ids = np.asarray(ids, dtype=np.int64).reshape(-1)
            order = np.argsort(ids, kind="stable")
            self._plan_ids = (ids[order], order)
            if ids.size and _dense_ids(ids):
                # _particles_of's table; filled last to first, so that a repeated id keeps its first particle
                self._id_table = np.full(int(ids.max()) + 1, -1, dtype=np.int64)
                self._id_table[ids[::-1]] = np.arange(ids.size - 1, -1, -1, dtype=np.int64)
        self._plan_tree, self._flow_tree, self._side_mem = None, None, None
        self._prepared, self._pending = None, None
        self._seen_v, self._seen_k, self._own_v_prev, self._own_a_prev = None, None, None, None
        self._hover_k = None
        self._dob, self._own_dist = None, None
        self._plan_s_hist, self._cutoff_hist = {}, {}
        # a new flight: nothing of an earlier one (a controller reused for another t = 0 exchange decides as a new one;
        # tests/test_detour.py): the detour's memory, the tracked reference, the learnt value model
        self._detour_mem, self._detour_state, self._ref_pos, self._own_err = None, None, None, None
        self.backstop_active = np.zeros(self.n, dtype=bool)
        self.backstop_layer = np.zeros(self.n, dtype=np.uint8)
        self.w_H = np.tile(lqr_value_weights(self.sigma_H, p.tracking_cost), (self.n, 1))
        rigid = (rigid_plan_for(S0, sites_m, p.dt_s, p.cost, p.guidance.v_cruise_m_s, p.guidance.a_brake_m_s2,
                                translation=p.rigid_translation, cruise_spacing_m=p.cruise_spacing_m)
                 if p.rigid_plan and p.use_slots else None)
        if rigid is None and p.group_plan and p.use_slots:
            rigid = group_plan_for(S0, sites_m, p.dt_s, p.cost, p.guidance.v_cruise_m_s, p.guidance.a_brake_m_s2,
                                   clearance_fraction=p.group_plan_clearance_fraction)
        self.plan = rigid if rigid is not None else MeanFieldPlan(S0, sites_m, p.dt_s, p.cost, p.guidance, p.repulsion,
                                                                   use_slots=p.use_slots, use_repulsion=p.use_repulsion)
        self._dest = self.plan.slots_m[self.own_index].copy()
        w0 = fit_initial_fpk_weights(self.sigma_F, S0 - S0.mean(axis=0), np.asarray(p.learner.fpk_kde_bandwidth))
        self.w_F = np.tile(w0, (self.n, 1))

    def _spacing_m(self) -> float:
        return self.plan.spacing_m

    def plan_positions_m(self) -> np.ndarray | None:
        """Each row's own plan particle's position now (n, 2) (a copy; None before the t = 0 exchange): what the
        tracking holds the UAV to, for the per-flight check of the guarantee (mfg_swarm.metrics.separation_guarantee)."""
        if self.plan is None:
            return None
        ref = self._ref_pos
        if ref is not None and ref[0] == self.plan.k:      # act() at this step: the particle as deflected (_detour)
            return ref[1].copy()
        return self.plan.states[self.own_index, 0:2].copy()

    @property
    def tracked_reference_m(self) -> tuple[int, np.ndarray] | None:
        """(step, (n, 2)): each row's reference position at the last act(), its plan particle as deflected around a
        failed vehicle (_detour); None before the first act()."""
        return self._ref_pos

    @property
    def plan_certificate(self) -> dict | None:
        """What the t = 0 plan guarantees: {"plan": kind, "clearance_m": d, "duration_s": T} when it is conflict-free by
        construction (every pair of particles at least d apart for the whole plan: the start/slot spacing for a rigid
        motion, the space-time check's bound for scheduled groups; every particle on its slot from T on; scheduled
        groups also name their ``route``), {"plan": "interacting", "clearance_m": None} otherwise."""
        if self.plan is None:
            return None
        if isinstance(self.plan, RigidPlan):
            sp = float(self.plan.spacing_m)
            return {"plan": self.plan.kind, "clearance_m": sp if np.isfinite(sp) else None,
                    "duration_s": float(self.plan.T)}
        if isinstance(self.plan, GroupPlan):
            return {"plan": "groups", "clearance_m": float(self.plan.clearance_m), "duration_s": float(self.plan.T),
                    "route": self.plan.route, "group_start_s": [float(x) for x in self.plan.start_s]}
        return {"plan": "interacting", "clearance_m": None}

    def sensed_cutoff_m(self, states: np.ndarray, sensed_states: np.ndarray | None = None
                        ) -> tuple[float, np.ndarray, float, np.ndarray] | None:
        """As the base class while every vehicle flies the plan, with the closest-approach test over the horizon
        (the reach (base_m, extra_m (N,), horizon_s, wide (N,)) of mfg_swarm.spatial.pairs_within_reach). A row
        within the sensor range of a vehicle that might be 'unplanned' gets the whole range (extra_i >= the range): the escape manoeuvre (backstop.escape_acc)
        then looks at every sensed vehicle over candidate accelerations up to a_max, far beyond the trigger reach, and
        the crowd fallback counts every sensed vehicle; so does a row that may yield (_yielding: off its own particle)
        or that may claim its parked slot (_claim_rows); None (everything within the range, for every row) when that
        is every row. Whether a vehicle is unplanned depends only on its own state and the plan (the common-mode
        re-check and the own-deviation gate only remove responses), so it is decided here on the true states with a
        margin for the sensor's quantisation; the braking test (_unplanned_by_braking) also on the states passed at
        the previous step (kept here; None when there are none, a bank of one: the sensed_cutoff_m calls are the
        simulator's, one per step). A row with no such vehicle within its range decides exactly as when every vehicle
        flies the plan (tests/test_scaling.py flies both deliveries bit for bit, with a gust and a failed vehicle).
        sensed_states (N, 4), if given: the states as the sensor delivers them to every row that senses them (the
        simulator's quantisation, the same for every observer); the state, lost and braking tests are then evaluated
        as the rows will evaluate them (_braking_superset for the braking) instead of with the quantisation's margins."""
        bp = self.preset.backstop
        if not bp.enabled or self.plan is None or states.shape[0] == 0:
            return None
        margin = self._SENSED_POS_MARGIN_M + bp.plan_mismatch_s * self._SENSED_VEL_MARGIN_M_S
        states = np.asarray(states, dtype=float)
        hint = np.arange(states.shape[0]) if states.shape[0] == self.plan.N else None      # vehicle j <-> particle j
        k = self.plan.k
        if bp.plan_mismatch_brake_m_s2 > 0:
            # kept for the braking test (_unplanned_by_braking): the previous sample of a vehicle no row was
            # delivered at that step
            self._cutoff_hist = {kk: x for kk, x in self._cutoff_hist.items() if kk == k - 1}
            self._cutoff_hist[k] = states.copy()
            a_plan = self._plan_acc(k)
        # the vehicles that may be unplanned to some row (off the plan, lost to it, or braking off it): every row within
        # the sensor range of one needs every vehicle it senses (the crowd count, the escape, the braking test's skip);
        # and the rows that may yield (the escape): wide_rows. The rest keep the reach below.
        # with the states as sensed (sensed_states) the state and lost tests are the rows' own, on the same numbers (a
        # 1e-9 m slack); else on the true states with the quantisation's margin
        exact = sensed_states is not None and np.shape(sensed_states) == states.shape and self.n == states.shape[0]
        q = np.asarray(sensed_states, dtype=float) if exact else states
        unpl = self._beyond_plan(q, bp.plan_mismatch_m - (1e-9 if exact else margin), hint)
        wide_rows = np.zeros(states.shape[0], dtype=bool)
        yield_m = bp.escape_yield_min_dev_m if bp.escape and bp.escape_yield else float("inf")
        if (bp.plan_lost_m > 0 or np.isfinite(yield_m)) and self._plan_ids is not None:
            # _lost: by id; a row is delivered vehicle j under id j (the map is fixed from the exchange on)
            part = self._vehicle_particles(states.shape[0])
            known = np.flatnonzero(part >= 0)
            dr = states[known, 0:2] - self.plan.states[part[known], 0:2]
            d2 = dr[:, 0] ** 2 + dr[:, 1] ** 2
            if bp.plan_lost_m > 0:
                if exact:
                    drq = q[known, 0:2] - self.plan.states[part[known], 0:2]
                    unpl[known[drq[:, 0] ** 2 + drq[:, 1] ** 2 > (bp.plan_lost_m - 1e-9) ** 2]] = True
                else:
                    unpl[known[d2 > (bp.plan_lost_m - margin) ** 2]] = True
            # _yielding: a row that far off its own particle may escape (its trigger predicts its nominal command
            # over the horizon, beyond the reach below)
            wide_rows[known[d2 > (yield_m - margin) ** 2]] = True
        if bp.plan_mismatch_brake_m_s2 > 0:
            # the braking test on the same states against their state at the previous step, without the observer's own
            # deviation (it only removes flags); margin: the quantisation of two velocity samples
            prev = self._cutoff_hist.get(k - 1)
            if k >= 1 and (hint is None or prev is None or a_plan is None or prev.shape != states.shape):
                return None
            if k >= 1:
                dt = self.preset.dt_s
                a_marg = 2.0 * self._SENSED_VEL_MARGIN_M_S / dt
                m2 = margin + (0.5 * dt * dt + bp.plan_mismatch_s * dt) * a_marg
                if exact:
                    # the states as every row will sense them: the braking test itself (up to the rows' model update)
                    unpl |= self._braking_superset(states, q, prev, a_plan, k)
                else:
                    beyond = lambda q, rows: self._beyond_plan(q, bp.plan_mismatch_m - m2, hint[rows])
                    unpl |= braking_off_plan(states, prev[:, 2:4], a_plan, dt, bp.plan_mismatch_brake_m_s2 - a_marg, beyond)
        wide_rows |= self._claim_rows(states, margin)
        if np.any(unpl):
            # every row within the sensor range of a possibly unplanned vehicle (the simulator's sensor: the same states)
            d, _ = cKDTree(states[unpl, 0:2]).query(states[:, 0:2], k=1, distance_upper_bound=bp.sensor_range_m + margin)
            wide_rows |= np.isfinite(d)
        if np.all(wide_rows):
            return None
        reach = super().sensed_cutoff_m(states)
        h = bp.horizon_s
        if reach is not None and bp.gap_push and self._spacing_now_m() >= bp.gap_push_min_spacing_m:
            # _gap_pairs: the gap push's trigger follows the spacing now, over its own horizon
            reach = (max(reach[0], bp.gap_push_trigger_fraction * self._spacing_now_m() + margin),
                     reach[1] * max(1.0, bp.gap_push_horizon_s / bp.horizon_s))
            h = max(h, bp.gap_push_horizon_s)
        tp = self.preset.tracking
        if reach is not None and tp.feedback and tp.relative_priority and np.isfinite(self.plan.spacing_m):
            # _formation_error's neighbours: plan particles within the formation radius, and every vehicle is within
            # plan_mismatch_m of the plan here (margin: the quantisation and that distance)
            # (the spacing now: a translation spread in cruise is farther apart than at the start, and the pad's
            # spacing keeps the reach short where the vehicles are dense)
            sp = getattr(self.plan, "spacing_reach_m", self.plan.spacing_m)
            reach = (max(reach[0], tp.formation_radius_spacings * sp + 2.0 * bp.plan_mismatch_m + margin), reach[1])
        if reach is None:
            return None
        if np.any(wide_rows):
            # base + extra_i + extra_j >= the sensor range for a wide row i: it is delivered every vehicle it senses
            reach = (reach[0], np.where(wide_rows, max(bp.sensor_range_m, float(np.max(reach[1]))), reach[1]))
        # the other rows only the pairs whose closest approach over the horizon h (constant velocities) comes within
        # the base: the half-plane responses act on a predicted closest approach below their trigger over a horizon
        # <= h (base: the largest trigger plus the sensor's margins), and the formation's neighbours are within the base
        # now (tau = 0). In streams that cross (swap4, crossing, circle) |v_i - c| is the stream speed and base +
        # extra_i + extra_j spans the sensor range; a UAV's own stream mates keep u ~ 0 (measured: swap4 N = 10,000,
        # 1.36 -> ~0.70 million sensed entries per step; docs/benchmarks.md, seventeenth round)
        return reach[0], reach[1], h, wide_rows

    def _braking_superset(self, states: np.ndarray, q: np.ndarray, prev: np.ndarray, a_plan: np.ndarray,
                          k: int) -> np.ndarray:
        """(N,) bool, for sensed_cutoff_m: the vehicles that some row within the sensor range of them may flag at step k
        by the braking test (_unplanned_by_braking), a superset. states (N, 4) the true states (rows i <-> vehicles i:
        a bank holding every vehicle), q (N, 4) as sensed (the same for every observer), prev the true states of
        step k - 1. Per vehicle, by braking_scan itself (one row sensing every vehicle, on copies of its memory) and
        _brakes_beyond_tracking's own estimate (_prev_deviation): the previous
        velocity sample the scan will take (the sensed one if the vehicle was delivered at k - 1: seen_v, else prev),
        the braking along it beyond plan_mismatch_brake_m_s2, the shifted state beyond the plan, and the braking
        beyond the neighbour's own tracking, eq. 8 with the observing row's w_H. That last test is linear in the
        row's weights, a_fb . u = g . w_H (g from the features' velocity gradient at the neighbour's leashed
        error), and act() updates w_H once per learner iteration before it (hjb_update: a normalised gradient step
        of norm mu plus the regulariser's c_H grad R, |grad R| <= |e_v| |J_v(e)|_F / 2 c3, e the row's own leashed
        error); so a row may flag j only if g . w_H - |g| delta_i exceeds what j's braking leaves, delta_i that
        update's bound. Left out (they only remove flags): the common mode (own_ref), a row that already senses an
        unplanned vehicle. A 1e-9 slack on every threshold covers the summation order."""
        bp, dt = self.preset.backstop, self.preset.dt_s
        N = states.shape[0]
        out = np.zeros(N, dtype=bool)
        if self._plan_ids is None:
            return out
        th, slack = bp.plan_mismatch_brake_m_s2, 1e-9
        part = self._vehicle_particles(N)
        cand = np.flatnonzero(part >= 0)
        p = part[cand]
        # braking_scan itself, as one row sensing every vehicle, on copies of its memory (it records what it saw)
        n_part = self.plan.N
        has_seen = self._seen_k is not None and self._seen_k.size == n_part
        seen_v = self._seen_v.copy() if has_seen else np.zeros((n_part, 2))
        seen_k = self._seen_k.copy() if has_seen else np.full(n_part, -1, dtype=np.int64)
        idx, shifted = braking_scan(np.zeros(cand.size, dtype=np.int64), _kernel_arg(p, np.int64),
                                    _kernel_arg(q[cand], np.float64), np.zeros(cand.size, dtype=np.bool_), 1, seen_v,
                                    seen_k, _kernel_arg(prev, np.float64), True, _kernel_arg(a_plan, np.float64), True,
                                    np.zeros((0, 2)), False, int(k), float(dt), float(th))
        if idx.size == 0:
            return out
        cand, p = cand[idx], p[idx]
        far = self._beyond_plan(shifted, bp.plan_mismatch_m, p)
        cand, p, shifted = cand[far], p[far], shifted[far]
        plan_prev = self._plan_s_hist.get(k - 1)
        if cand.size == 0 or not bp.plan_mismatch_brake_expected or plan_prev is None:
            out[cand] = True
            return out
        # the neighbour's deviation at the previous sample, as _brakes_beyond_tracking estimates it, and g
        meas, v_prev, e = self._prev_deviation(q[cand], shifted, p, a_plan, plan_prev)
        u = v_prev / np.maximum(np.linalg.norm(v_prev, axis=1), 1e-9)[:, None]
        Jv = self._feature_grad_v(self._leash(e))                        # (k, M, 2)
        g = -(Jv[:, :, 0] * u[:, 0:1] + Jv[:, :, 1] * u[:, 1:2]) / (2.0 * self.preset.cost.c3)   # a_fb . u = g . w
        r = meas - a_plan[p]
        A = r[:, 0] * u[:, 0] + r[:, 1] * u[:, 1]                        # (meas - a_plan) . u
        # the rows that sense each candidate
        pairs = cKDTree(states[cand, 0:2]).sparse_distance_matrix(cKDTree(states[:, 0:2]), bp.sensor_range_m + 1e-6,
                                                                   output_type="ndarray")
        which, rows = pairs["i"].astype(np.int64), pairs["j"].astype(np.int64)
        other = rows != cand[which]
        rows, which = rows[other], which[other]
        if rows.size == 0:
            return out
        delta = self._model_update_bound(states, np.unique(rows))
        gw = np.einsum("pm,pm->p", g[which], self.w_H[rows])
        gn = np.sqrt(np.einsum("km,km->k", g, g))
        maybe = A[which] - gw - gn[which] * delta[rows] < -th + slack
        out[cand[np.unique(which[maybe])]] = True
        return out

    def _feature_grad_v(self, e: np.ndarray) -> np.ndarray:
        """(k, M, 2): the velocity part of every sigma_H feature's gradient at the states e (k, 4)."""
        E = np.asarray(self.sigma_H.exponents, dtype=np.int64)
        scale = np.asarray(self.sigma_H.scale, dtype=float)
        k, M = e.shape[0], E.shape[0]
        if k == 0:
            return np.zeros((0, M, 2))
        st = e / scale[None, :]
        pw = st[:, :, None] ** np.arange(int(E.max()) + 1)[None, None, :]      # (k, 4, D + 1): s~_d^p
        out = np.empty((k, M, 2))
        for c, d in enumerate((2, 3)):
            ex = E.copy()
            ex[:, d] = np.maximum(ex[:, d] - 1, 0)
            # d sigma_m / d s_d = E_md / scale_d s~_d^(E_md - 1) prod_{d' != d} s~_d'^E_md'
            f = pw[:, 0, ex[:, 0]] * pw[:, 1, ex[:, 1]] * pw[:, 2, ex[:, 2]] * pw[:, 3, ex[:, 3]]
            out[:, :, c] = f * (E[:, d] / scale[d])[None, :]
        return out

    def _model_update_bound(self, states: np.ndarray, rows: np.ndarray) -> np.ndarray:
        """(n,) an upper bound of |w_H' - w_H| over act()'s learner iterations for the bank rows ``rows`` (the other
        entries: inf), for _braking_superset. hjb_update's step is mu g / |g| (norm mu) plus c_H grad R, |grad R|
        <= |e_v / scale_v^2| |J_v(e)|_F / 2 c3 (e the row's leashed error, |d sat| <= 1); e is the own state less the
        own particle, exactly, except for a row whose particle may be deflected around a failed vehicle this step
        (_detour: within the sensor range of a vehicle farther than onset_from_m from its own particle): there the
        bound over the whole leash box (|e_p| <= e_pos_max_m, |e_v| <= e_vel_max_m_s)."""
        p, tp = self.preset, self.preset.tracking
        out = np.full(self.n, np.inf)
        if not tp.learn_hjb:
            out[rows] = 0.0
            return out
        lp = p.learner
        scale = np.asarray(self.sigma_H.scale, dtype=float)
        c3 = self.track_preset.cost.c3
        e = self._leash(states[rows] - self.plan.states[self.own_index[rows]])
        jv = np.sqrt(np.einsum("kmd,kmd->k", *(2 * [self._feature_grad_v(e)])))
        cf = np.sqrt((e[:, 2] / scale[2] ** 2) ** 2 + (e[:, 3] / scale[3] ** 2) ** 2)
        b = lp.K * (lp.mu + lp.c_H * cf * jv / (2.0 * c3))
        dp = p.detour
        if dp.enabled:
            part = self._vehicle_particles(states.shape[0])
            known = np.flatnonzero(part >= 0)
            dr = states[known, 0:2] - self.plan.states[part[known], 0:2]
            lost = known[dr[:, 0] ** 2 + dr[:, 1] ** 2 > (dp.onset_from_m - 2.0 * self._SENSED_POS_MARGIN_M) ** 2]
            if lost.size:
                d, _ = cKDTree(states[lost, 0:2]).query(states[rows, 0:2], k=1,
                                                        distance_upper_bound=p.backstop.sensor_range_m + 1e-6)
                near = np.isfinite(d)
                if np.any(near):
                    b[near] = lp.K * (lp.mu + lp.c_H * self._box_grad_bound() / (2.0 * c3))
        out[rows] = b
        return out

    def _box_grad_bound(self) -> float:
        """max over the leash box of |e_v / scale_v^2| |J_v(e)|_F (J_v: the sigma_H features' velocity gradient), bounded
        monomial by monomial (|e_x|, |e_y| <= e_pos_max_m, |e_vx|, |e_vy| <= e_vel_max_m_s)."""
        if self._box_bound is None:
            # every monomial's derivative is largest in magnitude at the box's corner (all components at their caps)
            tp = self.preset.tracking
            scale = np.asarray(self.sigma_H.scale, dtype=float)
            J = self._feature_grad_v(np.array([[tp.e_pos_max_m, tp.e_pos_max_m, tp.e_vel_max_m_s, tp.e_vel_max_m_s]]))
            self._box_bound = float(tp.e_vel_max_m_s / np.min(scale[2:4] ** 2) * np.sqrt(np.sum(J * J)))
        return self._box_bound

    def _vehicle_particles(self, n: int) -> np.ndarray:
        """(n,) _particles_of(arange(n)): the plan particle of vehicles 0..n-1 (a simulator bank's rows), kept (the map
        is fixed from the exchange on)."""
        if self._index_particles is None or self._index_particles.size != n:
            self._index_particles = self._particles_of(np.arange(n))
        return self._index_particles

    def _claim_rows(self, states: np.ndarray, margin: float) -> np.ndarray:
        """(N,) bool: the vehicles (rows of a bank holding every vehicle, states (N, 4) in id order) whose own plan particle
        is parked (own_slot_claim_max_speed_m_s) with another vehicle within the own-slot claim's radius of it (plus
        margin): to that row the other vehicle is unplanned (own_slot_claim in _backstop), wherever it is on the plan."""
        bp = self.preset.backstop
        out = np.zeros(states.shape[0], dtype=bool)
        if not bp.own_slot_claim or self._plan_ids is None or states.shape[0] < 2:
            return out
        part = self._vehicle_particles(states.shape[0])
        p = self.plan.states
        rows = np.flatnonzero(part >= 0)
        pr = p[part[rows]]
        rows = rows[pr[:, 2] ** 2 + pr[:, 3] ** 2 < bp.own_slot_claim_max_speed_m_s ** 2]
        if rows.size == 0:
            return out
        r = min(bp.plan_mismatch_m, 0.5 * self._spacing_m()) + margin
        d, j = cKDTree(states[:, 0:2]).query(p[part[rows], 0:2], k=2, distance_upper_bound=r)
        out[rows] = np.any(np.isfinite(d) & (j != rows[:, None]), axis=1)
        return out

    _BRUTE_MAX_PAIRS = 4096     # _beyond_plan: up to this many (state, particle) pairs by brute force, not the k-d tree

    def _plan_distance(self, q: np.ndarray) -> np.ndarray:
        """(m,) distance of states q to the nearest plan particle in the metric
        |dr|^2 + (plan_mismatch_s |dv|)^2; the particles' k-d tree is built once per plan step."""
        w = self._plan_metric_w
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
        if 0 < todo.size * self.plan.N <= self._BRUTE_MAX_PAIRS and threshold_m > 0:
            # a few states (a bank of one's sensed vehicles): every particle's distance, without (re)building the
            # k-d tree (the plan moves every step); decided only where clearly beyond or within (the same 1e-9
            # relative margin as above), the rest exactly by the tree
            ps = self.preset.backstop.plan_mismatch_s
            dx = q[todo, None, :] - self.plan.states[None, :, :]
            d2 = np.min(dx[:, :, 0] ** 2 + dx[:, :, 1] ** 2 + ps * ps * (dx[:, :, 2] ** 2 + dx[:, :, 3] ** 2), axis=1)
            beyond = d2 > (threshold_m * (1.0 + 1e-9)) ** 2
            out[todo[beyond]] = True
            todo = todo[~(beyond | (d2 <= (threshold_m * (1.0 - 1e-9)) ** 2))]
        if todo.size:
            out[todo] = self._plan_distance(q[todo]) > threshold_m
        return out

    def _unplanned(self, sensed_states: np.ndarray, ids: np.ndarray | None = None) -> np.ndarray:
        """Sensed vehicles farther than plan_mismatch_m from every plan particle, in the state
        metric |dr|^2 + (plan_mismatch_s |dv|)^2 (the plan -
        the same on every UAV - says where everyone should be; no communication needed), and those
        lost to the plan (_lost)."""
        return self._by_vehicle(lambda q, i: self._off_plan(q, i) | self._lost(q, i), sensed_states, ids)

    def _by_vehicle(self, test, states: np.ndarray, ids: np.ndarray | None) -> np.ndarray:
        """(m,) test(states, ids) for sensed entries, evaluated once per distinct sensed vehicle (many rows sense it,
        with the same state: _distinct_sensed) and spread back to its entries; entry by entry where ids are missing or
        one id's entries differ. ``test`` decides each entry from its own state and id alone."""
        d = self._distinct_sensed(states, ids)
        if d is None:
            return test(states, ids)
        first, inv = d
        return test(states[first], np.asarray(ids, dtype=np.int64)[first])[inv]

    def _lost(self, states: np.ndarray, ids: np.ndarray | None) -> np.ndarray:
        """(m,) bool: vehicles farther than ``plan_lost_m`` from their own plan particle (known by their id from the
        t = 0 exchange): a failed vehicle holding where the stream has left it. Near *some* particle it still looks
        on the plan where the plan passes through it (measured: circle N = 1,000, a vehicle in Hold on a UAV's path
        into its slot, cleared as that UAV's own particle; the UAV flew into it, 0.025 m)."""
        lost_m = self.preset.backstop.plan_lost_m
        out = np.zeros(states.shape[0], dtype=bool)
        if ids is None or lost_m <= 0 or self._plan_ids is None or states.shape[0] == 0 or len(ids) != states.shape[0]:
            return out
        part = self._particles_of(np.asarray(ids, dtype=np.int64))
        known = part >= 0
        dr = states[known, 0:2] - self.plan.states[part[known], 0:2]
        out[known] = dr[:, 0] ** 2 + dr[:, 1] ** 2 > lost_m * lost_m
        return out

    def _spacing_now_m(self) -> float:
        """The plan particles' smallest distance now (a translation spreads in cruise), else the slot spacing."""
        now = getattr(self.plan, "spacing_now_m", None)
        return float(now) if now is not None else self._spacing_m()

    def _on_detour(self, sn: Neighbours, unplanned: np.ndarray) -> np.ndarray:
        """(m,) bool: entries (among ``unplanned``) of rows whose plan is deflected (_detour) that are within
        plan_mismatch_m of their own particle deflected the same way, in the plan metric."""
        out = np.zeros(sn.states.shape[0], dtype=bool)
        det = self._detour_state
        if det is None or sn.ids is None or self._plan_ids is None:
            return out
        mask, o, alpha, clear, _ = det
        idx = np.flatnonzero(unplanned & mask[sn.owner])
        if idx.size == 0:
            return out
        part = self._particles_of(np.asarray(sn.ids, dtype=np.int64)[idx])
        known = part >= 0
        idx, part = idx[known], part[known]
        ps_all = self.plan.states[part]
        rows = sn.owner[idx]
        ps = self.preset.backstop.plan_mismatch_s
        # either side: the neighbour chose its side at its own first meeting with the vehicle
        for sgn in (1.0, -1.0):
            ds, _ = detour_offset(ps_all, np.zeros((idx.size, 2)), o[rows], alpha[rows], clear, self.preset.detour,
                                  self.preset.dt_s, np.full(idx.size, sgn))
            dx = sn.states[idx] - (ps_all + ds)
            d2 = dx[:, 0] ** 2 + dx[:, 1] ** 2 + ps * ps * (dx[:, 2] ** 2 + dx[:, 3] ** 2)
            out[idx] |= d2 <= self.preset.backstop.plan_mismatch_m ** 2
        return out

    def _detour(self, own: np.ndarray, obs: Observation) -> tuple[np.ndarray, np.ndarray, np.ndarray, float,
                                                                  np.ndarray] | None:
        """The rows whose plan is deflected around a failed vehicle (guidance/detour.py, DetourParams): (mask (n,), the
        nearest such vehicle's sensed position (n, 2), the onset alpha (n,), the clearance c, the own side (n,)), or
        None. Such a vehicle is sensed, hovers (slower than ``hover_max_speed_m_s``) and is farther than
        ``onset_from_m`` from its own particle (a failed one, left behind by the stream); alpha and c are the same for
        every row that senses it (from its sensed state, the plan and the plan's spacing now)."""
        dp = self.preset.detour
        if not dp.enabled or self._plan_ids is None:
            return None
        if self._detour_mem is None:
            self._detour_mem = (np.full(self.n, -1, dtype=np.int64), np.zeros(self.n))
        sn = _sensed(obs)
        if sn.ids is None or sn.states.shape[0] == 0:
            return None
        st = sn.states
        ids = np.asarray(sn.ids, dtype=np.int64)
        d = self._distinct_sensed(st, sn.ids)
        if d is None:
            idx, dist = self._lost_hovering(st, ids)
        else:
            # each sensed vehicle once (the same state in every row that senses it), then its entries
            first, inv = d
            i1, dist1 = self._lost_hovering(st[first], ids[first])
            far1 = np.zeros(first.size, dtype=bool)
            far1[i1] = True
            idx = np.flatnonzero(far1[inv])
            if idx.size:
                at = np.zeros(first.size)
                at[i1] = dist1
                dist = at[inv[idx]]
        if idx.size == 0:
            return None
        alpha = detour_onset(dist, dp)
        rows = sn.owner[idx]
        first = nearest_per_row(rows, st[idx, 0:2] - own[rows, 0:2])
        mask = np.zeros(self.n, dtype=bool)
        o, al, side = np.zeros((self.n, 2)), np.zeros(self.n), np.zeros(self.n)
        r = rows[first]
        mask[r], o[r], al[r] = True, st[idx[first], 0:2], alpha[first]
        # the side of the own particle's lane, chosen at the row's first meeting with that vehicle (by id) and kept
        # while it is the row's nearest lost one: the vehicle drifts in the wind across a lane close to it
        tid = ids[idx[first]]
        # (where the lane passes it: a turning lane by its curvature, from the particle's velocity change over the last
        # step; the plan's command also holds the drag and the mean wind, which do not bend the lane)
        a_kin = self._plan_acc(self.plan.k)
        side[r] = detour_side(self.plan.states[self.own_index[r]], o[r],
                              None if a_kin is None else a_kin[self.own_index[r]])
        mem_id, mem_side = self._detour_mem
        keep = mem_id[r] == tid
        if dp.side_from_escape and self._side_mem is not None:
            # a row whose escape already chose a side for that vehicle (at its braking stop point, before it hovered:
            # BackstopParams.escape_braking_as_hover) deflects its lane to that side, not to the one its sensed position
            # gives now: the two differ for the lane right through it, and the escape would turn over under the row
            # (dense --fail-vehicle N = 800 seed 152, UAV 130: right at one step, left at the next, 0.035 m)
            e_id, e_side = self._side_mem
            vp = self.plan.states[self.own_index[r], 2:4]
            sgn = np.sign(e_side[r, 0] * -vp[:, 1] + e_side[r, 1] * vp[:, 0])     # the remembered side . left of track
            take = ~keep & (e_id[r] == tid) & (sgn != 0)
            side[r] = np.where(take, sgn, side[r])
        side[r] = np.where(keep, mem_side[r], side[r])
        mem_id[:], mem_side[:] = -1, 0.0
        mem_id[r], mem_side[r] = tid, side[r]
        clear = min(dp.clear_max_m, dp.clear_fraction * self._spacing_now_m())
        return mask, o, al, clear, side

    def _lost_hovering(self, st: np.ndarray, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """_detour's candidates among sensed states st (m, 4) with ids (m,): (the entries that hover - slower than
        ``hover_max_speed_m_s`` - and are farther than ``onset_from_m`` from their own particle, ascending; that
        distance)."""
        idx = np.flatnonzero(st[:, 2] ** 2 + st[:, 3] ** 2 < self.preset.backstop.hover_max_speed_m_s ** 2)
        if idx.size == 0:
            return idx, np.zeros(0)
        part = self._particles_of(ids[idx])
        known = part >= 0
        idx, part = idx[known], part[known]
        dist = np.hypot(*(st[idx, 0:2] - self.plan.states[part, 0:2]).T)
        far = dist > self.preset.detour.onset_from_m
        return idx[far], dist[far]

    def _yielding(self, sn: Neighbours, covered: np.ndarray) -> np.ndarray:
        """(m,) bool: the sensed entries that neither response covers (``covered`` False) and that the observing row
        yields to: the row is off its own particle by more than ``escape_yield_min_dev_m`` and the sensed vehicle
        (known by its id) flies within ``escape_yield_on_plan_m`` of its own particle; only while the plan's particles
        are at least ``escape_yield_min_spacing_m`` apart (room to pass between two of them).

        Why: the state test asks whether a vehicle is near *some* particle. A UAV blown metres behind its particle
        catches up through the slots of the UAVs ahead of it, near *their* particles, so it looks on the plan to
        them, and to it they are on the plan; in a rigid plan neither response covers the pair (measured: swap4
        --gust N = 10,000 seeds 5 and 7, UAVs 1.3-3 m behind their particles closed on the one ahead at 0.5 m/s: 1
        and 2 collided pairs). One side acts, the one off its particle: the escape predicts the other vehicles at
        constant velocity, which holds for one that flies its particle. Tried and not kept: both escaping
        (``escape_gap``: paper --gust N = 1,000, 6 pairs), the more deviated one yielding to any other (22 pairs
        there: in the gust every UAV is off its particle), and yielding in the unspread 0.5 m grid (dense --gust
        N = 144 without the spread, 1 -> 7 pairs: no room to pass). docs/default_controller.md, "A UAV off its
        particle yields to one on it"."""
        bp = self.preset.backstop
        out = np.zeros(sn.states.shape[0], dtype=bool)
        if self._own_err is None or self._plan_ids is None or sn.ids is None or sn.states.shape[0] == 0:
            return out
        if self._spacing_now_m() < bp.escape_yield_min_spacing_m:
            return out
        dev_own = np.hypot(self._own_err[:, 0], self._own_err[:, 1])
        idx = np.flatnonzero(~covered & (dev_own[sn.owner] > bp.escape_yield_min_dev_m))
        if idx.size == 0:
            return out
        part = self._particles_of(np.asarray(sn.ids, dtype=np.int64)[idx])
        known = part >= 0
        idx, part = idx[known], part[known]
        dr = sn.states[idx, 0:2] - self.plan.states[part, 0:2]
        out[idx] = np.hypot(dr[:, 0], dr[:, 1]) < bp.escape_yield_on_plan_m
        return out

    def _escape_side(self, own: np.ndarray, sn: Neighbours, hover_threat: np.ndarray,
                     at_m: np.ndarray | None = None) -> np.ndarray | None:
        """(n, 2): for a row with a threat entry that hovers (hover_threat (m,): slower than ``hover_max_speed_m_s``, failed in
        Hold, drifting), the unit vector across its own particle's track on the side of that track the nearest such vehicle is *not* on; 0
        for the other rows; None when there is none (backstop.escape_acc: a candidate towards the other side costs
        ``escape_side_commit`` x its lateral share of a_max). From the plan, not from the UAV's state: every UAV's
        particle flies a lane, the lanes left of the failed vehicle pass it on the left and those right of it on the
        right, the same for lane mates ahead and behind, whatever the noise does to each UAV's own state; a lane right
        through it passes on the right (as the keep-right term). With ``escape_side_memory`` the side chosen at a row's
        first meeting with a vehicle (by id) is kept while that vehicle is the row's nearest hovering one: a failed
        vehicle drifts in the wind, 0.2-0.3 m across the lanes, and a lane a few centimetres off it would swap sides.

        Why: a UAV coming up to a failed vehicle nearly head-on chose a side at one step and the other at the next: in
        dense --fail-vehicle N = 5,000 seed 24, UAV 1228 commanded +0.47, -0.84, +1.97, -1.93 m/s^2 across its track on
        four consecutive steps and passed the failed vehicle at 0.094 m.

        at_m (m, 2), optional: where each entry is taken to be for the side (None: where it is sensed); a vehicle still
        braking to its Hold is taken at its braking stop point (BackstopParams.escape_braking_as_hover)."""
        bp = self.preset.backstop
        if bp.escape_side_commit <= 0 or self.plan is None:
            return None
        idx = np.flatnonzero(hover_threat)
        if idx.size == 0:
            return None
        rows = sn.owner[idx]
        first = nearest_per_row(rows, sn.states[idx, 0:2] - own[rows, 0:2])      # the nearest hovering threat of each row
        r, q = rows[first], (sn.states if at_m is None else at_m)[idx[first], 0:2]
        part = self.plan.states[self.own_index[r]]
        vp = part[:, 2:4]
        vn = np.hypot(vp[:, 0], vp[:, 1])
        across = np.stack([-vp[:, 1], vp[:, 0]], axis=1) / np.maximum(vn, 1e-12)[:, None]     # left of the track
        cross = np.sum((part[:, 0:2] - q) * across, axis=1)          # > 0: the lane lies left of the vehicle
        moving = (vn > bp.u_noise_m_s)[:, None]                      # a parked particle has no track: no side
        side = np.where((cross > 0)[:, None], across, -across) * moving
        if bp.escape_side_memory and sn.ids is not None:
            # the side chosen when the row first met that vehicle, kept while it is the nearest hovering one (a failed
            # vehicle drifts in the wind: a lane 5 cm off it would otherwise swap sides under it)
            if self._side_mem is None:
                self._side_mem = (np.full(self.n, -1, dtype=np.int64), np.zeros((self.n, 2)))
            mem_id, mem_side = self._side_mem
            tid = sn.ids[idx[first]]
            keep = (mem_id[r] == tid) & np.any(mem_side[r] != 0, axis=1)
            # the remembered side as a sign across the current track (the track turns slowly; the sign is what is kept)
            sgn = np.sign(np.sum(mem_side[r] * across, axis=1))
            side = np.where((keep & (sgn != 0))[:, None], sgn[:, None] * across * moving, side)
            mem_id[r], mem_side[r] = tid, side
        det = self._detour_state
        if det is not None:
            # a row flying the plan deflected around a lost vehicle passes it on the deflection's side
            on = det[0][r]
            side = np.where(on[:, None], det[4][r][:, None] * across * moving, side)
        out = np.zeros((self.n, 2))
        out[r] = side
        return out

    def _gap_pairs(self, sn: Neighbours, covered: np.ndarray) -> np.ndarray:
        """(m,) bool: the sensed entries that no other response covers (``covered`` False: neither unplanned, nor in
        the planned response, nor yielded to), while the plan's particles are at least ``gap_push_min_spacing_m`` apart
        now. They get the gap push: the reciprocal half-plane push with a short horizon (``gap_push_*``).

        Why: two UAVs both off their particles, each near *some* particle or off the plan the way the other is (common
        mode), get no response from either (the gap): measured (with the crowded push's flow reach), swap4 --gust
        N = 10,000 seed 8, UAVs 9400 and 9401 (1.2 and 2.2 m off their particles) closed from 0.55 m to 0.06 m over
        three control periods, neither acting.
        The push reaches a pair predicted closer than 0.35 x the spacing within 1 s; with the 2 s horizon of the planned
        response it acted at the gust's onset on pairs that were only passing (paper --gust N = 1,000 seed 3: smallest
        separation 0.877 -> 0.508 m). Not in the unspread 0.5 m grid (no room: as for the yield; measured, dense
        --gust N = 144 with cruise_spacing_m = 0, seed 2: 19 collided pairs with it there, 1 without), except for a row
        that senses a vehicle lost to the plan (``gap_push_near_lost``, _lost: a failed one): the pad closing into its
        slots around a failed vehicle, where UAVs escaping it at full authority close on their lane mates (dense
        --fail-vehicle N = 10,000 seeds 6 and 7: a pair each, 0.021 / 0.085 m, neither acting). For a rigid plan
        the entries include the neighbours of a row on its particle (the planned response is off there), which
        fly 1.41 m and more apart and do not trigger it. docs/default_controller.md, "The gap push"."""
        bp = self.preset.backstop
        out = np.zeros(sn.states.shape[0], dtype=bool)
        if not bp.gap_push or self._own_err is None or sn.states.shape[0] == 0:
            return out
        if self._spacing_now_m() < bp.gap_push_min_spacing_m:
            if not bp.gap_push_near_lost:
                return out
            # only the rows that sense a failed vehicle (every vehicle within the sensor range: sensed_cutoff_m makes
            # such a row wide, so the entries are the same under the simulator's reach-limited delivery)
            # once per distinct vehicle (at N = 10,000 the pad's ~3 million entries took 0.44 s per step one by one)
            lost = self._by_vehicle(self._lost, sn.states, sn.ids)
            if not np.any(lost):
                return out
            near = np.bincount(sn.owner[lost], minlength=self.n) > 0
            return ~covered & near[sn.owner]
        return ~covered

    def _distinct_sensed(self, q: np.ndarray, ids: np.ndarray | None) -> tuple[np.ndarray, np.ndarray] | None:
        """_distinct(q, ids), computed once per act() for the same arrays (_detour and _unplanned both ask it of the
        step's sensed vehicles: ~6 ms each at N = 10,000)."""
        memo = self._distinct_memo
        if memo is not None and memo[0] is q and memo[1] is ids:
            return memo[2]
        d = self._distinct(q, ids)
        self._distinct_memo = (q, ids, d)
        return d

    @staticmethod
    def _distinct(q: np.ndarray, ids: np.ndarray | None) -> tuple[np.ndarray, np.ndarray] | None:
        """(first, inv): one representative entry per distinct id and each entry's rank among them (q[first][inv] is q),
        where every entry of an id carries the same state (the same vehicle sensed by many rows); None where ids are
        missing or two entries of one id differ. Distinct ids ascending, as np.unique gives them, in O(m + max id)
        instead of a sort where the ids are small (safety.kernels.distinct_dense, compiled: at N = 10,000 the numpy
        version's gathers and full comparison were ~45 ms of a ~250 ms control step); the representative of an id is
        one of its entries."""
        if ids is None or len(ids) != q.shape[0] or q.shape[0] == 0:
            return None
        ids = np.asarray(ids, dtype=np.int64)
        if _dense_ids(ids):
            first, inv, ok = distinct_dense(_kernel_arg(q, np.float64), _kernel_arg(ids, np.int64), int(ids.max()) + 1)
            return (first, inv) if ok else None
        _, first, inv = np.unique(ids, return_index=True, return_inverse=True)
        inv = inv.reshape(-1)
        if not np.array_equal(q[first][inv], q):
            return None
        return first, inv

    def _off_plan(self, sensed_states: np.ndarray, ids: np.ndarray | None = None) -> np.ndarray:
        """(m,) bool: _unplanned's state test, entry by entry: farther than plan_mismatch_m from every particle (ids, if
        given: each entry's own particle as _beyond_plan's hint; _unplanned queries each distinct vehicle once)."""
        if sensed_states.shape[0] == 0:
            return np.zeros(0, dtype=bool)
        hint = np.asarray(ids, dtype=np.int64) if ids is not None and len(ids) == sensed_states.shape[0] else None
        return self._beyond_plan(sensed_states, self.preset.backstop.plan_mismatch_m, hint)

    def _particle_velocity_near(self, xy: np.ndarray) -> np.ndarray:
        """(k, 2) the velocity of the plan particle nearest each point of xy (k, 2), by a k-d tree of the plan's
        positions kept for the plan step."""
        if self._flow_tree is None or self._flow_tree[0] != self.plan.k:
            self._flow_tree = (self.plan.k, cKDTree(self.plan.states[:, 0:2]))
        _, j = self._flow_tree[1].query(xy, k=1)
        return self.plan.states[j, 2:4]

    def _in_stream(self, states: np.ndarray) -> np.ndarray:
        """(m,) bool: the entries of states (m, 4) whose nearest plan particle flies faster than unplanned_flow_min_m_s
        (where the plan moves: a vehicle hovering there is not parked with the plan)."""
        if self.plan is None or states.shape[0] == 0:
            return np.zeros(states.shape[0], dtype=bool)
        vp = self._particle_velocity_near(states[:, 0:2])
        return vp[:, 0] ** 2 + vp[:, 1] ** 2 > self.preset.backstop.unplanned_flow_min_m_s ** 2

    def _cbf_share(self, sn: Neighbours, rows: np.ndarray) -> np.ndarray | None:
        """Each sensed entry's share of its barrier constraint (backstop.cbf_acc): crowd_cbf_share, but all of it (1)
        for a vehicle that hovers (slower than hover_max_speed_m_s) where the plan flies (its nearest particle faster
        than unplanned_flow_min_m_s): one failed into Hold in the stream, which takes no half. Not for a vehicle that is
        slow where the plan is slow too (a group at its departure: measured, full shares there made the constraints
        infeasible more often, crossing --gust N = 137 seed 118 0.262 -> 0.109 m). Only the entries of ``rows`` are
        read."""
        bp = self.preset.backstop
        if self.plan is None or not bp.crowd_cbf_hover_full_share:
            return None
        share = np.full(sn.states.shape[0], bp.crowd_cbf_share)
        in_rows = np.zeros(self.n, dtype=bool)
        in_rows[rows] = True
        v2 = sn.states[:, 2] ** 2 + sn.states[:, 3] ** 2
        idx = np.flatnonzero(in_rows[sn.owner] & (v2 < bp.hover_max_speed_m_s ** 2))
        if idx.size == 0:
            return share
        share[idx[self._in_stream(sn.states[idx])]] = 1.0
        return share

    def _unplanned_reach(self, states: np.ndarray, unplanned: np.ndarray, trig_m: float,
                         clear_m: float) -> tuple[np.ndarray, np.ndarray]:
        """The escape's trigger and clearance per sensed entry. An off-plan vehicle that still moves with the plan's
        flow where it is (its velocity within ``unplanned_flow_m_s`` of the nearest particle's, where that particle
        flies faster than ``unplanned_flow_min_m_s``: a UAV a gust blew off its particle in cruise) gets the smaller
        ``unplanned_flow_trigger_m`` / ``unplanned_flow_target_m`` (at most trig_m / clear_m): it closes on its
        neighbours only at the gust's relative speed, and the large reach made the escapes from such drifting
        neighbours carry UAVs through the formation (crossing --gust). A vehicle stopped or hovering in a moving
        plan, or off the plan where the plan itself is slow, keeps trig_m / clear_m."""
        bp = self.preset.backstop
        m = states.shape[0]
        trig, clear = np.full(m, trig_m), np.full(m, clear_m)
        idx = np.flatnonzero(unplanned)
        if idx.size == 0 or bp.unplanned_flow_m_s <= 0 or self.plan is None:
            return trig, clear
        vp = self._particle_velocity_near(states[idx, 0:2])
        dv = states[idx, 2:4] - vp
        flow = ((vp[:, 0] ** 2 + vp[:, 1] ** 2 > bp.unplanned_flow_min_m_s ** 2)
                & (dv[:, 0] ** 2 + dv[:, 1] ** 2 < bp.unplanned_flow_m_s ** 2))
        trig[idx[flow]] = min(trig_m, bp.unplanned_flow_trigger_m)
        clear[idx[flow]] = min(clear_m, bp.unplanned_flow_target_m)
        return trig, clear

    def _plan_acc(self, step: int) -> np.ndarray | None:
        """(N, 2) each plan particle's acceleration over the step before ``step`` (its velocity change / dt), None if
        the plan is not at ``step`` or its velocities at step - 1 were not recorded (records the current ones)."""
        if self.plan.k != step:
            return None
        s = self._plan_s_hist.get(step)
        if s is None:
            s = self.plan.states.copy()
            self._plan_s_hist = {k: x for k, x in self._plan_s_hist.items() if k == step - 1}
            self._plan_s_hist[step] = s
        prev = self._plan_s_hist.get(step - 1)
        return None if prev is None else (s[:, 2:4] - prev[:, 2:4]) / self.preset.dt_s

    def _particles_of(self, ids: np.ndarray) -> np.ndarray:
        """(m,) the plan particle of each vehicle id (the t = 0 exchange's order), -1 for an id it did not hold. By a
        table where the exchange's ids are small non-negative integers (the simulator's 0..N-1: a gather instead of
        a binary search over millions of sensed entries per step after a gust), else by binary search; the same
        answer either way (a repeated id: its first particle)."""
        table = self._id_table
        if table is not None:
            ids = np.asarray(ids)
            inside = (ids >= 0) & (ids < table.size)
            if inside.all():
                return table[ids]
            return np.where(inside, table[np.where(inside, ids, 0)], -1)
        sid, spart = self._plan_ids
        at = np.minimum(np.searchsorted(sid, ids), sid.size - 1)
        return np.where(sid[at] == ids, spart[at], -1)

    def _hover_latched(self, sn: Neighbours, step: int, unplanned: np.ndarray, hover: np.ndarray) -> np.ndarray:
        bp = self.preset.backstop
        if bp.hover_latch_s <= 0 or sn.ids is None or self.plan is None or self._plan_ids is None:
            return hover
        if self._hover_k is None or self._hover_k.shape[0] != self.plan.N:
            self._hover_k = np.full(self.plan.N, -(1 << 40), dtype=np.int64)      # the last step each hovered
        # only the off-plan entries can latch or renew (hover is off the plan too): after a gust a bank senses millions
        idx = np.flatnonzero(unplanned)
        part = self._particles_of(np.asarray(sn.ids, dtype=np.int64)[idx])
        idx, part = idx[part >= 0], part[part >= 0]
        st = sn.states[idx]
        v2 = st[:, 2] ** 2 + st[:, 3] ** 2
        k_latch = int(round(bp.hover_latch_s / self.preset.dt_s))
        latch = (step - self._hover_k[part] <= k_latch) & (v2 < bp.hover_latch_max_speed_m_s ** 2)
        if np.any(latch):
            # not one that flies towards its own plan particle: a healthy UAV recovering its plan after the gust pinned
            # it (crossing --gust N = 137 s125, no failure: latched, it kept the hover rules while it accelerated back
            # into the stream, 0.433 -> 0.198 m; with this gate 0.352 m)
            to_p = self.plan.states[part, 0:2] - st[:, 0:2]
            dist = np.maximum(np.hypot(to_p[:, 0], to_p[:, 1]), 1e-9)
            towards = (st[:, 2] * to_p[:, 0] + st[:, 3] * to_p[:, 1]) / dist
            latch &= towards < bp.hover_latch_max_towards_plan * np.sqrt(v2)
        out = hover.copy()
        out[idx[latch]] = True
        self._hover_k[part[out[idx]]] = step
        return out

    def _rear_responsible(self) -> bool:
        return self.preset.backstop.escape_rear_responsible

    def _seen_snapshot(self) -> tuple[np.ndarray, np.ndarray] | None:
        if self._seen_v is None or self.plan is None or self._plan_ids is None:
            return None
        return self._seen_v.copy(), self._seen_k.copy()

    def _entry_prev_v(self, sn: Neighbours, step: int,
                      seen: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray] | None:
        m = sn.states.shape[0]
        if sn.ids is None:
            return None
        seen_v, seen_k = seen
        part = self._particles_of(np.asarray(sn.ids, dtype=np.int64))
        pv = np.zeros((m, 2))
        ok = part >= 0
        was = np.zeros(m, dtype=bool)
        was[ok] = seen_k[part[ok]] == step - 1
        pv[was] = seen_v[part[was]]
        known = was.copy()
        full = self._cutoff_hist.get(step - 1)
        if full is not None and full.shape[0] == self.plan.N:
            f = ok & ~was
            pv[f] = full[part[f], 2:4]
            known |= f
        return pv, known

    def _unplanned_by_braking(self, sn: Neighbours, step: int, unplanned: np.ndarray, own: np.ndarray) -> np.ndarray:
        """(m,) bool: sensed vehicles that brake against their own plan particle by more than plan_mismatch_brake_m_s2
        and would be beyond plan_mismatch_m after one more period of it (braking_off_plan), for the rows that sense no
        vehicle off the plan yet (unplanned (m,): the entries already off it). The test is for the onset of a failure:
        around a vehicle that is off the plan, the UAVs that escape it brake and swerve on purpose (measured: with the
        test on every row, dense N = 1000, vehicle 10 failing at 20 s, seed 4: the escapes flagged the neighbours, whose
        escapes flagged theirs: 98 collided pairs instead of 2). The previous sample of a vehicle is what this bank
        sensed of it at step - 1, or, in the simulator, which delivers only the sensed vehicles within
        sensed_cutoff_m's reach, the full observed state passed to sensed_cutoff_m then. Records this step's sensed
        velocities."""
        bp = self.preset.backstop
        m = sn.states.shape[0]
        out = np.zeros(m, dtype=bool)
        if bp.plan_mismatch_brake_m_s2 <= 0 or self.plan is None or self._plan_ids is None:
            return out
        a_plan = self._plan_acc(step)
        own_prev, self._own_v_prev = self._own_v_prev, (step, np.array(own[:, 2:4], dtype=float))
        if sn.ids is None or m == 0:
            return out
        N = self.plan.N
        if self._seen_v is None:
            self._seen_v, self._seen_k = np.zeros((N, 2)), np.full(N, -1, dtype=np.int64)
        part = self._particles_of(np.asarray(sn.ids, dtype=np.int64))
        # one compiled pass over the entries (safety.kernels.braking_scan: braking_off_plan's numbers), then the plan
        # distance of the few that brake
        do_test = a_plan is not None and step >= 1
        full = self._cutoff_hist.get(step - 1)
        has_full = full is not None and full.shape[0] == N
        has_own = own_prev is not None and own_prev[0] == step - 1 and do_test
        own_ref = np.zeros((0, 2))
        if has_own:
            # the common mode the braking must exceed: the own row's acceleration the plan and the own command do not
            # explain - its own velocity change less what eq. 9 makes of the command it sent (the wind: a head wind
            # or a gust brakes the observer as it brakes its neighbours) - or, with "deviation", less only the own
            # particle's (then the observer's own commanded braking - following a neighbour that brakes, through
            # the formation's mean - hides that neighbour's Hold: docs/default_controller.md, fifteenth session)
            v, v0 = np.asarray(own[:, 2:4], dtype=float), own_prev[1]
            if bp.plan_mismatch_brake_common == "disturbance" and self._own_a_prev is not None \
                    and self._own_a_prev[0] == step - 1:
                c = self.preset.cost
                own_ref = disturbance_residual_m_s2(v, v0, self._own_a_prev[1], self.preset.dt_s, c.c0_per_s, c.v_o)
            else:
                own_ref = (v - v0) / self.preset.dt_s - a_plan[self.own_index]
        idx, shifted = braking_scan(_kernel_arg(sn.owner, np.int64), _kernel_arg(part, np.int64), _kernel_arg(sn.states, np.float64),
                                    _kernel_arg(unplanned, np.bool_), self.n, self._seen_v, self._seen_k,
                                    _kernel_arg(full if has_full else np.zeros((0, 4)), np.float64), has_full,
                                    _kernel_arg(a_plan if do_test else np.zeros((0, 2)), np.float64), do_test,
                                    _kernel_arg(own_ref, np.float64), has_own, int(step), float(self.preset.dt_s),
                                    float(bp.plan_mismatch_brake_m_s2))
        if idx.size:
            # beyond the plan after one more period of the braking, then (of those: in cruise, ~1 in 20 of the braking
            # entries; each test decides entry by entry, so the order does not matter) beyond the own tracking
            far = self._beyond_plan(shifted, bp.plan_mismatch_m, part[idx])
            idx, shifted = idx[far], shifted[far]
        if idx.size and bp.plan_mismatch_brake_expected:
            keep = self._brakes_beyond_tracking(sn, idx, shifted, part[idx], a_plan, step, own_ref if has_own else None)
            idx = idx[keep]
        out[idx] = True
        return out

    def _brakes_beyond_tracking(self, sn: Neighbours, idx: np.ndarray, shifted: np.ndarray, part: np.ndarray,
                                a_plan: np.ndarray, step: int, own_ref: np.ndarray | None) -> np.ndarray:
        """(k,) bool: of the braking entries idx (braking_scan's; shifted their states plus one more period of the
        braking), those whose braking exceeds plan_mismatch_brake_m_s2 also beyond what their own tracking explains:
        the command eq. 8 makes of their deviation from their particle at the previous sample (estimated from the
        sensed state and the measured braking; the observing row's value model w_H stands in for theirs), and beyond it
        less own_ref too ((n, 2) per row, the common mode of _unplanned_by_braking; None: not known this step). A UAV
        that was faster than its particle brakes back by command (eq. 8's nearly deadbeat answer to the last period's
        wind); a vehicle in Hold brakes whatever its deviation was. docs/default_controller.md, "The braking test subtracts the
        neighbour's own tracking"."""
        p = self.preset
        prev = self._plan_s_hist.get(step - 1)
        if prev is None:
            return np.ones(idx.size, dtype=bool)
        meas, v_prev, e = self._prev_deviation(sn.states[idx], shifted, part, a_plan, prev)
        a_exp = a_plan[part] + self._eq8_fb(e, sn.owner[idx])
        r = meas - a_exp
        speed = np.maximum(np.linalg.norm(v_prev, axis=1), 1e-9)
        th = p.backstop.plan_mismatch_brake_m_s2
        out = (r[:, 0] * v_prev[:, 0] + r[:, 1] * v_prev[:, 1]) / speed < -th
        if own_ref is not None:
            # and beyond the common mode, as the scan's test (a gust brakes the observer as it brakes the neighbour)
            r = r - own_ref[sn.owner[idx]]
            out &= (r[:, 0] * v_prev[:, 0] + r[:, 1] * v_prev[:, 1]) / speed < -th
        return out

    def _prev_deviation(self, q: np.ndarray, shifted: np.ndarray, part: np.ndarray, a_plan: np.ndarray,
                        plan_prev: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """From sensed states q (k, 4) and braking_scan's shifted states (one more period of the braking): (the
        measured velocity change / dt (k, 2), the previous velocity (k, 2), the deviation from the own particle
        ``part`` at the previous sample (k, 4), plan_prev the particles' states then)."""
        dt = self.preset.dt_s
        meas = (shifted[:, 2:4] - q[:, 2:4]) / dt + a_plan[part]         # the measured velocity change / dt
        v_prev = q[:, 2:4] - dt * meas
        p_prev = q[:, 0:2] - 0.5 * dt * (q[:, 2:4] + v_prev)
        return meas, v_prev, np.concatenate([p_prev, v_prev], axis=1) - plan_prev[part]

    def _leash(self, err: np.ndarray) -> np.ndarray:
        """A tracking error (k, 4) as the value model sees it: position and velocity parts each capped in norm
        (TrackingParams.e_pos_max_m, e_vel_max_m_s)."""
        tp = self.preset.tracking
        return np.concatenate([cap_norm(err[:, 0:2], tp.e_pos_max_m), cap_norm(err[:, 2:4], tp.e_vel_max_m_s)], axis=1)

    def _eq8_fb(self, err: np.ndarray, rows: np.ndarray) -> np.ndarray:
        """Eq. 8's feedback on tracking errors err (k, 4), leashed, with the value models of bank rows ``rows`` (k,):
        -(1 / 2 c3) B^T grad psi(e; w_H[rows]) (k, 2). act() leashes its own error the same way and takes grad psi
        from the HJB update."""
        return optimal_action(self.sigma_H.grad_psi(self._leash(err), self.w_H[rows]), self.preset.cost.c3)

    def _formation_error(self, obs: Observation) -> tuple[np.ndarray, np.ndarray]:
        """(e_bar (n, 4), count (n,)): the mean deviation from the plan, s - s_plan, over the own vehicle and the
        sensed neighbours whose plan particle is within formation_radius_spacings x the plan spacing of the own
        particle (each neighbour's particle by its id, from the t = 0 exchange; no communication). count - 1
        neighbours entered it (0: e_bar is the own deviation)."""
        n, e = self.n, self._own_err
        cnt = np.ones(n)
        sn = _sensed(obs)
        if sn.states.shape[0] == 0 or sn.ids is None or self._plan_ids is None or not np.isfinite(self.plan.spacing_m):
            return e.copy(), cnt
        sid, spart = self._plan_ids
        # the plan's spacing now: a translation spread in cruise holds its neighbours farther apart than at the start
        r_max = self.preset.tracking.formation_radius_spacings * self._spacing_now_m()
        # a sensed vehicle whose plan particle is near the own particle is near the own vehicle too (both track them):
        # the sensed positions pre-select, with the own deviation and twice the outlier bound as margin, before the
        # ids are looked up (the sensor delivers many more vehicles than the formation radius holds). A neighbour off
        # the plan other than the own vehicle is (a failed UAV braking in Hold) is not the formation: left out beyond
        # formation_outlier_m of the own deviation, in the plan metric (measured: with it, the dense formation around
        # vehicle 40 failing at 20 s, seed 2, was pulled after it: 6 collided pairs instead of 0). One compiled pass
        # (safety.kernels.formation_sums, the numpy formulation's numbers).
        out_m = self.preset.tracking.formation_outlier_m
        pre_r = r_max + 2.0 * out_m + 2.0 * float(np.max(np.linalg.norm(e[:, 0:2], axis=1)))
        sums, got = formation_sums(_kernel_arg(sn.owner, np.int64), _kernel_arg(sn.ids, np.int64),
                                   _kernel_arg(sn.states, np.float64), _kernel_arg(obs.own_states, np.float64),
                                   _kernel_arg(e, np.float64), _kernel_arg(sid, np.int64), _kernel_arg(spart, np.int64),
                                   _kernel_arg(self.plan.states, np.float64), _kernel_arg(self.own_index, np.int64), n,
                                   float(r_max), float(out_m), float(self.preset.backstop.plan_mismatch_s), float(pre_r))
        if not np.any(got):
            return e.copy(), cnt
        cnt += got
        return (e + sums) / cnt[:, None], cnt

    def _relative_priority(self, a_plan: np.ndarray, a_nom: np.ndarray, obs: Observation) -> np.ndarray:
        """The tracking command of a row with formation neighbours (TrackingParams.relative_priority), in place of
        a_nom = a_plan + a_fb(e): the error splits into the formation's common mode e_bar (_formation_error) and
        the relative error e - e_bar; the relative feedback a_rel = a_fb(e - e_bar) comes first, capped at
        acc_max, and the common share
        a_com = a_plan + a_fb(e_bar) gets at most min(common_acc_max, acc_max - |a_rel|). Both a_fb as in act()
        (the value model's eq. 8, errors leashed). Rows without formation neighbours keep a_nom."""
        p, tp = self.preset, self.preset.tracking
        a_max, c_max = p.learner.acc_max_m_s2, tp.common_acc_max_m_s2
        e_bar, cnt = self._formation_error(obs)
        if self._detour_state is not None:
            # a row flying the deflected plan (_detour) tracks it alone: its neighbours' errors are measured against
            # the plan they do not fly there
            cnt = np.where(self._detour_state[0], 1.0, cnt)
        rows = np.flatnonzero(cnt > 1)
        if rows.size == 0:
            return a_nom

        a_rel = cap_norm(self._eq8_fb(self._own_err[rows] - e_bar[rows], rows), a_max)
        a_com = a_plan[rows] + self._eq8_fb(e_bar[rows], rows)
        room = np.maximum(np.minimum(c_max, a_max - np.linalg.norm(a_rel, axis=1)), 0.0)
        a_com = cap_norm(a_com, room)
        out = a_nom.copy()
        out[rows] = cap_norm(a_rel + a_com, a_max)
        return out

    # -- Algorithm 4's coupling: phi_G(s_i, m_hat) over nearby plan particles, FPK-weighted (eq. 11)
    def _phi_G(self, own: np.ndarray, centroid: np.ndarray) -> tuple[np.ndarray, int]:
        """phi_G(s_i, m_hat) (n,) and the number of (row, particle) pairs: the plan particles within
        phi_g_radius_m of each row's position (its own particle left out), each row's in ascending
        index, weighted by max(m_hat, 0) with m_hat = w_F,i . sigma_F(x_j - centroid) (uniform without
        the FPK model or if every weight is 0). One fused pass per row (kernels.phi_G_plan)."""
        tp, cost = self.preset.tracking, self.preset.cost
        return kernels.phi_G_plan(own, self.own_index, self.plan.states, centroid, self.sigma_F.exponents, self.sigma_F.scale,
                                  self.w_F, tp.phi_g_radius_m, cost.eps_m2, cost.beta, tp.learn_fpk)

    def _fpk_update(self, own: np.ndarray, a: np.ndarray, centroid: np.ndarray, centroid_rate: np.ndarray,
                    hess_v_psi_trace: np.ndarray) -> None:
        """Algorithm 4 step 3 at the own state, FPK model in the plan's co-moving frame:
        F = J_F (b - d s_bar/dt) + sigma_F div b - 1/2 tr(G G^T hess m_hat), linear in w_F;
        b = A s + B (a + c0 v_o), div b = -2 c0 - (psi_vxvx + psi_vyvy) / (2 c3) (kernels.fpk_update_rows)."""
        cost, lp = self.preset.cost, self.preset.learner
        n = own.shape[0]
        self.w_F, _ = kernels.fpk_update_rows(self.sigma_F.exponents, self.sigma_F.scale, own - centroid[None, :], own, a,
                                              np.broadcast_to(centroid_rate, (n, 4)), hess_v_psi_trace, self.w_F,
                                              cost.c0_per_s, cost.v_o, cost.c3, lp.mu, self._GGt)

    # -- one control step in three parts (a flight computer's critical path is state in -> setpoint out):
    #    prepare(k) what does not depend on the observation, act(obs) the action, finish() the learning that
    #    only the next step uses. step(obs) = act(obs) + finish(); the parts give bit-identical results.
    def prepare(self, step: int) -> None:
        """Step ``step``'s observation-free part: the plan caught up to it, its action, centroid
        and centroid rate (cached; act() calls it if the caller did not). A real-time loop
        calls it at the tick, before it waits for the position."""
        if self.plan is None:
            raise RuntimeError("DefaultMFGController.prepare before exchange_t0(): the t = 0 exchange has not happened")
        if self._pending is not None:
            raise RuntimeError("DefaultMFGController.prepare: the previous act() was not finished (finish())")
        while self.plan.k < step:                              # a late start catches the plan up
            self.plan.advance()
        if self._prepared is None or self._prepared[0] != self.plan.k:
            p, tp = self.preset, self.preset.tracking
            a_plan_all = self.plan.action()
            x = self.plan.states
            rate = nominal_drift(x, a_plan_all, p.cost).mean(axis=0) if tp.learn_hjb and tp.learn_fpk else None  # d s_bar / dt
            self._prepared = (self.plan.k, a_plan_all, x.mean(axis=0), rate)

    def act(self, obs: Observation) -> StepInfo:
        """The action for ``obs`` (Algorithm 4's HJB update at the own state, eq. 8, the backstop);
        the last FPK update and the plan's advance wait for finish()."""
        self.prepare(obs.step)
        self._distinct_memo = None
        p, tp = self.preset, self.preset.tracking
        _, a_plan_all, centroid, rate = self._prepared
        own = np.asarray(obs.own_states, dtype=float)
        s_plan = self.plan.states[self.own_index]
        a_plan = a_plan_all[self.own_index]
        self._detour_state = det = self._detour(own, obs)
        if det is not None:
            # the own particle deflected around a lost vehicle with every lane near it (guidance/detour.py)
            rows = np.flatnonzero(det[0])
            ds, da = detour_offset(s_plan[rows], a_plan[rows], det[1][rows], det[2][rows], det[3], p.detour, p.dt_s,
                                   det[4][rows])
            s_plan[rows] += ds
            a_plan[rows] += da
        self._ref_pos = (self.plan.k, s_plan[:, 0:2].copy())
        e = own - s_plan
        self._own_err = e
        e = self._leash(e)
        n = self.n
        grad_evals = np.zeros(n, dtype=np.int64)
        mf_evals = np.full(n, self.plan.N, dtype=np.int64)      # plan particles advanced per UAV
        reg = np.zeros(n, dtype=bool)
        H_hat = np.zeros(n)
        grad_psi = None                                         # grad psi(e) with the current w_H
        fpk_args = None
        if tp.learn_hjb:
            for it in range(p.learner.K):
                phi_g, npairs = self._phi_G(own, centroid)
                mf_evals += npairs // max(n, 1)
                # hjb_update also returns grad psi and psi_vxvx + psi_vyvy at e with the new w_H
                self.w_H, H_hat, active, (grad_psi, hv_tr) = hjb_update(self.sigma_H, self.w_H, e, phi_g, self.track_preset)
                grad_evals += 1 + active
                reg |= active
                if tp.learn_fpk:
                    grad_evals += 1
                    if it < p.learner.K - 1:                    # the next iteration's phi_G reads w_F
                        self._fpk_update(own, a_plan + optimal_action(grad_psi, p.cost.c3), centroid, rate, hv_tr)
                    else:                                       # only the next step reads it: finish()
                        fpk_args = (own, a_plan, grad_psi, centroid, rate, hv_tr)
        if grad_psi is None:
            grad_psi = self.sigma_H.grad_psi(e, self.w_H)
        a_fb = optimal_action(grad_psi, p.cost.c3)      # eq. 8: -(1/2c3) B^T grad psi
        if not tp.feedback:
            a_fb = np.zeros_like(a_fb)
        a_nom = a_plan + a_fb
        if tp.feedback and tp.relative_priority:
            a_nom = self._relative_priority(a_plan, a_nom, obs)
        self._own_dist = self._observe_disturbance(own, obs.step)
        a = self._backstop(own, a_nom, obs)
        a = self._reject_disturbance(own, a, obs.step)
        self._own_a_prev = (obs.step, np.array(a, dtype=float))     # the braking test's common mode, next step
        self._pending = fpk_args or ()
        return StepInfo(a, grad_evals, reg, H_hat, mf_evals)

    def _observe_disturbance(self, own: np.ndarray, step: int) -> np.ndarray | None:
        """Each row's own disturbance estimate d_hat (n, 2) at this step (guidance/disturbance.py: the velocity change
        since the last step that the command sent then and eq. 9's drag do not explain, smoothed with
        TrackingParams.disturbance_smoothing), or None without the previous step's sample (a gap in the steps starts
        the observer again). Read by the feedforward (_reject_disturbance) and the backstop
        (BackstopParams.own_disturbance); the state is kept by _reject_disturbance, after the command is known."""
        if self._dob is None or self._dob[0] != step - 1:
            return None
        p = self.preset
        _, v0, a0, d0 = self._dob
        resid = disturbance_residual_m_s2(own[:, 2:4], v0, a0, p.dt_s, p.cost.c0_per_s, p.cost.v_o)
        lam = p.tracking.disturbance_smoothing
        return lam * d0 + (1.0 - lam) * resid

    def _reject_disturbance(self, own: np.ndarray, a: np.ndarray, step: int) -> np.ndarray:
        """The command sent for the acceleration ``a`` (n, 2) the rows chose: a less each row's observed disturbance
        beyond the deadband (self._own_dist, _observe_disturbance; TrackingParams.disturbance_feedforward), capped at
        acc_max. The observer's state (the step, the own velocities, the commands sent, the estimate) is kept for the
        next step."""
        tp, p = self.preset.tracking, self.preset
        d_hat = np.zeros((self.n, 2)) if self._own_dist is None else self._own_dist
        cmd = a
        if tp.disturbance_feedforward:
            cmd = cap_norm(a - shrink_m_s2(d_hat, tp.disturbance_deadband_m_s2), p.learner.acc_max_m_s2)
        self._dob = (step, np.array(own[:, 2:4], dtype=float), np.array(cmd, dtype=float), d_hat)
        return cmd

    def finish(self) -> None:
        """The rest of the step act() began: the FPK model's update at the own state (read from
        the next step on) and the plan's advance to the next step. No-op without a pending act()."""
        if self._pending is None:
            return
        fpk_args, self._pending = self._pending, None
        if fpk_args:
            own, a_plan, grad_psi, centroid, rate, hv_tr = fpk_args
            self._fpk_update(own, a_plan + optimal_action(grad_psi, self.preset.cost.c3), centroid, rate, hv_tr)
        self.plan.advance()

    def step(self, obs: Observation) -> StepInfo:
        info = self.act(obs)
        self.finish()
        return info

    def weights(self) -> dict[str, np.ndarray]:
        """Read-only views (no copy: the simulator reads row 0 every step; at N = 10,000 copying both
        banks cost ~10 MB per step). Valid snapshots: this class replaces w_H and w_F, never writes into them."""
        out = {"w_H": self.w_H.view(), "w_F": self.w_F.view()}
        for v in out.values():
            v.flags.writeable = False
        return out


class DefaultHJBController(_DefaultBase):
    """HJB_d with slots, closest-approach repulsion against the neighbours heard each step,
    priority saturation and the backstop. No swarm-wide exchange."""

    mode = "hjb"
    uses_t0_exchange = False
    ignores_sensed_if_heard = True
    """The backstop acts only on sensed vehicles that were not also heard this step (``_not_heard``): a
    simulator whose radio range covers the sensor range may leave Observation.sensed empty (every sensed
    vehicle is heard; the action is the same, tests/test_scaling.py)."""

    def __init__(self, preset: Preset, destination_site_m: np.ndarray) -> None:
        super().__init__(preset, destination_site_m)
        self._radius = np.full(self.n, self.preset.hjb_repulsion.radius_m)
        self._slots_known = False

    def _init_slots(self, own: np.ndarray, heard: HeardSummary) -> None:
        """Slot = site + own offset from the centroid of {own, heard at the first step};
        repulsion radius from the nearest heard neighbour (slot spacing)."""
        n, rp = self.n, self.preset.hjb_repulsion
        cnt = 1.0 + heard.count
        cen = np.stack([own[:, d] + heard.pos_sum_m[:, d] for d in range(2)], axis=1) / cnt[:, None]
        if self.preset.use_slots:
            self._dest = self.destination_site_m + own[:, 0:2] - cen
        self._radius = np.minimum(rp.radius_m, rp.slot_fraction * heard.nearest_m)
        self._slots_known = True

    @property
    def needs_heard_summary(self) -> bool:
        """The first step derives slots and radii from everything heard (interface.HeardSummary)."""
        return not self._slots_known

    def heard_cutoff_m(self, step: int, states: np.ndarray) -> tuple[float, np.ndarray, float]:
        """The reach (base_m, extra_m (N,), horizon_s) of heard states (interface.Controller): a heard j can
        change row i's action only if its predicted closest approach over the horizon, min over
        0 <= tau <= horizon of |d + tau u| (d = r_j - r_i, u = v_j - v_i), is below R (planner._pair_force:
        the push is exactly zero for rho >= R, and its rho is |d + tau u| at one tau in [0, horizon]); that
        implies |d| <= R + horizon |u| <= base + extra_i + extra_j, as |u| <= |v_i - c| + |v_j - c| (c: the
        median velocity). base = max R + 1 um against rounding. The backstop's exclusion of heard vehicles
        needs the sensed ones too: the caller adds them."""
        p, rp = self.preset, self.preset.hjb_repulsion
        if not p.use_repulsion or states.shape[0] == 0:
            return 0.0, np.zeros(states.shape[0]), 0.0
        v = states[:, 2:4]
        c = np.median(v, axis=0)
        rad = float(np.max(self._radius)) if self._slots_known else rp.radius_m
        hor = rp.horizon_s
        if rp.heard_guard_fraction > 0.0:
            # the guard on heard vehicles (step) acts below heard_guard_fraction x R within the backstop's horizon
            rad, hor = rad * max(1.0, rp.heard_guard_fraction), max(hor, p.backstop.horizon_s)
        return rad + 1e-6, hor * np.linalg.norm(v - c[None, :], axis=1), hor

    def exchange_t0(self, states, ids, own_index, sites_m) -> None:
        """Not used: HJB_d hears its neighbours at every step instead."""

    def step(self, obs: Observation) -> StepInfo:
        p = self.preset
        own = np.asarray(obs.own_states, dtype=float)
        heard = obs.neighbours if obs.neighbours is not None else Neighbours.empty()
        if not self._slots_known:
            self._init_slots(own, obs.heard_summary if obs.heard_summary is not None else HeardSummary.of(own, heard, self.n))
        s_rel = own - np.concatenate([self._dest, np.zeros_like(self._dest)], axis=1)
        a_goal = goal_acc(s_rel, p.guidance, p.cost)
        a_rep = (repulsion_from_neighbours(own, heard.states, heard.owner, self._radius, p.hjb_repulsion)
                 if p.use_repulsion else np.zeros_like(a_goal))
        a_nom = combine_priority(a_rep, a_goal, p.hjb_repulsion.a_plan_max_m_s2)
        g = p.hjb_repulsion.heard_guard_fraction
        if g > 0.0 and p.use_repulsion and heard.states.shape[0] > 0:
            # the guard on heard vehicles (not from the paper): the repulsion sums the pushes of every heard
            # neighbour, and the pushes of interleaving rows can outweigh the one of a pair about to collide
            # (crossing N = 50 seed 2: UAVs 8 and 44, heard every step, passed 0.046 m apart); the backstop's
            # half-plane constraint on each critical approach keeps it whatever the other pushes are
            # trigger = target = heard_guard_fraction x the own repulsion radius (heard_cutoff_m covers its reach)
            gm = g * self._radius[heard.owner]
            bp = replace(p.backstop, trigger_m=gm, target_m=gm)
            a_nom, _ = apply_backstop(a_nom, backstop_acc(own, heard.states, heard.owner, bp), p.learner.acc_max_m_s2)
        a = self._backstop(own, a_nom, obs)
        z = np.zeros(self.n, dtype=np.int64)
        return StepInfo(a, z, np.zeros(self.n, dtype=bool), np.zeros(self.n), z)

    def weights(self) -> dict[str, np.ndarray]:
        return {"w_H": np.zeros((self.n, 54))}


