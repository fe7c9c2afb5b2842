"""The per-vehicle controller process: MAVLink link + swarm exchange + controller core.

Data flows one way: telemetry (LOCAL_POSITION_NED) -> Observation -> controller bank of one
-> acceleration setpoint (SET_POSITION_TARGET_LOCAL_NED). Neighbour states come in through
the Zenoh exchange (``mfg_autopilot.runtime.exchange``); the MAVLink link is ``mavlink_bridge``.

Sequence (issue 4): wait for the vehicle's heartbeat and first position -> join the swarm
(MFG: the t = 0 exchange; HJB_d: wait until all N are present) -> stream setpoints, arm,
OFFBOARD -> control loop -> HOLD on the way out (mission over, arrived, signal, error).

With a field mission (``AutopilotConfig.mission``, issue 19; docs/mission.md): wait for the
vehicle's EKF origin (GPS_GLOBAL_ORIGIN, requested, the wait logged) -> if on the ground: arm,
MAV_CMD_NAV_TAKEOFF to the group's altitude, wait until there -> join the swarm with swarm-frame
states -> stream altitude-hold setpoints (type_mask 3387: the group's altitude, the controller's
ax, ay) -> OFFBOARD -> control loop -> the mission's end state (``on_arrival``: hold, or land and
wait for the vehicle to disarm). Every position is converted from the vehicle's own LOCAL_NED to
the swarm frame (``mission.frames``) before the controller sees it, every acceleration back to
the vehicle's axes; nothing assumes that two vehicles share an origin. A failure on the way
(arming denied, takeoff timeout, offboard refused, link lost) is a log line and a safe end state:
hold in the air, land if the mission says so, nothing commanded on the ground.

Clocks:
- lockstep: one control step per simulated dt. The vehicle's LOCAL_POSITION_NED stamped
  t_k gives the state; the setpoint for that step is stamped t_k (docs/lockstep.md), and the
  vehicle answers with the position stamped t_k+1.
- real time: a control step every dt of wall time, triggered by the first fresh
  LOCAL_POSITION_NED after the tick; the setpoint is sent at once and then held by a 20 Hz
  stream until the next step. If telemetry goes stale the stream stops (the vehicle's own
  offboard-loss failsafe takes over) and restarts when telemetry returns.

The log (JSON Lines, docs/controller_log.md) is flushed after every record.
"""

from __future__ import annotations

import gc
import logging
import math
import os
import pickle
import threading
import time
from pathlib import Path

import numpy as np

from mavlink_bridge import (
    BridgeError,
    ExtendedSysState,
    Heartbeat,
    HeartbeatTimeout,
    HomePosition,
    LocalPositionNed,
    MavLandedState,
    TelemetryTimeout,
    VehicleLink,
    load_signing_key,
)
from mavlink_bridge.adsb import adsb_states
from mfg_autopilot.interface import Neighbours, Observation
from mfg_autopilot.mission import GeodeticPoint, VehicleFrame
from mfg_autopilot.guidance.inner_loop import InnerLoop
from mfg_autopilot.presets import make_controller, preset_by_name, with_acc_lag, with_inner_loop
from mfg_autopilot.runtime.config import AutopilotConfig, AutopilotError
from mfg_autopilot.runtime.controller_log import ControllerLog
from mfg_autopilot.runtime.exchange import ExchangeError, ExchangeStopped, ExchangeTimeout, SwarmExchange
from mfg_autopilot.runtime.timing import GcClock, PhaseClock, agreed_start_unix_s, set_realtime_priority
from mfg_autopilot.runtime.zenoh_config import ZenohSettings

__all__ = ["Autopilot", "AutopilotConfig", "AutopilotError", "ControllerLog", "run_autopilot", "set_realtime_priority",
           "LOCKSTEP_PRESTREAM_TIME_BOOT_MS"]

log = logging.getLogger("mfg_autopilot")

LOCKSTEP_PRESTREAM_TIME_BOOT_MS = 0xFFFFFFFF
"""Stamp of the setpoints streamed during the OFFBOARD handshake in lockstep: never a
simulated time, so they satisfy PX4's stream check without advancing the world."""
# real time: OFFBOARD is entered this long before the agreed mission start (the mode's acknowledgement is ~ms on a
# loopback link; the held zero acceleration flown until the first step lets the vehicle drift at its velocity)
OFFBOARD_LEAD_S = 0.05


def _state_of(p: LocalPositionNed) -> np.ndarray:
    """Paper state [x, y, vx, vy] (x = north, y = east) from LOCAL_POSITION_NED."""
    return np.array([p.x_m, p.y_m, p.vx_m_s, p.vy_m_s], dtype=float)


class Autopilot:
    """One vehicle's controller process, given an open link and exchange."""

    def __init__(self, cfg: AutopilotConfig, link: VehicleLink, exchange: SwarmExchange, clog: ControllerLog, stop: threading.Event,
                 gc_clock: GcClock | None = None) -> None:
        self.cfg, self.link, self.exchange, self.clog, self.stop = cfg, link, exchange, clog, stop
        self.gc_clock = gc_clock
        preset = preset_by_name(cfg.preset)
        preset = preset if cfg.inner_loop is None else with_inner_loop(preset, cfg.inner_loop)
        # the airframe the escape's own-vehicle model assumes (TrackingParams.acc_lag_s; safety.backstop.OwnModel)
        self.preset = preset if cfg.acc_lag_s is None else with_acc_lag(preset, cfg.acc_lag_s)
        # TrackingParams.inner_loop: the step's command tracked at every LOCAL_POSITION_NED until the next step (real
        # time: _inner_track; lockstep, a vehicle stepped by sub-steps: _lockstep_inner)
        self.inner = InnerLoop.for_preset(self.preset)
        self.inner_setpoints = 0                      # inner-loop setpoints sent since the last step (its record)
        self._traffic_age_ms: int | None = None       # real time: the age of the traffic set the step used (its record)
        self._warned_whole_period = False             # lockstep inner loop without sub-steps: said once
        self.sites = cfg.sites_array()
        self.ctrl = make_controller(cfg.mode, self.preset, self.sites[cfg.instance : cfg.instance + 1])
        self.dt_s = self.preset.dt_s
        self.dt_ms = int(round(self.dt_s * 1000))
        self.gossips = cfg.mode.startswith("hjb")
        self.mission_start_unix_s: float | None = None
        self.n_t0 = 0
        self._traffic_sensor: bool | None = None    # proximity sensor on the vehicle (decided at the first step)
        self._last_checkpoint_monotonic_s = -math.inf
        self._home: HomePosition | None = None
        self.frame: VehicleFrame | None = None        # the vehicle's LOCAL_NED against the swarm frame (a mission)
        self.z_sp_local_m: float | None = None        # the altitude setpoint (LOCAL_NED z) with a mission
        self._plan_pos: np.ndarray | None = None      # MFG default: the own plan particle at the current step (_act)

    # ---------------------------------------------------------------- frames
    def swarm_state(self, p: LocalPositionNed) -> np.ndarray:
        """The paper state [x, y, vx, vy] of a LOCAL_POSITION_NED in the swarm frame (the vehicle's own
        local frame without a mission: every vehicle then shares one origin, the simulator's case)."""
        s = _state_of(p)
        return s if self.frame is None else self.frame.state_local_to_swarm(s, p.z_m)

    def _setpoint(self, acc_swarm: np.ndarray) -> tuple[float, float, float]:
        """The controller's action (swarm axes) as the vehicle's acceleration setpoint (its own axes)."""
        if self.frame is None:
            return (float(acc_swarm[0]), float(acc_swarm[1]), 0.0)
        a = self.frame.acc_swarm_to_local(np.asarray(acc_swarm, dtype=float))
        return (float(a[0]), float(a[1]), 0.0)

    # ---------------------------------------------------------------- a field mission's start
    def find_frame(self) -> None:
        """Wait for the vehicle's EKF origin and place its LOCAL_NED in the swarm frame."""
        cfg, m = self.cfg, self.cfg.mission
        self.clog.event("waiting_for_origin", note="GPS_GLOBAL_ORIGIN: the vehicle's LOCAL_NED is relative to it")
        origin = _interruptible(lambda s: self.link.wait_origin(s), cfg.origin_timeout_s, self.stop, TelemetryTimeout,
                                lambda: AutopilotError(f"no GPS_GLOBAL_ORIGIN from vehicle {cfg.system_id} within "
                                                       f"{cfg.origin_timeout_s} s: has its EKF a position (GPS fix)?"), slice_s=2.0)
        if origin is None:
            raise _Stopped()
        self.frame = m.frame.vehicle(GeodeticPoint(origin.lat_deg, origin.lon_deg, origin.alt_amsl_m))
        d = self.frame.origin_ned_m
        self.clog.event("origin", lat_deg=origin.lat_deg, lon_deg=origin.lon_deg, alt_amsl_m=origin.alt_amsl_m,
                        offset_ned_m=[round(float(v), 3) for v in d])
        # the group's cruise altitude above the field (the datum's altitude) as this vehicle's local z
        alt_amsl = m.datum.alt_amsl_m + m.altitude_agl_m(cfg.system_id)
        self.z_sp_local_m = float(origin.alt_amsl_m - alt_amsl)

    def lift_off(self) -> LocalPositionNed:
        """On the ground: arm, take off to the group's altitude and wait until there (AUTO.LOITER).
        Returns the position at altitude. Already in the air (a restart): nothing to do."""
        cfg = self.cfg
        p = self.link.wait_local_position(None, cfg.vehicle_timeout_s)
        target = self.z_sp_local_m
        if p.z_m < target + 1.0:                       # within a metre of the altitude or above it: airborne
            self.clog.event("airborne", z_m=p.z_m)
            return p
        self.link.arm(cfg.command_timeout_s)
        self.clog.event("armed")
        alt_amsl = self.frame.origin.alt_amsl_m - target
        self.link.takeoff(alt_amsl, cfg.command_timeout_s)
        self.clog.event("takeoff", altitude_amsl_m=alt_amsl, z_m=target)
        deadline = time.monotonic() + cfg.takeoff_timeout_s
        while True:
            if self.stop.is_set():
                raise _Stopped()
            p = self.link.wait_local_position(None, cfg.vehicle_timeout_s)
            if p.z_m <= target + 0.3 and p.time_boot_ms >= 0:
                self.clog.event("at_altitude", z_m=p.z_m)
                return p
            if time.monotonic() > deadline:
                raise AutopilotError(f"vehicle {cfg.system_id} did not reach {-target:.1f} m above its origin within "
                                     f"{cfg.takeoff_timeout_s} s of takeoff (at {-p.z_m:.1f} m)")
            self.stop.wait(0.2)

    # ---------------------------------------------------------------- phases
    def join_swarm(self, s0: np.ndarray) -> int:
        """MFG: the t = 0 exchange (N - 1 states); in real time it also agrees the mission clock's start
        (timing.agreed_start_unix_s: each state carries the Unix time it was published). HJB_d: wait until all N are
        present."""
        cfg = self.cfg
        if getattr(self.ctrl, "uses_t0_exchange", not self.gossips):
            published = 0.0 if cfg.lockstep else time.time()
            got = self.exchange.initial_exchange(s0, timeout_s=cfg.exchange_timeout_s, time_s=published, stop=self.stop)
            if not cfg.lockstep:
                self.mission_start_unix_s, note = agreed_start_unix_s((m.time_s for m in got.values()), time.time())
                self.clog.event("mission_clock", start_unix_s=self.mission_start_unix_s,
                                in_s=self.mission_start_unix_s - time.time(), **({"note": note} if note else {}))
                if note:
                    log.warning(note)
            ids = np.array(sorted(got), dtype=np.int64)
            states = np.array([got[i].state for i in ids], dtype=float)
            own = int(np.flatnonzero(ids == cfg.instance)[0])
            self.ctrl.exchange_t0(states, ids, np.array([own]), self.sites[ids])
            cert = getattr(self.ctrl, "plan_certificate", None)
            if cert is not None:
                self.clog.event("t0_exchange", states_received=len(ids) - 1, plan=cert)
                if cert.get("plan") == "interacting" and len(ids) > 1:
                    log.warning("no conflict-free plan for this layout: the interacting plan flies, with no separation "
                                "guarantee (docs/default_controller.md, 'Separation by construction')")
            else:
                self.clog.event("t0_exchange", states_received=len(ids) - 1)
            self.n_t0 = len(ids) - 1
            return self.n_t0
        self.exchange.wait_present(range(cfg.n), timeout_s=cfg.exchange_timeout_s, stop=self.stop)
        self.clog.event("swarm_present", n=cfg.n)
        return 0

    def take_off(self, offboard_at_unix_s: float | None = None) -> None:
        """Stream setpoints, arm, enter OFFBOARD (typed errors from the bridge say what failed). offboard_at_unix_s:
        the agreed mission start (real time): OFFBOARD is entered just before it, so that the vehicle holds where it
        was exchanged until the swarm starts (in OFFBOARD with the held zero acceleration it would drift)."""
        cfg = self.cfg
        stamp = LOCKSTEP_PRESTREAM_TIME_BOOT_MS if cfg.lockstep else None
        self.link.set_held_setpoint((0.0, 0.0, 0.0), stamp, z_m=self.z_sp_local_m)
        self.link.start_setpoint_stream(cfg.setpoint_rate_hz)
        # PX4 needs only an offboard setpoint within COM_OF_LOSS_T; its docs ask for > 2 Hz for a
        # while first, and older firmware (and a loaded link) is happier with a second of it
        time.sleep(1.2)
        hb = self.link.latest_heartbeat()
        if hb is None or not hb.armed:                  # a field mission armed before its takeoff
            self.link.arm(cfg.command_timeout_s)
            self.clog.event("armed")
        if offboard_at_unix_s is not None:
            self.stop.wait(max(0.0, offboard_at_unix_s - OFFBOARD_LEAD_S - time.time()))
            if self.stop.is_set():
                raise _Stopped()
        self.link.start_offboard(cfg.command_timeout_s)
        self.clog.event("offboard")
        if cfg.lockstep:
            self.link.stop_setpoint_stream()     # from now on one setpoint per simulated step

    def _observe(self, k: int, state: np.ndarray, time_s: float) -> Observation:
        heard = None
        if self.gossips:
            msgs = self.exchange.gossip(k, time_s, state, self.cfg.range_m, timeout_s=self.cfg.gossip_timeout_s,
                                        lockstep=self.cfg.lockstep)
            if msgs:
                heard = Neighbours(np.array([m.state for m in msgs], dtype=float), np.zeros(len(msgs), dtype=np.int64),
                                   np.array([m.vehicle_id for m in msgs], dtype=np.int64))
            else:
                heard = Neighbours.empty()
        return Observation(k, time_s, state[None, :], heard, self._sensed(int(round(time_s * 1000))))

    # ---- proximity sensor (docs/proximity.md): the vehicle's ADSB_VEHICLE traffic as Observation.sensed
    def _sensed(self, t_ms: int) -> Neighbours | None:
        """Lockstep: the complete traffic set stamped ``t_ms`` (the step's own time; waited
        for, bounded by step_timeout_s). Real time: the newest set younger than
        traffic_max_age_s. None if the controller has no sensor range or the vehicle
        sent no traffic within traffic_probe_s of the first step (no sensor: no backstop)."""
        cfg = self.cfg
        if getattr(self.ctrl, "sensor_range_m", None) is None:
            return None
        if self._traffic_sensor is None:
            self._traffic_sensor = self.link.wait_traffic_sensor(cfg.traffic_probe_s)
            self.clog.event("proximity_sensor", present=self._traffic_sensor,
                            note=None if self._traffic_sensor else f"no traffic from the vehicle within {cfg.traffic_probe_s} s: backstop inactive")
        if not self._traffic_sensor:
            return None
        if self._home is None and cfg.mission is not None:
            # traffic is placed around the mission's datum: the swarm frame (ADSB_VEHICLE is WGS84; the
            # datum's flat-earth scaling is within a few cm of the tangent plane over a km)
            d = cfg.mission.datum
            self._home = HomePosition(d.lat_deg, d.lon_deg, d.alt_amsl_m)
        if cfg.mission is None:
            # the newest HOME_POSITION: PX4 sets home again at arming, wherever the vehicle is then
            self._home = self.link.latest(HomePosition) or self._home
        if self._home is None:
            self._home = self.link.wait_for(HomePosition, lambda h: True, cfg.vehicle_timeout_s)
            if self._home is None:
                raise AutopilotError(f"no HOME_POSITION from vehicle {cfg.system_id} within {cfg.vehicle_timeout_s} s: "
                                     "cannot place its traffic")
        if cfg.lockstep:
            try:
                reports = self.link.sensed_traffic(t_ms, timeout_s=cfg.step_timeout_s)
            except TelemetryTimeout:
                raise AutopilotError(f"vehicle {cfg.system_id} sent no complete traffic set for t = {t_ms} ms within "
                                     f"{cfg.step_timeout_s} s; is its world (mock_vehicle.world) running?") from None
        else:
            got = self.link.latest_traffic(cfg.traffic_max_age_s)
            reports = [] if got is None else got[1]
        ids, states = adsb_states(reports, self._home)
        if cfg.mission is None and states.shape[0] and (self._home.x_m or self._home.y_m):
            # ADSB_VEHICLE is WGS84, placed north/east of home; home itself is at (x, y) in LOCAL_NED (HOME_POSITION
            # carries both). Zero in lockstep (a vehicle frozen until OFFBOARD arms where its origin is); in real time
            # it drifts in the wind before arming: its neighbours were all seen that far off (twenty-seventh session)
            states = states.copy()
            states[:, 0] += self._home.x_m
            states[:, 1] += self._home.y_m
        if not cfg.lockstep:
            # real time: the set is as old as the vehicle's clock says (up to 1 / its traffic rate, 0.05-0.2 s): carried
            # forward to the step at the sensed velocities, as the simulator's sensor sees them at the step (the
            # formation feedback reads each neighbour's deviation from its particle: 0.3 m of staleness is a 1 m/s^2
            # brake; docs/proximity.md, "Real time needs fresh traffic")
            self._traffic_age_ms = None if got is None else t_ms - got[0]
            if self._traffic_age_ms is not None and self._traffic_age_ms > 0 and states.shape[0]:
                states = states.copy()
                states[:, 0:2] += states[:, 2:4] * min(self._traffic_age_ms / 1000.0, cfg.traffic_max_age_s)
        return Neighbours(states, np.zeros(len(ids), dtype=np.int64), ids)

    def _record(self, k: int, t_s: float, state: np.ndarray, acc: np.ndarray, info, obs: Observation,
                latency_s: tuple[float, float, float] | None, timing: dict | None = None) -> None:
        w = self.ctrl.weights()
        rec = {"type": "step", "step": k, "time_s": t_s, "state": state, "acc_m_s2": acc,
               "grad_evals": int(info.grad_evals[0]), "mf_evals": int(info.mf_evals[0]),
               "reg_active": bool(info.reg_active[0]), "residual": float(info.residual[0]) if math.isfinite(info.residual[0]) else None,
               "states_received": 0 if obs.neighbours is None else int(obs.neighbours.states.shape[0]),
               "heard_ids": [] if obs.neighbours is None or obs.neighbours.ids is None else obs.neighbours.ids.tolist(),
               "sensed_ids": None if obs.sensed is None else obs.sensed.ids.tolist(),
               "backstop_active": bool(np.asarray(getattr(self.ctrl, "backstop_active", [False]))[0]),
               "w_H": w["w_H"][0], "wall_s": time.time()}
        if hasattr(self.ctrl, "backstop_layer"):
            # which safety layer made the command (safety.backstop.Layer bits; 0: none): the default controllers
            rec["backstop_layer"] = int(np.asarray(self.ctrl.backstop_layer)[0])
        if self._plan_pos is not None:
            rec["plan_pos_m"] = self._plan_pos[0]
        every = self.cfg.log_fpk_weights_every
        if "w_F" in w and every and (k % every == 0 or k >= self.cfg.steps - 1):
            rec["w_F"] = w["w_F"][0]     # thinned: 69 floats are half the line and the log's largest CPU cost
        if latency_s is not None:
            rec["latency_ms"], rec["latency_wake_ms"], rec["latency_compute_ms"] = (x * 1e3 for x in latency_s)
        if timing is not None:
            rec["timing"] = timing
        if self._traffic_age_ms is not None:
            rec["traffic_age_ms"] = self._traffic_age_ms      # real time: the sensed traffic set's age at this step
        if self.inner is not None:
            rec["inner_setpoints"] = self.inner_setpoints      # sent by the inner loop since the previous step
            self.inner_setpoints = 0
        self.clog.write(rec)

    def _arrived(self, state: np.ndarray) -> bool:
        dest = np.asarray(self.ctrl.destinations_m, dtype=float)[0]
        return bool(np.linalg.norm(state[:2] - dest) <= self.cfg.arrival_tol_m)

    # ---------------------------------------------------------------- the control step
    # A controller that splits its step (preset_default.DefaultMFGController: prepare / act /
    # finish, bit-identical to step) gets only act() between the position and the setpoint;
    # any other controller's step() is the action and the rest at once.
    def _prepare(self, k: int) -> None:
        prepare = getattr(self.ctrl, "prepare", None)
        if prepare is not None:
            prepare(k)

    def _act(self, obs: Observation):
        act = getattr(self.ctrl, "act", None)
        if act is None:
            return self.ctrl.step(obs)
        info = act(obs)
        # the own plan particle at this step (finish() advances the plan): logged, so that a flight's tracking error
        # and the plan's guarantee can be checked afterwards (mfg_swarm.metrics.separation_guarantee)
        plan_pos = getattr(self.ctrl, "plan_positions_m", None)
        self._plan_pos = plan_pos() if plan_pos is not None else None
        return info

    def _finish(self) -> None:
        finish = getattr(self.ctrl, "finish", None)
        if finish is not None:
            finish()

    # ---------------------------------------------------------------- loops
    def run_lockstep(self, p0: LocalPositionNed) -> str:
        cfg = self.cfg
        p = p0
        clock = PhaseClock(self.link, self.gc_clock)
        carried: dict = {}
        while True:
            if self.stop.is_set():
                return "signal"
            clock.start()
            t_ms = p.time_boot_ms
            k = t_ms // self.dt_ms                  # the step index is the vehicle's simulated time
            if k >= cfg.steps:
                if self.gossips:                    # nobody leaves while another waits for its last state
                    late = self.exchange.finish_lockstep(k, t_ms / 1000.0, self.swarm_state(p), timeout_s=cfg.gossip_timeout_s)
                    if late:
                        self.clog.event("finish_wait_timeout", vehicles=sorted(late))
                return "mission_time"
            state = self.swarm_state(p)
            obs = self._observe(k, state, t_ms / 1000.0)
            clock.mark()
            info = self._act(obs)
            clock.mark()
            acc = np.asarray(info.acc_m_s2[0], dtype=float)
            sp = self._setpoint(acc)
            # the setpoint goes on the wire first: the vehicle (and the world barrier behind it)
            # steps while this process finishes the step, writes its log line and checkpoint
            deadline = time.monotonic() + self.cfg.step_timeout_s
            self.link.send_acc_setpoint(sp, t_ms, z_m=self.z_sp_local_m)
            clock.mark()
            self._finish()
            clock.mark()
            timing = clock.record(("observe", "control", "send", "finish"))
            timing.update(carried)      # the previous step's log line + checkpoint, and its wait for this position
            self._record(k, t_ms / 1000.0, state, acc, info, obs, None, timing)
            self._checkpoint(k)
            self._prepare(k + 1)        # the next position is stamped after t_ms: step k + 1 or later
            clock.mark()
            p = self._lockstep_await_position(sp, t_ms, deadline)
            if self.inner is not None:
                p = self._lockstep_inner(p, t_ms, (k + 1) * self.dt_ms, state, acc)
            clock.mark()
            carried = clock.phases(("log", "wait"), first=4)

    def _lockstep_inner(self, p: LocalPositionNed, t0_ms: int, t_next_ms: int, state0: np.ndarray,
                        acc0: np.ndarray) -> LocalPositionNed:
        """Lockstep with the inner loop (TrackingParams.inner_loop): a vehicle stepped by its physics sub-step
        (``mock-vehicle --lockstep --dt-s`` = its ``--physics-dt-s``; ``mfg-swarm run`` starts it so) answers each
        setpoint with the position one sub-step on. Until the next control step (t_next_ms) every position gets the
        step's command corrected towards its reference (guidance/inner_loop.py), stamped with the position's time.
        Times on the vehicle's ms clock, as the simulator counts them. Returns the position at (or after) t_next_ms."""
        # the command as the vehicle got it (float32 on the wire), as the simulator starts it
        self.inner.start(t0_ms / 1000.0, state0.reshape(1, 4), np.float32(acc0).astype(float).reshape(1, 2))
        if p.time_boot_ms >= t_next_ms and not self._warned_whole_period:
            self._warned_whole_period = True
            self.clog.event("inner_loop_idle", note="the vehicle steps a whole control period per setpoint: the inner "
                                                    "loop has no position in between (mock-vehicle --dt-s = its "
                                                    "--physics-dt-s steps it by sub-steps)")
        while p.time_boot_ms < t_next_ms and not self.stop.is_set():
            t_ms = p.time_boot_ms
            acc = self.inner.acc_m_s2(t_ms / 1000.0, self.swarm_state(p).reshape(1, 4))[0]
            sp = self._setpoint(acc)
            self.link.send_acc_setpoint(sp, t_ms, z_m=self.z_sp_local_m)
            self.inner_setpoints += 1
            p = self._lockstep_await_position(sp, t_ms, time.monotonic() + self.cfg.step_timeout_s)
        return p

    def _lockstep_await_position(self, sp: tuple[float, float, float], t_ms: int, deadline: float) -> LocalPositionNed:
        """Wait for the position stamped after t_ms (the setpoint stamped t_ms was sent),
        re-sending the setpoint every step_retry_s of silence (UDP loss; the vehicle ignores
        duplicates); AutopilotError at ``deadline`` (monotonic)."""
        while True:
            try:
                return self.link.wait_local_position(t_ms, timeout_s=max(0.0, min(self.cfg.step_retry_s, deadline - time.monotonic())))
            except TelemetryTimeout:
                if time.monotonic() >= deadline or self.stop.is_set():
                    raise AutopilotError(f"vehicle {self.cfg.system_id} did not advance past t = {t_ms} ms within "
                                         f"{self.cfg.step_timeout_s} s of lockstep setpoints; is it still in OFFBOARD?") from None
            self.link.send_acc_setpoint(sp, t_ms, z_m=self.z_sp_local_m)

    def run_realtime(self) -> str:
        """Control steps on the mission clock: step k at mission start + k dt (wall time), so
        a restarted controller (or one that missed a tick) stays on the same schedule."""
        cfg = self.cfg
        hold_on_arrival = True if cfg.hold_on_arrival is None else cfg.hold_on_arrival
        if self.mission_start_unix_s is None:
            self.mission_start_unix_s = time.time()
        arrived_since = None
        stale = False
        last_k = -1
        clock = PhaseClock(self.link, self.gc_clock)
        while True:
            k_due = int(math.floor((time.time() - self.mission_start_unix_s) / self.dt_s + 1e-9))
            k = max(k_due, last_k + 1)          # on time: the next step; late (or resumed): the one due now
            if k >= cfg.steps:
                return "mission_time"
            tick_unix = self.mission_start_unix_s + k * self.dt_s
            # one wake-up per tick (stop.set() from the signal handler ends the wait at once); the
            # wait is re-checked against the wall clock at least every second
            while not self.stop.is_set() and time.time() < tick_unix:
                if self.inner is not None and self.inner.started and not stale:
                    self._inner_track(min(0.25, max(0.0, tick_unix - time.time())))
                else:
                    self.stop.wait(min(1.0, max(0.0, tick_unix - time.time())))
            if self.stop.is_set():
                return "signal"
            tick = time.monotonic()
            if self.link.heartbeat_age_s() > cfg.vehicle_lost_s:
                self._await_vehicle_return()
                stale = False
                continue
            # the observation-free part of step k first, then the position received after it
            self._prepare(k)
            last = self.link.latest_local_position()
            try:
                p = self.link.wait_local_position(None if last is None else last.time_boot_ms, timeout_s=cfg.telemetry_stale_s)
            except TelemetryTimeout:
                if not stale:
                    stale = True
                    self.link.stop_setpoint_stream()
                    self.clog.event("telemetry_stale", age_s=self.link.telemetry_age_s(),
                                    note="setpoints stopped; the vehicle's offboard-loss failsafe takes over")
                self.stop.wait(0.05)
                continue
            if stale:
                stale = False
                self.clog.event("telemetry_back")
                self._resume_offboard()
            t_woken = time.monotonic()
            clock.start()
            state = self.swarm_state(p)
            last_k = k
            obs = self._observe(k, state, p.time_boot_ms / 1000.0)
            clock.mark()
            info = self._act(obs)
            clock.mark()
            t_computed = time.monotonic()
            acc = np.asarray(info.acc_m_s2[0], dtype=float)
            sp = self._setpoint(acc)
            sent_monotonic_s = self.link.send_acc_setpoint(sp, z_m=self.z_sp_local_m)
            clock.mark()
            self.link.set_held_setpoint(sp, z_m=self.z_sp_local_m)
            if self.inner is not None:
                self.inner.start(p.time_boot_ms / 1000.0, state, np.float32(acc).astype(float))
            self._finish()
            clock.mark()
            # arrival of this LOCAL_POSITION_NED at the socket (kernel timestamp where the
            # transport has one) -> this setpoint handed to the kernel; the rest of the step
            # (finish), logging and the checkpoint come after it. Split: until this loop had
            # the position (receive thread, wake-up), the observation + action, the send.
            latency = (sent_monotonic_s - p.received_monotonic_s,
                       t_woken - p.received_monotonic_s, t_computed - t_woken)
            self._record(k, p.time_boot_ms / 1000.0, state, acc, info, obs, latency,
                         clock.record(("observe", "control", "send", "finish")))
            self._checkpoint(k)
            ended = self._check_mode()
            if ended:
                return ended
            if time.monotonic() - tick > self.dt_s:
                log.warning("control step %d took %.3f s > dt = %.3f s", k, time.monotonic() - tick, self.dt_s)
            if hold_on_arrival and self._arrived(state):
                arrived_since = arrived_since if arrived_since is not None else p.time_boot_ms / 1000.0
                if p.time_boot_ms / 1000.0 - arrived_since >= cfg.arrival_hold_s:
                    return "arrived"
            else:
                arrived_since = None

    def _inner_track(self, timeout_s: float) -> None:
        """Between real-time steps (TrackingParams.inner_loop): wait up to timeout_s for the next LOCAL_POSITION_NED and
        send the step's command corrected towards the trajectory it promised (guidance/inner_loop.py), as the setpoint
        and as the held one the stream repeats. Not more than two periods after the step (a late step: hold it)."""
        last = self.link.latest_local_position()
        try:
            p = self.link.wait_local_position(None if last is None else last.time_boot_ms, timeout_s=timeout_s)
        except TelemetryTimeout:
            return
        t_s = p.time_boot_ms / 1000.0
        if t_s - self.inner.start_time_s > 2.0 * self.dt_s:
            return
        acc = self.inner.acc_m_s2(t_s, self.swarm_state(p).reshape(1, 4))[0]
        sp = self._setpoint(acc)
        self.link.send_acc_setpoint(sp, z_m=self.z_sp_local_m)
        self.link.set_held_setpoint(sp, z_m=self.z_sp_local_m)
        self.inner_setpoints += 1

    def _await_vehicle_return(self) -> None:
        """The vehicle's heartbeat vanished: stop commanding, wait for it, redo the handshake."""
        cfg = self.cfg
        self.link.stop_setpoint_stream()
        self.clog.event("vehicle_lost", heartbeat_age_s=self.link.heartbeat_age_s(), note="setpoints stopped; waiting")
        t = time.monotonic()
        deadline = t + cfg.vehicle_timeout_s
        while not self.stop.is_set():
            try:
                self.link.wait_heartbeat(min(1.0, max(0.01, deadline - time.monotonic())), newer_than_monotonic_s=t)
                break
            except BridgeError:
                if time.monotonic() > deadline:
                    raise AutopilotError(f"vehicle {cfg.system_id} did not come back within {cfg.vehicle_timeout_s} s "
                                         f"(--vehicle-timeout-s)") from None
        if self.stop.is_set():
            return
        self.link.wait_local_position(None, cfg.vehicle_timeout_s)
        self.clog.event("vehicle_back")
        self.take_off()

    # ---------------------------------------------------------------- checkpoints
    def _identity(self) -> dict:
        c = self.cfg
        return {"swarm": c.swarm, "instance": c.instance, "n": c.n, "mode": c.mode, "preset": c.preset,
                "lockstep": c.lockstep, "sites": None if c.sites_m is None else [list(x) for x in c.sites_m]}

    def _checkpoint(self, k: int) -> None:
        """Persist what must survive a controller crash (the t = 0 exchange as held by the
        controller, its learned weights, the mission clock), atomically; at most once per
        ``checkpoint_interval_s`` of wall time (step 0 always: the first
        call). A restarted controller resumes from the newest checkpoint, so from the
        controller state of at most that long ago; the mission clock (real time) and the
        vehicle's simulated time (lockstep) still place it on the right step."""
        if not self.cfg.state_dir:
            return
        now = time.monotonic()
        if now - self._last_checkpoint_monotonic_s < self.cfg.checkpoint_interval_s:
            return
        self._last_checkpoint_monotonic_s = now
        blob = pickle.dumps({"version": 1, "identity": self._identity(), "step": k, "ctrl": self.ctrl,
                             "mission_start_unix_s": self.mission_start_unix_s, "states_received_t0": self.n_t0},
                            protocol=pickle.HIGHEST_PROTOCOL)
        d = Path(self.cfg.state_dir)
        d.mkdir(parents=True, exist_ok=True)
        tmp = d / f".checkpoint.{os.getpid()}.tmp"
        with open(tmp, "wb") as fh:
            fh.write(blob)
        # rename is atomic for a crashing process (what the checkpoint is for); no fsync: it
        # cost ~20 ms per step on the lockstep hot path and only guards against power loss
        os.replace(tmp, d / "checkpoint.pkl")

    def try_resume(self) -> bool:
        """Load the checkpoint of a previous run of this same vehicle's mission, if any."""
        if not self.cfg.state_dir:
            return False
        path = Path(self.cfg.state_dir) / "checkpoint.pkl"
        if not path.exists():
            return False
        try:
            with open(path, "rb") as fh:
                ck = pickle.load(fh)
        except Exception as exc:  # a corrupt checkpoint is reported, never trusted
            self.clog.event("checkpoint_unreadable", path=str(path), error=f"{type(exc).__name__}: {exc}")
            return False
        if ck.get("version") != 1 or ck.get("identity") != self._identity():
            self.clog.event("checkpoint_ignored", path=str(path), note="it belongs to another mission or configuration")
            return False
        self.ctrl = ck["ctrl"]
        self.mission_start_unix_s = ck["mission_start_unix_s"]
        self.n_t0 = ck["states_received_t0"]
        self.clog.event("resumed", from_step=ck["step"], note="no new swarm exchange: t = 0 states and weights from the checkpoint")
        return True

    def _resume_offboard(self) -> None:
        """Telemetry is back: stream setpoints again. Whether the vehicle's failsafe left
        OFFBOARD meanwhile is judged by ``_check_mode`` on the heartbeats that follow."""
        self.link.start_setpoint_stream(self.cfg.setpoint_rate_hz)
        self._stream_since = time.monotonic()
        self._resume_pending = True

    def _check_mode(self) -> str | None:
        """Real time, on fresh heartbeats. After a telemetry outage, if the vehicle's failsafe
        left OFFBOARD, re-enter it (at most every 3 s). Otherwise a mode change away from
        OFFBOARD came from someone else (a pilot, a GCS): respect it and end the mission."""
        hb = self.link.latest_heartbeat()
        now = time.monotonic()
        if hb is None or now - hb.received_monotonic_s > 1.5:
            return None
        if hb.is_offboard:
            if getattr(self, "_resume_pending", False) and now - getattr(self, "_stream_since", now) > 2.5:
                self._resume_pending = False    # the vehicle never left OFFBOARD, or is back in it
            return None
        if not getattr(self, "_resume_pending", False):
            self.clog.event("left_offboard", mode=hb.px4_mode.name, note="mode changed by someone else; not fighting it")
            return "vehicle_left_offboard"
        if now - getattr(self, "_last_reenter", -1e9) < 3.0 or now - self._stream_since < 1.2:
            return None                         # PX4 wants > 1 s of setpoints before OFFBOARD
        self._last_reenter = now
        try:
            self.link.start_offboard(self.cfg.command_timeout_s)
            self._resume_pending = False
            self.clog.event("offboard", resumed=True, was=hb.px4_mode.name)
        except BridgeError as exc:
            self.clog.event("offboard_resume_failed", error=str(exc))
        return None


def run_autopilot(cfg: AutopilotConfig, stop: threading.Event | None = None) -> int:
    """Run one vehicle's controller to the end of its mission. Returns a process exit code."""
    stop = stop or threading.Event()
    clog = ControllerLog(cfg.log_path)
    clog.write({"type": "start", "wall_s": time.time(),
                "config": {k: (vars(v) if isinstance(v, ZenohSettings) else (v.name or "mission") if k == "mission" and v is not None
                               else v) for k, v in vars(cfg).items()}})
    link = None
    reason = "error"
    ap = None
    gc_clock = GcClock().install()
    try:
        key = None if cfg.mavlink_key_file is None else load_signing_key(cfg.mavlink_key_file)
        # the swarm's session first: a bad Zenoh configuration fails before anything flies
        with SwarmExchange(cfg.zenoh, _swarm_key(cfg.swarm), cfg.instance, cfg.n) as exchange:
            link = VehicleLink.open(cfg.connect, target_system=cfg.system_id, target_component=1,
                                    source_system=cfg.system_id, tlog_path=cfg.tlog_path, signing_key=key)
            # start-up waits are long on a loaded machine, so they are sliced to notice a signal
            if _interruptible(lambda t: link.wait_heartbeat(t), cfg.vehicle_timeout_s, stop, HeartbeatTimeout,
                              lambda: HeartbeatTimeout(cfg.system_id, 1, cfg.vehicle_timeout_s)) is None:
                raise _Stopped()
            clog.event("vehicle_found", system_id=cfg.system_id)
            p0 = _interruptible(lambda t: link.wait_local_position(None, t), cfg.vehicle_timeout_s, stop, TelemetryTimeout,
                                lambda: TelemetryTimeout("LOCAL_POSITION_NED", cfg.system_id, cfg.vehicle_timeout_s))
            if p0 is None:
                raise _Stopped()
            ap = Autopilot(cfg, link, exchange, clog, stop, gc_clock)
            if cfg.mission is not None:
                ap.find_frame()
                p0 = ap.lift_off()
            s0 = ap.swarm_state(p0)
            try:
                n_t0 = ap.n_t0 if ap.try_resume() else ap.join_swarm(s0)
            except ExchangeStopped:
                raise _Stopped() from None
            except ExchangeTimeout as exc:
                where = f"; check that --zenoh-connect {list(cfg.zenoh.connect)} is reachable" if cfg.zenoh.connect else ""
                raise AutopilotError(f"{exc}{where}") from None
            # start-up garbage (imports, the t = 0 exchange and plan) is collected once and
            # frozen, so the cyclic GC's full collections during the flight have little to scan
            gc.collect()
            gc.freeze()
            if cfg.rt_priority is not None:
                set_realtime_priority(cfg.rt_priority, clog)
            if stop.is_set():
                reason = "signal"
            else:
                ap.take_off(None if cfg.lockstep else ap.mission_start_unix_s)
                reason = ap.run_lockstep(p0) if cfg.lockstep else ap.run_realtime()
            clog.write({"type": "end", "reason": reason, "wall_s": time.time(),
                        "states_received_total": int(exchange.states_received_total),
                        "states_received_t0": n_t0,
                        "destination_m": np.asarray(ap.ctrl.destinations_m, dtype=float)[0]})
        return 0
    except _Stopped:
        reason = "signal"
        clog.write({"type": "end", "reason": reason, "wall_s": time.time(), "note": "stopped during start-up"})
        return 0
    except (BridgeError, AutopilotError, ExchangeError, TimeoutError, ValueError) as exc:
        clog.event("error", error=f"{type(exc).__name__}: {exc}")
        log.error("%s: %s", type(exc).__name__, exc)
        return 1
    except Exception as exc:  # a bug: say so loudly, still command HOLD on the way out
        clog.event("error", error=f"internal error {type(exc).__name__}: {exc}")
        log.exception("internal error")
        return 1
    finally:
        if link is not None:
            try:
                _end_state(cfg, link, clog, reason)
            except BridgeError as exc:
                clog.event("hold_failed", error=str(exc))
            link.close()
        gc_clock.remove()
        clog.close()


def _end_state(cfg: AutopilotConfig, link: VehicleLink, clog: ControllerLog, reason: str) -> None:
    """The vehicle's safe end state: nothing for a vehicle never heard of, or disarmed on the ground;
    a mission that ends in ``land`` (and finished: mission time or arrival) lands and waits for the
    disarm; everything else holds (PX4 Hold: brake and keep position and altitude)."""
    hb = link.latest_heartbeat()
    if hb is None:
        return                                              # a vehicle never heard of is not commanded
    if cfg.mission is not None and not hb.armed:
        clog.event("on_ground", reason=reason)
        return
    ext = link.latest(ExtendedSysState)
    if cfg.mission is not None and ext is not None and ext.landed_state == MavLandedState.ON_GROUND:
        link.disarm(cfg.command_timeout_s)             # armed but never left the ground (e.g. takeoff failed)
        clog.event("disarmed_on_ground", reason=reason)
        return
    if cfg.mission is not None and cfg.mission.on_arrival == "land" and reason in ("mission_time", "arrived"):
        link.stop_setpoint_stream()
        link.land(cfg.command_timeout_s)
        clog.event("land", reason=reason)
        got = link.wait_for(Heartbeat, lambda h: not h.armed, cfg.land_timeout_s)
        if got is None:
            clog.event("land_timeout", note=f"not disarmed within {cfg.land_timeout_s} s of the land command")
        else:
            clog.event("landed", disarmed=True)
        return
    link.hold(cfg.command_timeout_s if reason != "error" else 3.0)
    clog.event("hold", reason=reason)


class _Stopped(Exception):
    """A signal arrived during a start-up wait."""


def _interruptible(wait, timeout_s: float, stop: threading.Event, timeout_error: type, on_timeout, slice_s: float = 0.5):
    """``wait(t)`` in slices of ``slice_s`` until it returns, ``stop`` is set (returns None),
    or ``timeout_s`` passes (raises ``on_timeout()``: the error for the whole wait)."""
    deadline = time.monotonic() + timeout_s
    while not stop.is_set():
        left = deadline - time.monotonic()
        if left <= 0:
            raise on_timeout()
        try:
            return wait(min(slice_s, left))
        except timeout_error:
            continue
    return None


def _swarm_key(name: str) -> str:
    return name
