"""Parameters of the safety layer (the proximity backstop), declared once with units.

Reasons and measured effects: ``docs/default_controller.md`` (section "Backstop"); the ``orca`` baseline:
``docs/benchmarks.md`` ("ORCA baseline").
"""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["BackstopParams", "OrcaParams"]


@dataclass(frozen=True)
class BackstopParams:
    """Communication-free proximity backstop (onboard sensor of short range)."""

    enabled: bool = True
    sensor_range_m: float = 10.0
    horizon_s: float = 2.0
    u_noise_m_s: float = 0.5        # relative speeds below this (wind jitter at hover) are not extrapolated
    trigger_m: float = 0.15         # act only if the predicted closest approach is below this (< dense plan clearance)
    target_m: float = 0.15          # ... and then push for this clearance
    share: float = 0.5              # own share of the correction (the other vehicle is assumed to take the rest)
    planned_max_own_dev_m: float = 0.1     # MFG: the response above only while the own UAV is this close to its plan particle (tracking error ~4 cm rms)
    # MFG only: a sensed vehicle farther than this from every plan particle is not flying the
    # plan (failed, gust-blown, unknown) and gets the 'unplanned' response below
    plan_mismatch_m: float = 0.5
    plan_mismatch_s: float = 0.5    # velocity weight of that distance (a hovering vehicle in a moving plan stands out)
    # MFG only: ... and a sensed vehicle farther than this from its own particle (by its id; a failed vehicle the stream
    # has left) is unplanned too, even where some particle passes through it; 0 turns it off
    plan_lost_m: float = 10.0
    # MFG only: a sensed vehicle that brakes (its sensed velocity change since the previous control step, along its
    # velocity) harder than its own plan particle by more than this - and by more than the common mode below (a head
    # wind brakes the observer too) - is also unplanned if one more period of it takes it beyond plan_mismatch_m
    # (seen before its state alone leaves the plan); only for rows that sense no vehicle off the plan already (UAVs
    # escaping a failed one brake and swerve too); 0 turns the test off. docs/default_controller.md, "The backstop"
    plan_mismatch_brake_m_s2: float = 0.6
    # ... relative to the observer's own "disturbance" (its velocity change that the plan and its own command do not
    # explain: the wind) or, as before the fifteenth session, its own "deviation" from its particle (which hid a Hold
    # the observer followed by command)
    plan_mismatch_brake_common: str = "disturbance"
    # ... and (plan_mismatch_brake_expected) beyond what the vehicle's own tracking explains: the command eq. 8 makes of
    # its deviation from its particle at the previous sample (estimated from the sensed states; the observer's value
    # model stands in for its own), with and without the common mode above. Eq. 8's held loop is nearly deadbeat at
    # the 0.5 s period, so a UAV faster than its particle brakes back by command a period later: in calm cruise a UAV's
    # along-track acceleration spreads 0.32 m/s^2 rms (its command 0.30, the wind 0.14), and without this 0.9 m/s^2 was
    # under 3 of them (circle N = 1,000 seed 83, calm: 60 vehicles flagged, 83 interventions; 0 and 0 with it). The
    # threshold, 0.6: PX4's Hold brakes >= 1.0 m/s^2 on average over any control period that ends >= 0.5 s after it
    # began (its ramp: 4 m/s^3 to 2 m/s^2), so a Hold is flagged at the first sample at which it is 0.5-1.0 s old
    # unless the command it replaced braked >= 0.4 m/s^2 itself (then a period later): behind it the UAV 1.41 m back
    # can keep 0.194 m (mfg_swarm.limits). 0.9 without the tracking (fifteenth session), 1.75 before (a Hold 0.6 s old
    # went unflagged: 0.08-0.12 m). docs/default_controller.md, "The braking test subtracts the neighbour's own tracking"
    plan_mismatch_brake_expected: bool = True
    own_slot_claim: bool = True     # MFG: a sensed vehicle within min(plan_mismatch_m, spacing / 2) of the own particle is unplanned ...
    own_slot_claim_max_speed_m_s: float = 0.5   # ... while that particle is this slow (parked: before its start, after its arrival)
    planned_response_rigid: bool = False   # MFG: also the response to planned vehicles when the plan is rigid (conflict-free by construction)
    unplanned_trigger_m: float = 0.6   # used: min(this, 0.5 * smallest slot spacing)
    unplanned_target_m: float = 0.8    # used: min(this, 0.6 * smallest slot spacing)
    # MFG: ... but an unplanned vehicle moving with the plan's flow (velocity within unplanned_flow_m_s of the nearest
    # particle's, that particle faster than unplanned_flow_min_m_s: blown off its particle in cruise) gets these
    # (at most the two above); 0 turns it off. docs/default_controller.md, "The escape's reach follows the flow"
    unplanned_flow_m_s: float = 2.0
    unplanned_flow_min_m_s: float = 2.0
    unplanned_flow_trigger_m: float = 0.25
    unplanned_flow_target_m: float = 0.5
    unplanned_share: float = 1.0
    # MFG: the crowd fallback's half-plane push (escape_max_unplanned_fraction below) takes the flow reach per vehicle
    # too (False: unplanned_trigger_m / unplanned_target_m for all). docs/default_controller.md, "The crowded push takes
    # the flow reach too"
    push_flow_reach: bool = True
    common_mode: bool = True           # MFG: a vehicle off the plan by the own deviation (a shared gust) is not unplanned
    common_mode_min_own_dev_m: float = 0.2   # ... checked only for rows this far off their own particle (same metric)
    # ... but a vehicle the braking test flagged (its braking beyond the observer's own disturbance: the common mode
    # already taken off) stays unplanned: re-checked by position only it was cleared, in a gust, in the 0.5 s it had to
    # be passed in (circle --gust with a failure, N = 100 seed 81: UAV 9 behind the failed 10, flagged at 0.85 s and
    # cleared; thirtieth session)
    common_mode_keeps_braking: bool = True
    # MFG: the escape manoeuvre against unplanned vehicles (backstop.escape_acc) instead of the
    # single half-plane push; it keeps clear of every sensed vehicle while avoiding the threat
    escape: bool = True
    escape_sample_s: float = 0.1       # prediction sampling over horizon_s
    escape_directions: int = 16        # candidate directions (at a_max / 2 and a_max), plus a_nom and 0
    escape_planned_clear_m: float = 0.5    # clearance kept from planned vehicles: min(this, escape_planned_fraction * spacing)
    escape_planned_fraction: float = 0.4
    escape_threat_weight: float = 1.0      # weight of a conflict with a threat in the escape cost
    escape_planned_weight: float = 1.0     # ... and with a planned vehicle
    escape_effort: float = 1.0         # weight of |a - a_nom|^2 / a_max^2 (minimal intervention)
    escape_lateral_cost: float = 1.5   # lateral (to the own velocity) deviations cost this x more than along-track (1.0 before: docs/default_controller.md, "Failed vehicle in a stream")
    escape_d_floor_m: float = 0.05     # the conflict cost (clear / max(d, this) - 1)^2 grows steeply as d -> 0
    escape_urgency: bool = True        # weight a conflict by tau_min / max(t of closest approach, tau_min)
    # safety first (nineteenth session): a candidate with a second phase that keeps every sensed entry at least this x
    # its clearance away beats every candidate that has none, whatever their cost; if no candidate has one, the cost
    # alone decides, as with 0 = off (backstop.escape_acc). Measured: circle N = 10,000 --gust seed 74, a UAV took a
    # predicted 0.24 m approach at the horizon's end for 1.4 less effort and collided (docs/default_controller.md)
    escape_hard_fraction: float = 0.5
    escape_keep_right: float = 2.0     # cost of a full-authority escape to the left of a conflicting approach (both turn right)
    # MFG, against a vehicle off the plan that hovers (slower than hover_max_speed_m_s: failed in Hold, drifting in the
    # wind), four rules that hold only together, and two more measured and off (docs/default_controller.md, "Where it
    # does not hold yet", tenth and eleventh sessions):
    # - the lane side: a row escaping it passes it on the side its own particle's lane lies on (from the plan, which
    #   every UAV shares, so the lanes split around it the same way for all): a candidate across the track towards the
    #   other side costs escape_side_commit x its lateral share of a_max (UAVs coming up to it nearly head-on swerved to
    #   alternate sides on consecutive steps and passed it at 0.09 m);
    # - escape_side_memory: the side chosen at a row's first meeting with that vehicle is kept while it is the row's
    #   nearest hovering one (the vehicle drifts; a lane 5 cm off it would otherwise swap sides under it);
    # - unplanned_hover_clear_now: the clearance from it is min(unplanned_target_m, 0.6 x the plan's spacing *now*),
    #   not the slot-sized 0.3 m of the 0.5 m pad (the pad flies 1.1-1.4 m apart in cruise);
    # - escape_trigger_coast: a row is also active if *coasting* (a = 0 over the horizon) brings it below its trigger,
    #   not only its nominal command held (a momentary tracking correction held for 2 s predicted a 0.5 m miss of a
    #   vehicle the UAV then passed at 0.09 m; the escape acted 1 s before the pass). Only against a hovering vehicle:
    #   for every unplanned one, the unspread pad in a gust (a UAV fights the gust, coasting drifts) went 1 -> 4 pairs.
    # - unplanned_hover_trigger_now (off): its trigger too, min(unplanned_trigger_m, 0.5 x the spacing now): with the
    #   slot-sized 0.25 m trigger under a 0.8 m clearance the escape opened the predicted pass to 0.3 m at one step,
    #   was off at the next, and the tracking took the UAV back into its lane, through the failed vehicle;
    # - escape_side_over_keep_right (off): in a row with a lane side, the keep-right term does not count against a
    #   hovering vehicle (keep-right makes two *escaping* vehicles pick opposite sides; a hovering one does not escape,
    #   and its 2.0 outweighed the lane side's 1.0: a UAV whose lane side was left swerved right).
    #   The two together kept half the 0.5 m dense spacing past the failed vehicle at N = 3,000 (4 seeds, was 1 of 4)
    #   and raised it at 5,000, but N = 10,000 seed 8 went from 0 to 2 collided pairs (three UAVs escaping it next to
    #   their slots; either rule alone: 1 pair there): off until that is understood (eleventh session, docs).
    escape_side_commit: float = 1.0
    escape_side_memory: bool = True
    hover_max_speed_m_s: float = 1.0
    # MFG: ... and a vehicle that counted as hovering off the plan within the last hover_latch_s (by its id) still counts
    # while it stays off the plan and slower than hover_latch_max_speed_m_s (each such step renews it; 0 s: off). A
    # vehicle failed into Hold fights a gust with its position loop's integrator and, when the gust ends, flies back
    # towards its Hold point at up to 1-3 m/s (PX4's Hold over 133 failure-inside-a-gust runs: 90th percentile 1.8 m/s,
    # largest 3.13): past hover_max_speed_m_s it lost the hover rules mid-encounter (swap4 --gust N = 1,000 s78: UAV 17's
    # crowded row stopped escaping it and met it at 0.093 m; twenty-fifth session, docs/default_controller.md)
    # ... unless it flies towards its own plan particle (the cosine between its velocity and the direction to its
    # particle is hover_latch_max_towards_plan or more): a healthy UAV the gust pinned, recovering its plan
    hover_latch_s: float = 5.0
    hover_latch_max_speed_m_s: float = 3.0
    hover_latch_max_towards_plan: float = 0.5
    unplanned_hover_clear_now: bool = True
    unplanned_hover_trigger_now: bool = False
    escape_side_over_keep_right: bool = False
    escape_trigger_coast: bool = True
    escape_max_unplanned_fraction: float = 0.5   # a row sensing a larger share of off-plan vehicles gets the half-plane push
    escape_gap: bool = False          # also escape below the planned trigger from vehicles neither response covers (measured on one case only, slow: off)
    # MFG: a UAV off its own particle by more than escape_yield_min_dev_m yields to a sensed vehicle that neither
    # response covers and that flies its own particle (by id, within escape_yield_on_plan_m): it escapes (trigger /
    # clearance below), the other keeps tracking, as the escape's prediction assumes. docs/default_controller.md,
    # "A UAV off its particle yields to one on it"
    escape_yield: bool = True
    escape_yield_min_dev_m: float = 0.5
    escape_yield_on_plan_m: float = 0.3
    escape_yield_min_spacing_m: float = 1.0   # only where the plan's particles are this far apart now (room to pass)
    escape_yield_trigger_m: float = 0.25   # used: min(this, 0.5 * smallest slot spacing)
    escape_yield_clear_m: float = 0.5      # used: min(this, 0.6 * smallest slot spacing)
    # MFG: sensed vehicles that no other response covers (the gap: both off their particles, each near some particle or
    # cleared as common mode) get a reciprocal half-plane push when predicted (over gap_push_horizon_s) closer than
    # gap_push_trigger_fraction x the plan's spacing now, for gap_push_target_fraction x it; only while that spacing
    # is at least gap_push_min_spacing_m, or (gap_push_near_lost) for a row that senses a vehicle lost to the plan
    # (plan_lost_m: a failed one; the escapes around it open gaps in the closing pad). docs/default_controller.md,
    # "The gap push"
    gap_push: bool = True
    gap_push_trigger_fraction: float = 0.35
    gap_push_target_fraction: float = 0.45
    gap_push_share: float = 0.5
    gap_push_horizon_s: float = 1.0
    gap_push_min_spacing_m: float = 1.0
    gap_push_near_lost: bool = True
    escape_two_phase: bool = True      # candidate held for one control period, then the best of {a_nom, 0, -a_1, a_1}
    # MFG: a crowded row (escape_max_unplanned_fraction: most of what it senses is off the plan, a gust has blown the
    # swarm about) gets the reciprocal control-barrier filter of backstop.cbf_acc over every sensed vehicle instead of
    # the summed half-plane push (which left a crowd of UAVs chasing their particles to cross each other: crossing
    # --gust N = 137, 3 of 30 seeds collided). Barrier of Wang, Ames, Egerstedt (2017) with each vehicle's braking
    # authority crowd_cbf_alpha_m_s2, decay crowd_cbf_gamma, safe distance crowd_cbf_safe_fraction x the plan's spacing,
    # each vehicle taking crowd_cbf_share of every constraint. docs/default_controller.md, "The crowd's barrier filter"
    crowd_cbf: bool = True
    crowd_cbf_alpha_m_s2: float = 1.0
    crowd_cbf_gamma: float = 1.0
    crowd_cbf_safe_fraction: float = 0.25
    crowd_cbf_share: float = 0.5
    crowd_cbf_hover_full_share: bool = True   # ... but all of it against a vehicle hovering in the plan's stream (_cbf_share)
    crowd_cbf_max_constraints: int = 16
    # ... and inside the safe distance (d <= D_s, where the barrier's root is 0 and h is undefined) a constraint never
    # lets the row accelerate towards that vehicle (B_ij clamped to >= 0): a pair inside D_s that opened for a moment
    # had B_ij ~ -2 alpha rdot / 0 (no constraint), the row's nominal command drove it back in, the next sample found it
    # closing and pushed out: in and out every period until they met (merge --gust N = 300 s86, UAV 38 and the failed
    # vehicle 0.3 m apart, 0.065 m; twenty-fifth session). Off: the former filter
    crowd_cbf_inside_no_approach: bool = True
    # ... and as the last layer of every other row that senses a vehicle off the plan (not hovering) and does not escape,
    # over its command, against every sensed vehicle but one hovering off the plan (guidance.controller._backstop_rows;
    # twenty-first session). Off: a failure inside a gust collided less (42 runs: 5 -> 3), but the 0.5 m grid without
    # the cruise spread in a gust collided more (dense N = 144 seed 2: 1 -> 6 pairs; docs/benchmarks.md, twenty-first round)
    cbf_last_layer: bool = False
    # MFG: a crowded row (escape_max_unplanned_fraction) still escapes from a vehicle hovering off the plan where the plan
    # flies (hover_max_speed_m_s, unplanned_flow_min_m_s: failed into Hold in the stream), and then takes no crowd filter:
    # the filter brakes along each line of sight among many constraints, and three UAVs whose rows a gust had crowded met
    # the failed vehicle so (paper N = 300 s76, N = 1,000 s78, circle N = 300 s77; docs/benchmarks.md, twenty-second round).
    # Only where braking cannot do it (twenty-third session): the row flies faster than
    # escape_hover_in_crowd_min_speed_m_s and (escape_hover_in_crowd_brake_gate) closes on the vehicle faster than it can
    # stop short of the escape's clearance braking at a_max after one control period (backstop.cannot_brake_short). Without
    # the gates a UAV still slow at its group's departure, blown behind its particle, is 'hovering in the stream' too, and
    # its crowded neighbours swerved into each other (crossing --gust N = 137 seed 117, no failure: 0.114 m; 0.304 with them)
    escape_hover_in_crowd: bool = True
    escape_hover_in_crowd_min_speed_m_s: float = 2.0
    escape_hover_in_crowd_brake_gate: bool = True
    # MFG: which off-plan vehicles the escape also predicts braking to a stop at a_max (besides constant velocity).
    # "measured" (twenty-fourth session): those that hover (hover_max_speed_m_s), or that braked by more than
    # escape_brake_hypothesis_min_m_s2 along their velocity since the previous sample beyond the observing row's own
    # disturbance (the common mode: a gust brakes the observer as it brakes its neighbours), or that have no previous
    # sample; "threat": every one, as before. In a gust half the vehicles a row senses are off the plan: predicted to
    # stop dead ahead of it they made rows swerve from stops nobody made into neighbours that swerved as well (paper
    # --gust with a failure, N = 300 seed 87: UAVs 86 / 87, 0.044 m; docs/default_controller.md, "The braking hypothesis
    # is measured"). HJB_d keeps no velocity history: every threat, as with "threat".
    escape_brake_hypothesis: str = "measured"
    escape_brake_hypothesis_min_m_s2: float = 0.5
    # MFG: an off-plan vehicle measured braking (along its velocity since the previous sample, beyond the common mode,
    # by more than escape_brake_hypothesis_min_m_s2) is taken as the hovering one it is about to be: the unplanned
    # response's full reach (not the flow's, unplanned_flow_*), the hovering clearance, the lane side (at its braking
    # stop point, where PX4's Hold will hold it), the side memory and the coast trigger. A failed vehicle takes 1-2 s of
    # PX4's jerk-limited Hold to get below hover_max_speed_m_s; in that time the UAVs behind it took it for a gust-blown
    # neighbour (0.25 m trigger) and chose a side at one step and the other at the next, and with PX4's lag each
    # reversal came 0.15 s later (thirtieth session, the 133 failure-inside-a-gust runs: docs/default_controller.md)
    escape_braking_as_hover: bool = True
    # MFG: the UAV behind is the one responsible (as a driver is for the car ahead). A row does not wake its
    # escape for a vehicle behind it (its position relative to the row's along the row's own velocity is negative) unless
    # that vehicle hovers or brakes into its Hold (hover_max_speed_m_s, escape_braking_as_hover: a failed vehicle takes no
    # responsibility), or would come within the escape's clearance inside one control period at the speed it closes
    # (imminent: the one behind may be crowded, its barrier filter taking only its reciprocal half - swap4 --gust with a
    # failure on the paper's plant, N = 1,000 s78, the PD Hold: UAVs 20 / 52, 0.148 -> 0.097 m without this exception);
    # such a vehicle still weighs in the candidates of a row that escapes something else, as a planned neighbour does.
    # A closing pair always keeps one responsible UAV: if each had the other behind, r.v_i < 0 and -r.v_j < 0 with
    # r = p_j - p_i, then r.(v_j - v_i) > 0 and they separate. After a gust two healthy UAVs escaping each other at once
    # swerved into each other, each predicting the other flying straight on (circle --gust with a failure, N = 2,000
    # s231: UAVs 248 / 252, 0.064 m; 0.139 m with the rule; thirty-fifth session, docs/benchmarks.md). HJB_d does not
    # apply it (its escape is flown as it was measured)
    escape_rear_responsible: bool = True
    # MFG, off by default (an option: measured, it mends five collided runs of the failure sets and breaks three others,
    # one of them held out - docs/benchmarks.md, thirty-sixth round): a tube around the failed vehicle's predicted
    # tracks. The escape predicts a vehicle failing into Hold at
    # constant velocity and braking at a_max; neither is what it flies (PX4's jerk-limited Hold, its own gust, the
    # fly-back to its Hold point), and at the edge of its safe set the prediction is what failed (thirty-third to
    # thirty-fifth rounds). So its position t seconds ahead is taken as uncertain by escape_tube_m_s2 t^2 / 2 (an unknown
    # acceleration bound), and the escape asks that much more than the clearance, in its trigger and its choice, up to
    # escape_tube_spacing_fraction x the plan's spacing now (the room between the lanes: uncapped, the rows of the
    # 0.5 m pad closing past a failed vehicle swerved into each other, dense --gust with a failure, N = 2,000 s202: 53
    # pairs). Only for a hovering / braking threat where the plan flies (_in_stream) that still moves faster than
    # escape_tube_min_speed_m_s: PX4 holds a vehicle at rest at its Hold point (the tube on one at rest swung UAV 5 from
    # one side to the other, circle N = 100 s81: 0.237 -> 0.047 m); and only while the plan's spacing now is at least
    # escape_tube_min_spacing_m (a tighter formation has no room for it: the 0.5 m dense grid in a gust without its
    # cruise spread went 1 -> 26 collided pairs with a 0.125 m tube). 0: off; measured with 1.0 (the failed vehicle's
    # own gust, ~1 m/s^2 here). HJB_d: never (no plan to be in the stream of). docs/default_controller.md, "A tube
    # around the failed vehicle's tracks"
    escape_tube_m_s2: float = 0.0
    escape_tube_spacing_fraction: float = 0.25
    escape_tube_min_speed_m_s: float = 0.5
    escape_tube_min_spacing_m: float = 1.0
    # MFG: the escape's predictions and the barrier filter's constraints carry the own vehicle's disturbance (the
    # acceleration it flies beyond its command, from its own telemetry: guidance/disturbance.py, the observer of
    # TrackingParams.disturbance_smoothing) beyond own_disturbance_deadband_m_s2: a gust across the line of sight ate
    # the escape's swerve (swap4 --gust with a failure, N = 1,000 seed 78: 1.79 m/s^2 chosen, 1.38 against it)
    own_disturbance: bool = True
    own_disturbance_deadband_m_s2: float = 0.3
    tau_min_s: float = 0.5
    a_max_m_s2: float = 2.0

    def __post_init__(self) -> None:
        if self.escape_brake_hypothesis not in ("threat", "measured"):
            raise ValueError("BackstopParams.escape_brake_hypothesis must be 'threat' or 'measured', got "
                             f"{self.escape_brake_hypothesis!r}")
        if self.plan_mismatch_brake_common not in ("disturbance", "deviation"):
            raise ValueError("BackstopParams.plan_mismatch_brake_common must be 'disturbance' or 'deviation', got "
                             f"{self.plan_mismatch_brake_common!r}")
        for name, ok, what in (("crowd_cbf_alpha_m_s2", self.crowd_cbf_alpha_m_s2 > 0, "> 0"),
                               ("crowd_cbf_gamma", self.crowd_cbf_gamma >= 0, ">= 0"),
                               ("crowd_cbf_safe_fraction", 0 <= self.crowd_cbf_safe_fraction < 1, "in [0, 1)"),
                               ("crowd_cbf_share", 0 < self.crowd_cbf_share <= 1, "in (0, 1]"),
                               ("escape_tube_m_s2", self.escape_tube_m_s2 >= 0, ">= 0"),
                               ("escape_tube_spacing_fraction", self.escape_tube_spacing_fraction >= 0, ">= 0"),
                               ("escape_tube_min_speed_m_s", self.escape_tube_min_speed_m_s >= 0, ">= 0"),
                               ("escape_tube_min_spacing_m", self.escape_tube_min_spacing_m >= 0, ">= 0"),
                               ("crowd_cbf_max_constraints", self.crowd_cbf_max_constraints >= 1, ">= 1"),
                               ("own_disturbance_deadband_m_s2", self.own_disturbance_deadband_m_s2 >= 0, ">= 0"),
                               ("escape_hover_in_crowd_min_speed_m_s", self.escape_hover_in_crowd_min_speed_m_s >= 0,
                                ">= 0"),
                               ("escape_brake_hypothesis_min_m_s2", self.escape_brake_hypothesis_min_m_s2 >= 0, ">= 0"),
                               ("hover_latch_s", self.hover_latch_s >= 0, ">= 0"),
                               ("hover_latch_max_speed_m_s", self.hover_latch_max_speed_m_s >= 0, ">= 0"),
                               ("hover_latch_max_towards_plan", -1 <= self.hover_latch_max_towards_plan <= 1,
                                "in [-1, 1]")):
            if not ok:
                raise ValueError(f"BackstopParams.{name} must be {what}, got {getattr(self, name)!r}")


@dataclass(frozen=True)
class OrcaParams:
    """The ``orca`` baseline (:mod:`mfg_autopilot.safety.orca`): optimal reciprocal collision
    avoidance (van den Berg, Guy, Lin and Manocha 2011) over what the proximity sensor sees.

    In ORCA's model every vehicle is a disc of ``radius_m`` that can take any velocity up to
    ``max_speed_m_s`` at once; a pair is kept ``2 radius_m`` apart for ``time_horizon_s`` if both
    take half of the velocity change. Our vehicles are acceleration-limited (the preset's
    ``learner.acc_max_m_s2``), so the radius carries the margin for what a step cannot reach."""

    radius_m: float = 0.2               # ORCA's disc per vehicle (2 x 0.2 = 0.4 m < the dense start spacing 0.5 m)
    time_horizon_s: float = 5.0         # tau: velocities that collide within tau are excluded (2 s: 2-8x the collided pairs)
    neighbour_dist_m: float = 10.0      # neighbours farther than this are ignored (<= the sensor range)
    max_neighbours: int = 30            # only the nearest this many sensed vehicles get an ORCA half-plane (RVO2's
                                        # examples use 10: in converging streams the threats are not the 10 nearest)
    max_speed_m_s: float = 4.0          # the disc of admissible velocities (the default guidance's cruise speed)

    def __post_init__(self) -> None:
        for k in ("radius_m", "time_horizon_s", "neighbour_dist_m", "max_speed_m_s"):
            v = getattr(self, k)
            if not (isinstance(v, (int, float)) and v > 0 and v < float("inf")):
                raise ValueError(f"OrcaParams.{k} must be finite and > 0, got {v!r}")
        if not (isinstance(self.max_neighbours, int) and self.max_neighbours >= 1):
            raise ValueError(f"OrcaParams.max_neighbours must be an int >= 1, got {self.max_neighbours!r}")
