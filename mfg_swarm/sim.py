"""The in-process swarm simulator: the controller core driving all N vehicles at once.

One loop per control step t_k = k dt:
1. every UAV observes its own state (rounded to float32, as MAVLink's
   LOCAL_POSITION_NED carries it, so that the simulator and a lockstep process swarm
   see the same numbers);
2. HJB_d: each UAV receives the states of the UAVs within radio range d (k-d tree);
   MFG: the N - 1 states at t = 0 only;
3. the learners (one numpy bank for all UAVs) return accelerations, rounded to
   float32 as SET_POSITION_TARGET_LOCAL_NED carries them;
4. the plant (eq. 9, each vehicle's own noise stream from (seed, id)) advances dt.

Fault events (``SimConfig``):
- ``fail_vehicle`` K, ``fail_at_s`` T: from the first physics sub-step instant >= T (a control instant
  t_k = T when T is one; else inside the control step: a real failure does not wait for the next sample),
  vehicle K stops following its controller and holds (PX4 Hold), towards the braking stop ahead of its state at
  that instant (``braking_stop_m``, as PX4's navigator sets it). Until then in that step it flies the command it was
  given at t_k. ``hold_model`` "px4" (the default; ``sim --hold-model px4``): PX4's trajectory (``PositionSmoothing``,
  MPC_JERK_AUTO = ``hold_jerk_m_s3``) tracked by PX4's position and velocity loops
  (``mock_vehicle.smoothing.Px4AutoXY``), activated at the failure from its state and the acceleration it flew, every
  physics sub-step, as the mock flies Hold. "pd" (the model until the twenty-fifth session): a saturated PD
  (``mock_vehicle.plant.hold_acc_m_s2``) whose acceleration changes from the one it flew last (before the failure:
  its last command, within the airframe's limit) at most ``hold_jerk_m_s3`` (4 m/s^3:
  ``mock_vehicle.plant.jerk_limited_m_s2``, every physics sub-step); with ``hold_jerk_m_s3`` 0 no jerk limit, the PD
  computed at t_k and held over the step, braking at the airframe's limit from the first instant (pessimistic, kept
  to compare; failure times on the control grid only). It still broadcasts
  (HJB_d hears it) and is still seen by proximity sensors. Several failed vehicles: ``fail_vehicle`` a tuple of
  ids, ``fail_at_s`` one time for all or a tuple of one per vehicle (``sim --fail-vehicle K1 --fail-vehicle K2
  [--fail-at T1 --fail-at T2]``); each holds from its own failure on.
- ``gust`` (:class:`GustParams`): an extra acceleration on every vehicle during a time
  window, beyond the modelled wind noise V_o (the controllers' model does not contain it).
  Vehicle i gets acc_m_s2 * (1 + spread * u_i) along the base direction rotated by
  jitter_deg * w_i, u_i, w_i uniform in [-1, 1], the base direction uniform; all drawn
  from numpy's PCG64 seeded with (seed, 0x6057) so a run is reproducible. It is applied
  after each plant step, exactly as a constant acceleration over the part of the step
  inside the window (dr = a h^2/2 ... with h that part; dv = a h), and is not counted in
  the motion energy (it is not commanded).
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from mfg_autopilot.guidance.inner_loop import InnerLoop
from mfg_autopilot.interface import HeardSummary, Neighbours, Observation
from mfg_autopilot.paper.params import Preset
from mfg_autopilot.presets import MODES, make_controller, with_acc_lag
from mfg_autopilot.safety.layers import counts_by_layer
from mock_vehicle.plant import PX4_ACC_LAG_S, PlantParams, SwarmPlant, WindParams, braking_stop_m, hold_acc_m_s2, jerk_limited_m_s2
from mock_vehicle.smoothing import AutoParams, Px4AutoXY
from mock_vehicle.proximity import quantise_sensed_states, sensed_pairs, sensed_rows

from .metrics import arrivals, separation_guarantee
from .results import Trajectories, compute_metrics
from .scenarios import Scenario
from .spatial import count_within, pairs_within_reach, pos_sums_by_tree, rows_within_reach, sorted_unique

__all__ = ["SimConfig", "GustParams", "simulate", "plant_params_for", "as_f32", "gust_acc_m_s2"]


def as_f32(x: np.ndarray) -> np.ndarray:
    """Round to float32 and back: what a MAVLink float field carries."""
    return np.asarray(x, dtype=np.float32).astype(np.float64)


@dataclass(frozen=True)
class GustParams:
    """A wind gust beyond the modelled V_o (module docstring)."""

    start_s: float = 20.0
    duration_s: float = 5.0
    acc_m_s2: float = 1.0          # mean gust acceleration (V_o's noise is ~0.1 m/s per sqrt(s))
    spread: float = 0.5            # per-vehicle magnitude spread (fraction)
    jitter_deg: float = 30.0       # per-vehicle direction spread

    def __post_init__(self) -> None:
        if not (self.duration_s > 0 and self.acc_m_s2 >= 0 and 0 <= self.spread <= 1 and self.start_s >= 0):
            raise ValueError(f"bad gust parameters: {self}")


def gust_acc_m_s2(gust: GustParams, seed: int, n: int) -> np.ndarray:
    """Each vehicle's gust acceleration (n, 2), deterministic in (seed, n)."""
    rng = np.random.Generator(np.random.PCG64(np.random.SeedSequence([seed, 0x6057])))
    base = rng.uniform(0.0, 2.0 * np.pi)
    u = rng.uniform(-1.0, 1.0, n)
    w = rng.uniform(-1.0, 1.0, n)
    ang = base + np.deg2rad(gust.jitter_deg) * w
    return (gust.acc_m_s2 * (1.0 + gust.spread * u))[:, None] * np.stack([np.cos(ang), np.sin(ang)], axis=1)


@dataclass(frozen=True)
class SimConfig:
    scenario: Scenario
    mode: str                      # "mfg" or "hjb"
    preset: Preset
    seed: int = 0
    steps: int = 200
    range_m: float | None = None   # HJB_d radio range d
    physics_dt_s: float = 0.1
    link_float32: bool = True
    fail_vehicle: int | tuple[int, ...] | None = None   # vehicle(s) K that stop following their controller (Hold) ...
    fail_at_s: float | tuple[float, ...] = 0.0          # ... from this time on (one for all, or one per vehicle)
    hold_jerk_m_s3: float = 4.0       # its Hold's jerk limit (PX4 MPC_JERK_AUTO); 0: none
    gust: GustParams | None = None
    hold_model: str = "px4"           # its Hold: "px4" (PX4's trajectory and position loop) or "pd" (PD + jerk limit)
    # the airframes' acceleration response lag (PlantParams.acc_lag_s; 0: none); None: airframe_acc_lag_s(preset), PX4's
    # for the default guidance, none for the paper's presets (eq. 9). Resolved at construction: always a float after it
    acc_lag_s: float | None = None
    # the lag the controllers' own-vehicle model assumes (TrackingParams.acc_lag_s: the escape's prediction of its own
    # swerve); None: the preset's (0: none). Measured against the plant's lag it is not a net gain yet
    # (docs/benchmarks.md, twenty-ninth round), so the simulator does not set it from acc_lag_s
    model_acc_lag_s: float | None = None

    @property
    def failures(self) -> tuple[tuple[int, float], ...]:
        """(vehicle, time s) of every failure, in the order given."""
        if self.fail_vehicle is None:
            return ()
        ks = (self.fail_vehicle,) if np.isscalar(self.fail_vehicle) else tuple(self.fail_vehicle)
        ts = (self.fail_at_s,) * len(ks) if np.isscalar(self.fail_at_s) else tuple(self.fail_at_s)
        return tuple((int(k), float(t)) for k, t in zip(ks, ts))

    @property
    def gossips(self) -> bool:
        """HJB_d modes exchange states with neighbours in range at every step."""
        return self.mode.startswith("hjb")

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise ValueError(f"mode must be one of {', '.join(MODES)}, got {self.mode!r}")
        if self.gossips and not (self.range_m is not None and self.range_m >= 0):
            raise ValueError("HJB_d needs a radio range: give --range-m D or --power-mw P")
        if self.steps < 1:
            raise ValueError(f"steps must be >= 1, got {self.steps}")
        if self.seed < 0:
            raise ValueError(f"seed must be >= 0, got {self.seed}")
        ks = () if self.fail_vehicle is None else np.atleast_1d(self.fail_vehicle)
        ts = np.atleast_1d(np.asarray(self.fail_at_s, dtype=float))
        if self.fail_vehicle is not None and (len(ks) == 0 or not all(float(k).is_integer() and 0 <= k < self.scenario.n
                                                                      for k in ks)):
            raise ValueError(f"fail_vehicle must be in [0, {self.scenario.n - 1}], got {self.fail_vehicle}")
        if len(set(int(k) for k in ks)) != len(ks):
            raise ValueError(f"fail_vehicle names a vehicle twice: {self.fail_vehicle}")
        if ts.size != 1 and ts.size != len(ks):
            raise ValueError(f"fail_at_s: give one time for all failed vehicles or one per vehicle ({len(ks)}), got "
                             f"{self.fail_at_s}")
        if not np.all(np.isfinite(ts) & (ts >= 0)):
            raise ValueError(f"fail_at_s must be finite and >= 0, got {self.fail_at_s}")
        if self.acc_lag_s is None:
            object.__setattr__(self, "acc_lag_s", airframe_acc_lag_s(self.preset))
        PlantParams(acc_lag_s=self.acc_lag_s)        # the plant's own check of the lag, before anything flies
        if self.model_acc_lag_s is not None:
            PlantParams(acc_lag_s=self.model_acc_lag_s)
        if self.hold_model not in ("pd", "px4"):
            raise ValueError(f"hold_model must be pd or px4, got {self.hold_model!r}")
        if self.hold_model == "px4" and not 1.0 <= self.hold_jerk_m_s3 <= 80.0:
            raise ValueError(f"hold_model px4 takes hold_jerk_m_s3 as MPC_JERK_AUTO, in [1, 80] m/s^3, got "
                             f"{self.hold_jerk_m_s3}" + ("; the abrupt Hold (0: no jerk limit) is the PD's: "
                                                         "hold_model='pd' (sim --hold-model pd)"
                                                         if self.hold_jerk_m_s3 == 0 else ""))
        if not (np.isfinite(self.hold_jerk_m_s3) and self.hold_jerk_m_s3 >= 0):
            raise ValueError(f"hold_jerk_m_s3 must be finite and >= 0 (0: no jerk limit), got {self.hold_jerk_m_s3}")
        if self.fail_vehicle is not None and self.hold_jerk_m_s3 == 0:
            dt = self.preset.dt_s
            off = ts[np.abs(ts / dt - np.round(ts / dt)) > 1e-9]
            if off.size:
                raise ValueError(f"fail_at_s {off.tolist()} is not on the control grid (dt = {dt} s): the abrupt Hold "
                                 f"(hold_jerk_m_s3 = 0) is the PD held over a control step; failures inside a step need "
                                 f"PX4's jerk-limited Hold (hold_jerk_m_s3 > 0)")


def _step_with_hold(plant: SwarmPlant, acc_cmd: np.ndarray, dt_s: float, K, hold_pos_m: np.ndarray,
                    hold_acc_m_s2_prev: np.ndarray, jerk_m_s3: float,
                    first_sub: np.ndarray | None = None,
                    models: list[Px4AutoXY] | None = None, inner=None, t0_s: float = 0.0,
                    gust_kick=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One control step with vehicle(s) K (an index, or an index array: then hold_pos_m and hold_acc_m_s2_prev are
    (len(K), 2)) in Hold, every physics sub-step apart (as the mock vehicle flies it): their acceleration is the Hold
    PD's on their state then (``hold_acc_m_s2``), jerk-limited from the previous sub-step's (``jerk_limited_m_s2``);
    the others hold ``acc_cmd``. The sub-steps draw the same noise and make the same operations as one
    ``plant.step(acc_cmd, dt_s)`` does for them, so they move bit for bit as without the loop.

    ``first_sub`` (len(K),), ints: the sub-step at which each vehicle enters Hold during this step (0, the default:
    from the step's start). Before it the vehicle flies its command ``acc_cmd``; at it, its Hold point becomes the
    braking stop ahead of its state then (``braking_stop_m``, replacing its row of hold_pos_m) and its smoothing
    starts from the acceleration it flew (PX4's ``FlightTaskAuto::activate``).

    ``models`` (len(K),): PX4's trajectory and position loop per vehicle (``hold_model`` "px4") instead of the PD and
    the jerk limit; a model not yet active is activated at the vehicle's first Hold sub-step (its state then, its Hold
    point, the acceleration it flew), as the mock activates it at the mode switch.
    ``inner(i, states)`` (TrackingParams.inner_loop): the others fly its command (n, 2) at each sub-step i instead of
    holding ``acc_cmd``, and ``gust_kick(t_a, t_b)`` (if given) adds the gust of each sub-step
    [t_a, t_b] right after it, so that the inner loop meets it inside the period.
    Returns (the applied accelerations, K's the mean over the sub-steps - everyone's with ``inner``; K's last
    acceleration (len(K), 2); the Hold points (len(K), 2))."""
    K = np.atleast_1d(np.asarray(K, dtype=np.int64))
    k_sub = plant.params.substeps(dt_s)
    h = dt_s / k_sub
    acc = acc_cmd.copy()
    applied, mean_k = None, np.zeros((K.size, 2))
    a_k = np.asarray(hold_acc_m_s2_prev, dtype=float).reshape(K.size, 2).copy()
    hold_pos_m = np.asarray(hold_pos_m, dtype=float).reshape(K.size, 2).copy()
    first = np.zeros(K.size, dtype=np.int64) if first_sub is None else np.asarray(first_sub, dtype=np.int64)
    mean_all = np.zeros_like(acc) if inner is not None else None
    for i in range(k_sub):
        if inner is not None:
            acc = inner(i, plant.states)
        starting = first == i
        if i > 0 and starting.any():          # a failure inside the step: Hold from this sub-step's state
            hold_pos_m[starting] = braking_stop_m(plant.states[K[starting]])
        on = first <= i
        if on.any():
            if models is None:
                target = hold_acc_m_s2(plant.states[K[on]], hold_pos_m[on], plant.params.acc_limit_m_s2)
                a_k[on] = jerk_limited_m_s2(a_k[on], target, jerk_m_s3, h)
            else:
                for j in np.flatnonzero(on):
                    state_j = plant.states[K[j]]
                    if not models[j].active:
                        models[j].activate(state_j, hold_pos_m[j], a_k[j])
                    a_k[j] = models[j].acc_m_s2(state_j, h, plant.params.acc_limit_m_s2)
            acc[K[on]] = a_k[on]
        got = plant.step(acc, h)
        if gust_kick is not None:
            gust_kick(t0_s + i * h, t0_s + (i + 1) * h)
        a_k = got[K].copy()            # what the airframe applied (within its limit): also the last flown command
        mean_k += a_k
        applied = got if applied is None else applied
        if mean_all is not None:
            mean_all += got
    applied = applied.copy() if mean_all is None else mean_all / k_sub
    applied[K] = mean_k / k_sub
    return applied, a_k, hold_pos_m


def airframe_acc_lag_s(preset: Preset) -> float:
    """The acceleration lag of the airframe a preset flies by default (s): PX4's (``PX4_ACC_LAG_S``, 0.154 s) for the
    default guidance's presets, which are built to fly a PX4 airframe, and none for the paper's, whose reproduction is
    the paper's plant, eq. 9 (the command flown at once). The simulator's and ``mfg-swarm run``'s default; the mock
    vehicle's own default is PX4's."""
    return PX4_ACC_LAG_S if getattr(preset, "tracking", None) is not None else 0.0


def plant_params_for(preset: Preset, physics_dt_s: float = 0.1, acc_lag_s: float = 0.0) -> PlantParams:
    """The plant that matches the preset's model (same c0, v_o, V_o, acceleration limit); ``acc_lag_s`` the
    airframe's acceleration response lag (``PlantParams.acc_lag_s``), which the model does not have."""
    c = preset.cost
    return PlantParams(wind=WindParams(c0_per_s=c.c0_per_s, mean_wind_m_s=tuple(c.mean_wind_m_s),
                                       wind_diffusion_m_s=tuple(map(tuple, c.wind_diffusion_m_s))),
                       acc_limit_m_s2=preset.learner.acc_max_m_s2, physics_dt_s=physics_dt_s, acc_lag_s=acc_lag_s)


FULL_HEARD_MAX_STATES = 0
"""HJB_d: up to this many heard states in a step (summed over UAVs) every heard state is delivered,
whatever the controller's heard_cutoff_m (kept for experiments: the cutoff gives the same actions)."""

def heard_summary_by_tree(tree: cKDTree, pts: np.ndarray, range_m: float, counts: np.ndarray,
                          pos_sum: np.ndarray | None = None) -> HeardSummary:
    """HeardSummary over every vehicle within range_m of each one (self excluded), without listing
    every heard pair: pts (N, 2), tree = cKDTree(pts), counts (N,) the exact heard counts; pos_sum
    (N, 2) the sums of the heard positions if already known (spatial.count_within), else
    summed from the tree's pairs in row blocks (memory O(block N))."""
    if pos_sum is None:
        pos_sum = pos_sums_by_tree(tree, pts, range_m)
    dnn, _ = tree.query(pts, k=2)
    nearest = np.where(dnn[:, 1] <= range_m, dnn[:, 1], np.inf)
    return HeardSummary(np.asarray(counts, dtype=np.int64), pos_sum, nearest)


def hear(obs: np.ndarray, range_m: float, ctrl, step: int, sensed_pairs_: np.ndarray | None = None,
         sensor_range_m: float | None = None, tree: cKDTree | None = None) -> tuple[Neighbours, HeardSummary | None, np.ndarray]:
    """HJB_d's exchange at one step: every UAV hears the UAVs within range_m (k-d tree).

    Returns (heard, summary, counts): counts (N,) is the exact number of states each UAV
    received (the communication metric). If the controller declares a ``heard_cutoff_m`` reach
    (controller.Controller) that stays below range_m, and the sensor range is below range_m,
    only the heard states within the reach and the sensed ones (``sensed_pairs_``: the backstop
    leaves heard vehicles to communication) are listed - O(N log N + those pairs) instead of
    O(pairs within d): at the destination every UAV hears everyone - with a HeardSummary over
    all heard states when the controller needs it. ``tree``: a cKDTree of obs[:, 0:2] if the caller has one.

    The counts come from :func:`~mfg_swarm.spatial.count_within` (exact; a grid for large N,
    O(N (d / s + density d s)) instead of O(N x neighbours)); at large N the summary's position sums
    come from the same pass (summed in another order: rounding only)."""
    n = obs.shape[0]
    if n < 2:
        return Neighbours.from_pairs(obs, np.zeros((0, 2), np.int64)), None, np.zeros(n, dtype=np.int64)
    pts = obs[:, 0:2]
    tree = cKDTree(pts) if tree is None else tree
    reach = ctrl.heard_cutoff_m(step, obs) if hasattr(ctrl, "heard_cutoff_m") else None
    if reach is not None and (sensor_range_m is None or sensor_range_m < range_m):
        want_summary = getattr(ctrl, "needs_heard_summary", True)
        counts, pos_sum = (count_within(pts, range_m, tree, pos_sums=True) if want_summary
                           else (count_within(pts, range_m, tree), None))
        pairs = (pairs_within_reach(tree, pts, reach, range_m, vel=obs[:, 2:4]) if int(counts.sum()) > FULL_HEARD_MAX_STATES
                 else None)
        if pairs is not None:
            if sensed_pairs_ is not None and sensed_pairs_.size:
                sp = np.sort(np.asarray(sensed_pairs_, dtype=np.int64), axis=1)
                k = sorted_unique(np.concatenate([pairs[:, 0] * n + pairs[:, 1], sp[:, 0] * n + sp[:, 1]]))
                pairs = np.stack([k // n, k % n], axis=1)
            heard = Neighbours.from_pairs(obs, pairs)
            summary = heard_summary_by_tree(tree, pts, range_m, counts, pos_sum) if want_summary else None
            return heard, summary, counts
    heard = Neighbours.from_pairs(obs, tree.query_pairs(range_m, output_type="ndarray"))
    return heard, None, heard.counts(n)


class _Progress:
    def __init__(self, total: int, enabled: bool) -> None:
        self.total, self.enabled, self.last = total, enabled, -1.0

    def update(self, k: int) -> None:
        if not self.enabled:
            return
        now = time.monotonic()
        if now - self.last < 0.2 and k < self.total:
            return
        self.last = now
        width = 30
        done = int(width * k / self.total)
        sys.stderr.write(f"\r  [{'#' * done}{'.' * (width - done)}] step {k}/{self.total}")
        if k >= self.total:
            sys.stderr.write("\n")
        sys.stderr.flush()


def simulate(cfg: SimConfig, progress: bool | None = None) -> tuple[Trajectories, dict]:
    """Fly the scenario; return the trajectories and metrics.json's contents."""
    t_wall = time.perf_counter()
    sc = cfg.scenario
    # the airframe the controllers' own-vehicle model assumes (TrackingParams.acc_lag_s), if given
    preset = cfg.preset if cfg.model_acc_lag_s is None else with_acc_lag(cfg.preset, cfg.model_acc_lag_s)
    n, T, dt = sc.n, cfg.steps, preset.dt_s
    plant = SwarmPlant(sc.initial_pos_m, plant_params_for(preset, cfg.physics_dt_s, cfg.acc_lag_s), cfg.seed,
                       initial_vel_m_s=getattr(sc, "initial_vel_m_s", None))
    f32 = as_f32 if cfg.link_float32 else (lambda x: np.asarray(x, dtype=float))

    pos = np.empty((T + 1, n, 2)); vel = np.empty((T + 1, n, 2)); acc_log = np.empty((T, n, 2))
    comm = np.zeros((T + 1, n), dtype=np.int64); grad = np.zeros((T, n), dtype=np.int64)
    mfe = np.zeros((T, n), dtype=np.int64); reg = np.zeros((T, n), dtype=bool)

    ctrl = make_controller(cfg.mode, preset, sc.destination_m)
    ids = np.arange(n)
    cert = {}
    if getattr(ctrl, "uses_t0_exchange", not cfg.gossips):
        ctrl.exchange_t0(f32(plant.states), ids, ids, sc.destination_m)       # the t = 0 exchange
        cert = getattr(ctrl, "plan_certificate", None) or {}
        if cert.get("plan") == "interacting" and n > 1:
            print("[sim] note: no conflict-free plan was found for this layout (docs/default_controller.md, 'Separation by "
                  "construction'); the interacting plan flies, with no separation guarantee", file=sys.stderr)
        if cert.get("duration_s") is not None and cert["duration_s"] > cfg.steps * cfg.preset.dt_s:
            print(f"[sim] note: the t = 0 plan ({cert['plan']}) takes {cert['duration_s']:.0f} s; --steps {cfg.steps} "
                  f"flies {cfg.steps * cfg.preset.dt_s:.0f} s, so not every UAV will have arrived "
                  f"(--steps {int(np.ceil(cert['duration_s'] / cfg.preset.dt_s)) + 20} would do)", file=sys.stderr)
        comm[0] += n - 1
    sensor_range_m = getattr(ctrl, "sensor_range_m", None)
    # HJB_d whose radio range covers the sensor range hears every vehicle it senses; a controller that ignores
    # sensed vehicles it also heard (``ignores_sensed_if_heard``) then needs no sensed states at all
    sensing_unused = (cfg.gossips and sensor_range_m is not None and sensor_range_m <= cfg.range_m
                      and getattr(ctrl, "ignores_sensed_if_heard", False))
    w_ref = np.empty((T + 1, ctrl.weights()["w_H"].shape[1]))
    bar = _Progress(T, sys.stderr.isatty() if progress is None else progress)

    # MFG: each UAV's own plan particle at every control instant, for the guarantee's per-flight check (metrics
    # "guarantee"); the plan has been caught up to step k when step k begins (it advances at the end of each step)
    plan_pos = np.full((T + 1, n, 2), np.nan) if getattr(ctrl, "plan_positions_m", None) and cert else None
    failures = cfg.failures
    fail_ids = np.array([K for K, _ in failures], dtype=np.int64)
    holding = np.zeros(len(failures), dtype=bool)                 # failed already
    holds_pos, holds_acc = np.zeros((len(failures), 2)), np.zeros((len(failures), 2))   # Hold point, last acceleration
    hold_models = ([Px4AutoXY(AutoParams(mpc_jerk_auto_m_s3=cfg.hold_jerk_m_s3)) for _ in failures]
                   if cfg.hold_model == "px4" else None)
    a_gust = gust_acc_m_s2(cfg.gust, cfg.seed, n) if cfg.gust is not None else None
    h_sub = dt / plant.params.substeps(dt)        # a failure inside a control step begins at a physics sub-step
    inner = InnerLoop.for_preset(preset)

    def _gust_kick(t_a: float, t_b: float) -> None:
        """The gust's share of [t_a, t_b] added to the states at t_b (it acts beyond the plant's model)."""
        t0, t1 = max(t_a, cfg.gust.start_s), min(t_b, cfg.gust.start_s + cfg.gust.duration_s)
        if t1 > t0:
            h = t1 - t0
            st = plant.states.copy()
            st[:, 0:2] += 0.5 * a_gust * h * h + a_gust * h * (t_b - t1)
            st[:, 2:4] += a_gust * h
            plant.states = st

    gust_kick = _gust_kick if cfg.gust is not None else None
    dt_ms, h_ms = int(round(dt * 1000)), int(round(h_sub * 1000))

    def inner_acc(i: int, states: np.ndarray) -> np.ndarray:
        """The inner loop's commands at sub-step i of the step it was started at, as a lockstep process computes them:
        from the float32 telemetry, on the vehicle's ms clock, sent as float32 (autopilot._lockstep_inner)."""
        t0_ms = int(round(inner.start_time_s * 1000))
        return f32(inner.acc_m_s2((t0_ms + i * h_ms) / 1000.0, f32(states)))
    backstop_active = np.zeros((T, n), dtype=bool)
    # which safety layer made each command (safety.backstop.Layer bits), for controllers that say (the default ones)
    layered = hasattr(ctrl, "backstop_layer")
    backstop_layer = np.zeros((T, n), dtype=np.uint8) if layered else None
    for k in range(T):
        obs = f32(plant.states)
        pos[k], vel[k] = plant.states[:, 0:2], plant.states[:, 2:4]
        w_ref[k] = ctrl.weights()["w_H"][0]
        heard = sensed = None
        heard_summary = None
        sp = rows = None
        if sensor_range_m is not None and n > 1 and not sensing_unused:
            # onboard proximity sensor: true neighbour states within its range, no communication, sorted by
            # (owner, id) and at the resolution of the ADSB_VEHICLE a mock forwards them in (docs/proximity.md);
            # only the sensed vehicles that can change an action (the controller's sensed_cutoff_m reach, if any)
            # every vehicle's state as the sensor delivers it (the same to every observer): the reach can then
            # decide on what the rows will see
            q_all = quantise_sensed_states(obs)
            reach = ctrl.sensed_cutoff_m(obs, sensed_states=q_all) if hasattr(ctrl, "sensed_cutoff_m") else None
            if reach is not None and not cfg.gossips:      # the rows straight away (hear() would need the pairs)
                rows = rows_within_reach(obs[:, 0:2], reach, sensor_range_m, vel=obs[:, 2:4])
            else:
                sp = None if reach is None else pairs_within_reach(None, obs[:, 0:2], reach, sensor_range_m, clip=True,
                                                                   vel=obs[:, 2:4])
                sp = sensed_pairs(obs, sensor_range_m) if sp is None else sp
        if cfg.gossips:
            heard, heard_summary, counts = hear(obs, cfg.range_m, ctrl, k, sp, sensor_range_m)
            comm[k] += counts
        if sp is not None or rows is not None:
            owner, other = rows if rows is not None else sensed_rows(sp)
            sensed = Neighbours(np.take(q_all, other, axis=0), owner, other)     # = q_all[other]; np.take copies ~3x faster
        if plan_pos is not None:
            ctrl.prepare(k)
            plan_pos[k] = ctrl.plan_positions_m()
        info = ctrl.step(Observation(k, k * dt, obs, heard, sensed, heard_summary))
        if plan_pos is not None:
            # the particle as the controller tracked it at this step (deflected around a failed vehicle: guidance/detour.py)
            ref = getattr(ctrl, "tracked_reference_m", None)
            if ref is not None and ref[0] == k:
                plan_pos[k] = ref[1]
        acc_cmd = f32(info.acc_m_s2)
        if inner is not None:
            inner.start(k * dt_ms / 1000.0, obs, acc_cmd)
        kicked = False              # the sub-steps took this step's gust (the inner loop meets it inside the period)
        if failures and any((k + 1) * dt > t + 1e-9 for _, t in failures):
            # the failed vehicles, each from its own failure on: at this control instant, or at a physics sub-step
            # inside this step (first_sub), flying its command until then
            first_sub = np.zeros(len(failures), dtype=np.int64)
            for j, (Kj, tj) in enumerate(failures):
                if (k + 1) * dt > tj + 1e-9 and not holding[j]:
                    holding[j] = True
                    first_sub[j] = max(0, int(np.ceil((tj - k * dt) / h_sub - 1e-9)))
                    holds_pos[j] = braking_stop_m(obs[Kj:Kj + 1])[0]    # PX4's loiter point: the braking stop ahead
                    # PX4's smoothing starts from the last setpoint's acceleration (the one it flew in offboard)
                    holds_acc[j] = acc_log[k - 1, Kj] if k > 0 else 0.0
            Ks = fail_ids[holding]
            if cfg.hold_jerk_m_s3 > 0:
                acc_log[k], holds_acc[holding], holds_pos[holding] = _step_with_hold(
                    plant, acc_cmd, dt, Ks, holds_pos[holding], holds_acc[holding], cfg.hold_jerk_m_s3,
                    first_sub[holding],
                    None if hold_models is None else [m for m, on in zip(hold_models, holding) if on],
                    inner_acc if inner is not None else None, k * dt, gust_kick if inner is not None else None)
                kicked = inner is not None
            else:       # no jerk limit: the PD held over the control step, at the airframe's limit from the first instant
                acc_cmd[Ks] = hold_acc_m_s2(obs[Ks], holds_pos[holding], plant.params.acc_limit_m_s2)
                acc_log[k] = plant.step(acc_cmd, dt)
        elif inner is not None:
            acc_log[k], _, _ = _step_with_hold(plant, acc_cmd, dt, np.zeros(0, dtype=np.int64), np.zeros((0, 2)),
                                               np.zeros((0, 2)), 0.0, inner=inner_acc, t0_s=k * dt, gust_kick=gust_kick)
            kicked = True
        else:
            acc_log[k] = plant.step(acc_cmd, dt)
        if gust_kick is not None and not kicked:
            gust_kick(k * dt, (k + 1) * dt)
        backstop_active[k] = np.asarray(getattr(ctrl, "backstop_active", np.zeros(n, dtype=bool)), dtype=bool)
        if layered:
            backstop_layer[k] = np.asarray(ctrl.backstop_layer, dtype=np.uint8)
        for Kj, tj in failures:
            if tj <= k * dt + 1e-9:
                # a failed vehicle flies its Hold, not this step's command: its row's flags are no intervention (the
                # bank still computes the row; with the disturbance observer its flags follow the Hold's acceleration)
                backstop_active[k, Kj] = False
                if layered:
                    backstop_layer[k, Kj] = 0
        grad[k], mfe[k], reg[k] = info.grad_evals, info.mf_evals, info.reg_active
        bar.update(k + 1)
    pos[T], vel[T] = plant.states[:, 0:2], plant.states[:, 2:4]
    w_ref[T] = ctrl.weights()["w_H"][0]
    if plan_pos is not None:
        ctrl.prepare(T)
        plan_pos[T] = ctrl.plan_positions_m()

    traj = Trajectories(dt_s=dt, pos_m=pos, vel_m_s=vel, acc_m_s2=acc_log, dest_m=np.asarray(ctrl.destinations_m, dtype=float).copy(),
                        comm_states=comm, grad_evals=grad, mf_evals=mfe, reg_active=reg, w_H_ref=w_ref,
                        extra={"backstop_active": backstop_active,
                               **({"backstop_layer": backstop_layer} if layered else {})})
    metrics = compute_metrics(traj, n=n, mode=cfg.mode, range_m=cfg.range_m if cfg.gossips else None,
                              seed=cfg.seed, wall_s=time.perf_counter() - t_wall, scenario=sc.name,
                              preset=preset.name, path="sim")
    metrics["backstop_activations"] = int(backstop_active.sum())
    metrics["safety_interventions"] = metrics["backstop_activations"]   # (vehicle, step) pairs the backstop acted
    if layered:
        # the same (vehicle, step) pairs by the layer that made the command (a row may carry two bits: a filtered
        # layer and the last layer over it)
        metrics["safety_interventions_by_layer"] = counts_by_layer(backstop_layer)
    cert = getattr(ctrl, "plan_certificate", None)
    if cert is not None:
        metrics["plan"] = cert            # what the t = 0 plan guarantees (guidance: rigid, scheduled groups, or none)
    metrics.update(start_spacing_m=sc.min_start_spacing_m, slot_spacing_m=sc.slot_spacing_m)
    metrics["acc_lag_s"] = cfg.acc_lag_s
    if inner is not None:
        metrics["inner_loop"] = {"kp_per_s2": inner.kp, "kd_per_s": inner.kd}
    if failures:
        Ks = [K for K, _ in failures]
        others = np.ones(n, dtype=bool); others[Ks] = False
        arrived, _ = arrivals(pos, traj.dest_m, dt)
        one = len(failures) == 1        # one failed vehicle: its id and time as numbers, as before
        metrics.update(fail_vehicle=Ks[0] if one else Ks, fail_at_s=failures[0][1] if one else [t for _, t in failures],
                       hold_jerk_m_s3=cfg.hold_jerk_m_s3,
                       hold_model=cfg.hold_model,
                       failed_vehicle_collision_pairs=sum(1 for p in metrics["collided_pairs_list"]
                                                          if any(K in p for K in Ks)),
                       arrived_fraction_others=float(arrived[others].mean()) if others.any() else None)
    if plan_pos is not None:
        # the certified plan's guarantee on this flight: UAVs within e_max of their particles keep the particles'
        # distance - 2 e_max (a UAV that failed leaves the tracking set at its failure: its pairs are the backstop's)
        tracking = np.ones((T + 1, n), dtype=bool)
        for K, t_fail in failures:
            tracking[int(np.ceil(t_fail / dt - 1e-9)):, K] = False
        metrics["guarantee"] = {"certified": cert.get("clearance_m") is not None, **separation_guarantee(pos, plan_pos, tracking, metrics["min_separation_m"])}
    if cfg.gust is not None:
        metrics["gust"] = {k: getattr(cfg.gust, k) for k in ("start_s", "duration_s", "acc_m_s2", "spread", "jitter_deg")}
    return traj, metrics
