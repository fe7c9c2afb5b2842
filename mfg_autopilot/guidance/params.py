"""Parameters of the product controller (the ``default`` preset), declared once with units.

The paper's symbols keep their meaning (c0, c1, c2, c3, c4, v_o, V_o); what the paper does
not have (slots, the interacting mean-field plan, closest-approach repulsion, the tracking
value model, the proximity backstop) is named here with its unit and bounds. Reasons and
measured effects: ``docs/default_controller.md``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from mfg_autopilot.paper.params import CostParams, LearnerParams, Preset
from mfg_autopilot.safety.params import BackstopParams, OrcaParams

__all__ = ["GuidanceParams", "RepulsionParams", "TrackingParams", "DetourParams", "DefaultPreset", "DEFAULT"]


@dataclass(frozen=True)
class GuidanceParams:
    """Goal term: velocity command towards the slot, v_des = -r_hat * min(v_cruise,
    sqrt(2 a_brake |r|), k_r |r|), then a_goal = k_v (v_des - v) + c0 (v - v_o), capped."""

    v_cruise_m_s: float = 4.0
    a_brake_m_s2: float = 0.5
    k_r_per_s: float = 0.4
    k_v_per_s: float = 1.0
    a_goal_max_m_s2: float = 1.0    # the goal term is capped first (priority saturation)
    k_fp_per_s2: float = 1.0        # plan only: formation keeping (place in the group), position gain
    k_fd_per_s: float = 2.0         # plan only: formation keeping, velocity gain

    def __post_init__(self) -> None:
        for k, v in vars(self).items():
            if not v > 0:
                raise ValueError(f"{k} must be > 0, got {v}")


@dataclass(frozen=True)
class RepulsionParams:
    """Closest-approach barrier between pairs (plan particles or heard neighbours).

    For a pair with relative position d and velocity u, tau* = clip(-d.u/|u|^2, 0, horizon)
    and rho = |d + tau* u| is the predicted closest approach; if rho < radius the pair is
    pushed apart along d + tau* u (plus a 'keep right' tangential share) with
    min(gain, (R - rho) / max(tau*, tau_min)^2) each: half of the relative acceleration that
    would open the closest approach to R by tau*."""

    radius_m: float = 1.0           # upper bound; the used radius is min(radius_m, slot_fraction * min slot spacing)
    slot_fraction: float = 0.5       # 0.5: rows of crossing formations can interleave
    horizon_s: float = 3.0
    gain_m_s2: float = 1.0          # cap of one pair's push
    tau_min_s: float = 0.5          # urgency floor of the push
    urgency: float = 1.0            # 1: each member takes half of the needed relative acceleration
    form_yield_m_s2: float = 0.05   # plan: formation keeping weight 1 / (1 + |a_rep| / this)
    keep_right: float = 0.3         # tangential share (breaks symmetric head-on deadlocks)
    brake: float = 0.0              # share along -u (lowers the closing speed)
    a_rep_max_m_s2: float = 1.0
    a_plan_max_m_s2: float = 1.4    # plan / reactive command cap, below the vehicle limit
    heard_guard_fraction: float = 0.0   # HJB_d only (DefaultHJBController): a heard vehicle predicted closer than this x the
                                        # repulsion radius gets the backstop's half-plane constraint (trigger = target; 0: off)


@dataclass(frozen=True)
class TrackingParams:
    """The HJB value model used as a tracking controller of the own plan particle:
    psi(e) = w_H^T sigma_H(e), w_H(0) the Riccati value of the tracking cost
    c1_track |e_r|^2 + c2 |e_v|^2 + c3 |a|^2 (c2, c3 the paper's)."""

    c1_track: float = 24.0          # gives k_p = 4 s^-2, k_d = 2.9 s^-1: stable at dt = 0.5 s with margin
    e_pos_max_m: float = 0.5        # tracking error leash (the value model sees at most this)
    e_vel_max_m_s: float = 1.0
    feedback: bool = True           # False: fly the plan's feedforward only (ablation)
    learn_hjb: bool = True          # Algorithm 3/4's online NGD update of w_H on the tracking error
    learn_fpk: bool = True          # Algorithm 4's FPK model weights the phi_G quadrature
    phi_g_radius_m: float = 5.0     # plan particles within this range enter phi_G(s_i, m)
    # MFG, rows with formation neighbours: the feedback on the error relative to the local formation mean (what
    # the proximity sensor sees: each sensed neighbour's s_j - s_plan,j, by its id) has priority over the plan's
    # feedforward plus the feedback on that common mode, which gets at most common_acc_max_m_s2 (a gust beyond
    # the model blows neighbours nearly alike: the formation may drift with it and catch up later, but each UAV
    # fighting it alone to its own particle pushed rows into each other; docs/default_controller.md "Gusts")
    relative_priority: bool = True
    common_acc_max_m_s2: float = 1.2       # the common-mode share's cap (< acc_max: the rest is kept for the relative error)
    formation_radius_spacings: float = 3.0  # sensed neighbours whose plan particle is within this x the plan spacing
    formation_outlier_m: float = 1.0       # ... and whose deviation from the plan is within this of the own one
                                           # (|de_r|^2 + (plan_mismatch_s |de_v|)^2, the backstop's plan metric)
    # MFG: the own disturbance observer's feedforward (guidance/disturbance.py; not from the paper; off): the command
    # sent is the chosen acceleration less the acceleration eq. 9 does not explain in the own telemetry (smoothed; only
    # beyond a deadband above the modelled wind noise). Measured (docs/benchmarks.md, twenty-first round): it halves the
    # tracking error in a gust, but a UAV that a strong gust saturates drifts while its neighbours now hold their
    # particles, and --gust flights came closer (all seven families, N = 300, seeds 74-75: smallest 0.33 -> 0.20 m);
    # a failure inside a gust collided less often (5 -> 2 of 42 runs). Off until that trade is resolved
    disturbance_feedforward: bool = False
    disturbance_smoothing: float = 0.5      # lam: d_hat = lam d_hat + (1 - lam) residual
    disturbance_deadband_m_s2: float = 0.3  # ~3.7 x the smoothed residual's std per axis under V_o alone (0.08 m/s^2)
    # the telemetry-rate inner loop (guidance/inner_loop.py; not from the paper; on): between control steps the vehicle
    # tracks the trajectory the period's command promised, a = sat(a_k + k_p (r_ref - r) + k_d (v_ref - v)), at every
    # physics sub-step (simulator), LOCAL_POSITION_NED (autopilot, real time) or sub-step of a lockstep vehicle stepped by
    # its physics sub-step (docs/lockstep.md). For an airframe with an acceleration
    # lag (PlantParams.acc_lag_s; PX4 ~0.154 s), against which eq. 8's held gains ring, and for a gust inside the
    # period (docs/default_controller.md). Where a vehicle is stepped whole periods it is idle: the held flight
    inner_loop: bool = True
    inner_kp_per_s2: float = 4.0
    inner_kd_per_s: float = 4.0
    # the airframe's acceleration lag the controller's own-vehicle model assumes (the escape's prediction of its own
    # swerve: safety.backstop.OwnModel; not from the paper; 0: none, the command flown at once). A lagged airframe
    # with the inner loop swerves ~27 % less in the first period than a command flown at once. Measured with PX4's
    # lag on 133 gust + failure flights it moved the collided pairs, it did not remove them (10 -> 12; docs/benchmarks.md,
    # twenty-ninth round): off until the neighbours' prediction matches it (sim model_acc_lag_s, mfg-autopilot
    # --acc-lag-s)
    acc_lag_s: float = 0.0

    def __post_init__(self) -> None:
        for name in ("inner_kp_per_s2", "inner_kd_per_s"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and 0.0 <= v < float("inf")):
                raise ValueError(f"TrackingParams.{name} must be finite and >= 0, got {v!r}")
        if not 0.0 <= self.disturbance_smoothing < 1.0:
            raise ValueError(f"TrackingParams.disturbance_smoothing must be in [0, 1), got {self.disturbance_smoothing!r}")
        if not (isinstance(self.acc_lag_s, (int, float)) and 0.0 <= self.acc_lag_s <= 2.0):
            raise ValueError(f"TrackingParams.acc_lag_s must be in [0, 2] s (0: none), got {self.acc_lag_s!r}")
        if not self.disturbance_deadband_m_s2 >= 0.0:
            raise ValueError(f"TrackingParams.disturbance_deadband_m_s2 must be >= 0, got {self.disturbance_deadband_m_s2!r}")


@dataclass(frozen=True)
class DetourParams:
    """MFG: the plan deflected around a hovering vehicle lost to it (guidance/detour.py; not from the paper; issue 18).
    The support (|along| <= plateau_m + ramp_m, |across| <= width_m) must lie inside the backstop's sensor range."""

    enabled: bool = True
    clear_fraction: float = 0.6     # the lanes pass the vehicle at least this x the plan's spacing now ...
    clear_max_m: float = 0.85       # ... and at most this (c; lanes compress by 1 - c / width_m)
    width_m: float = 3.0            # lanes within this of the vehicle, across their track, are deflected
    plateau_m: float = 0.5          # along the track: fully deflected within this of the vehicle ...
    ramp_m: float = 8.0             # ... and a raised cosine over this much before and after (lateral acceleration
                                    # c (pi / ramp)^2 / 2 v^2: 1.05 m/s^2 at 4 m/s)
    onset_from_m: float = 3.0       # a hovering vehicle this far from its own particle is detoured around ...
    onset_m: float = 6.0            # ... fully once it is this much farther (a smoothstep between)
    min_speed_m_s: float = 0.5      # slower particles are faded out (no lane)
    side_from_escape: bool = True   # a row whose escape already passes that vehicle on a side (the escape's side memory,
                                    # BackstopParams.escape_side_memory) deflects its lane to that side: one decision

    def __post_init__(self) -> None:
        for k in ("clear_fraction", "clear_max_m", "width_m", "plateau_m", "ramp_m", "onset_from_m", "onset_m",
                  "min_speed_m_s"):
            if not getattr(self, k) > 0:
                raise ValueError(f"DetourParams.{k} must be > 0, got {getattr(self, k)}")
        if not self.clear_max_m < self.width_m:
            raise ValueError("DetourParams.clear_max_m must be < width_m (lanes would swap order)")


@dataclass(frozen=True)
class DefaultPreset(Preset):
    """The product preset: the paper's model and cost plus the pieces above."""

    name: str = "default"
    learner: LearnerParams = field(default_factory=lambda: LearnerParams(w_H_init="lqr", K=1, acc_max_m_s2=2.0,
                                                                           state_scale=(1.0, 1.0, 1.0, 1.0),
                                                                           fpk_scale=(10.0, 10.0, 2.0, 2.0)))
    dt_s: float = 0.5
    guidance: GuidanceParams = field(default_factory=GuidanceParams)
    repulsion: RepulsionParams = field(default_factory=RepulsionParams)
    hjb_repulsion: RepulsionParams = field(default_factory=lambda: RepulsionParams(heard_guard_fraction=0.5))   # HJB_d's reactive repulsion on heard states
    tracking: TrackingParams = field(default_factory=TrackingParams)
    backstop: BackstopParams = field(default_factory=BackstopParams)
    detour: DetourParams = field(default_factory=DetourParams)     # MFG: the plan deflected around a failed vehicle
    orca: OrcaParams = field(default_factory=OrcaParams)     # the ``orca`` mode's baseline (safety/orca.py), not used by mfg / hjb
    use_plan: bool = True           # MFG: track the interacting mean-field plan (False: own guidance + no plan)
    rigid_plan: bool = True         # MFG: when the target layout is an isometry of the start, the plan is that rigid
                                    # motion (guidance/rigid_plan.py: every distance kept by construction)
    group_plan: bool = True         # MFG: otherwise every group a rigid translation on a schedule checked in space-time at t = 0
                                    # (guidance/group_plan.py); if no schedule is found, the interacting plan
    group_plan_clearance_fraction: float = 0.75   # ... certified to keep other groups' particles this x the start/slot spacing apart
    rigid_translation: bool = True  # MFG: a single group's plan is its rigid translation to the site (False: the interacting plan)
    cruise_spacing_m: float = 2.1   # ... which spreads about its centroid in cruise until neighbours are this far apart, and
                                    # closes again before the site (a similarity: every distance only grows, then returns; 0: off);
                                    # the half turn spreads each group about its own centroid the same way where the groups
                                    # leave room (rigid_plan.py; 1.4 until the thirty-third session: room for the UAV behind
                                    # a failed vehicle, docs/default_controller.md "Room behind every UAV")
    use_slots: bool = True          # destination as a site with one slot per UAV
    use_repulsion: bool = True

    @property
    def tracking_cost(self) -> CostParams:
        from dataclasses import replace
        return replace(self.cost, c1=self.tracking.c1_track)


DEFAULT = DefaultPreset()
"""The product preset (``--preset default``), the default of every entry point."""
