"""A PX4-like vehicle: mode machine, setpoint filter, failsafe, telemetry and parameters
around the eq. 9 plant (issue 3; SPEC section 4). No sockets here: ``MockVehicle.handle``
takes a decoded message, ``MockVehicle.tick`` advances the clocks; both send through the
``send(msg, port)`` callback given at construction (``port=None`` means every port).

Where things live: this module holds the configuration, the input (commands, setpoints,
parameters), the clocks, the horizontal dynamics and the proximity sensor; the PX4 mode machine
(arming, takeoff, land, failsafe, the vertical axis, the ground) is ``lifecycle.LifecycleMixin``;
what the vehicle reports is ``telemetry.TelemetryMixin``; PX4's setpoint gates are ``setpoint``.

Clocks (docs/lockstep.md):
- real time: simulated time = wall time since start; physics sub-stepped every
  ``physics_dt_s`` of wall time; ``time_boot_ms`` = wall ms since start.
- lockstep: simulated time starts at 0 and advances by exactly ``dt_s`` when, armed and in
  OFFBOARD, a setpoint stamped with the current simulated ``time_boot_ms`` arrives.

Signing (issue 10, docs/security.md): with ``require_signed`` every message whose
signature is not valid and fresh (``Received.signature``) is ignored before it reaches
the mode machine, the setpoint filter or the parameters, and logged once per kind
("unsigned COMMAND_LONG", "bad signature SET_MODE", "replayed timestamp
SET_POSITION_TARGET_LOCAL_NED", ... for the commanding messages, "... other message"
for the rest). Signing what the vehicle sends is the port's job (``MavlinkPort``).

Dynamics (air start, the default): frozen at the initial state until the first OFFBOARD entry
(the vehicle hovers at its slot); then OFFBOARD integrates the held setpoint, every other mode PX4
Hold (``hold_acc_m_s2`` around PX4's braking stop ahead of where it began, ``plant.braking_stop_m``); in the auto
modes (Takeoff, Hold, Land) the acceleration changes at most MPC_JERK_AUTO from the one flown before, every physics
sub-step (``plant.jerk_limited_m_s2``: PX4's ``PositionSmoothing``). A setpoint PX4's position controller refuses
(``setpoint.classify_setpoint``: an axis without a term, x/y not in pairs, a NaN in a used field)
keeps OFFBOARD but flies PX4's "stop and wait" (velocity 0). Ground start (``start_on_ground``) and
the altitude loop: ``lifecycle``. Own EKF origin (``origin``): ``telemetry`` and ``geo``.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from mavlink_bridge import (
    MSG_ID_BY_NAME,
    PX4_HOLD,
    PX4_LAND,
    PX4_OFFBOARD,
    PX4_POSCTL,
    PX4_TAKEOFF,
    BadData,
    CommandAck,
    CommandInt,
    CommandLong,
    MavCmd,
    MavModeFlag,
    MavParamType,
    MavResult,
    Message,
    NamedValueInt,
    ParamRequestList,
    ParamRequestRead,
    ParamSet,
    ParamValue,
    PositionTargetTypeMask,
    Px4Mode,
    Received,
    SetMode,
    SetPositionTargetLocalNed,
    UnknownMessage,
)
from mavlink_bridge.adsb import TRAFFIC_MARKER_NAME
from mavlink_bridge.ratelog import RejectLog

from .geo import LocalFrame
from .lifecycle import POSCTL_DT_S, LifecycleMixin
from .params import ParamTable
from .plant import PX4_ACC_LAG_S, PlantParams, SwarmPlant, WindParams, hold_acc_m_s2, jerk_limited_m_s2, saturate_norm
from .proximity import traffic_reports
from .setpoint import SETPOINT_LIMITS, check_setpoint, classify_setpoint  # noqa: F401  (check_setpoint: re-exported)
from .smoothing import AutoParams, Px4AutoXY
from .telemetry import FAST_TELEMETRY, TELEMETRY_IDS, TelemetryMixin

__all__ = ["VehicleConfig", "MockVehicle", "RejectLog", "check_setpoint", "SETPOINT_LIMITS", "SIGNED_COMMAND_MESSAGES"]

log = logging.getLogger("mock_vehicle")

SIGNED_COMMAND_MESSAGES = (CommandLong, CommandInt, SetMode, SetPositionTargetLocalNed, ParamSet)
"""Messages that command the vehicle; with signing on, each has its own rejection kind."""

_ID = MSG_ID_BY_NAME


@dataclass(frozen=True)
class VehicleConfig:
    """Everything the mock vehicle needs, read once at the command line."""

    instance: int = 0
    initial_pos_m: tuple[float, float] = (0.0, 0.0)
    initial_vel_m_s: tuple[float, float] | None = None
    seed: int = 0
    home_lat_deg: float = 47.397742
    home_lon_deg: float = 8.545594
    home_alt_amsl_m: float = 488.0
    altitude_m: float = 10.0
    wind: WindParams = field(default_factory=WindParams)
    acc_limit_m_s2: float = 2.0
    physics_dt_s: float = 0.1
    acc_lag_s: float = PX4_ACC_LAG_S  # the airframe's acceleration response lag (plant.PlantParams.acc_lag_s; SIM_ACC_TAU):
                                     # PX4's by default
    dt_s: float = 1.0
    lockstep: bool = False
    com_of_loss_t_s: float = 1.0
    deny_arming: bool = False
    start_on_ground: bool = False                          # boot ON_GROUND, disarmed, at initial_pos_m (z = 0)
    origin: tuple[float, float, float] | None = None       # EKF origin (lat_deg, lon_deg, alt_amsl_m); None: the home
    params: tuple[tuple[str, float], ...] = ()             # PX4-style parameters set at boot (params.PARAM_SPECS), after the above
    rates_hz: dict = field(
        default_factory=lambda: {
            "heartbeat": 1.0,
            "local_position": 30.0,
            "attitude": 10.0,
            "global_position": 5.0,
            "sys_status": 1.0,
            "extended_sys_state": 1.0,
            "home_position": 0.5,
        }
    )
    lockstep_resend_hz: float = 5.0
    traffic_rate_hz: float = 5.0     # proximity sensor (with a world): report/answer rate in real time, re-send rate in lockstep
    hold_model: str = "px4"
    """How the auto modes (Takeoff, Hold, Land) move horizontally: "px4" (the default) PX4's trajectory
    (``PositionSmoothing``) tracked by PX4's position and velocity loops (``smoothing.Px4AutoXY``); "pd" the saturated
    PD towards the Hold point, jerk-limited at MPC_JERK_AUTO (``plant.hold_acc_m_s2``, ``plant.jerk_limited_m_s2``),
    the mock's model before PX4's was ported."""

    HOLD_MODELS = ("pd", "px4")

    def __post_init__(self) -> None:
        if self.hold_model not in self.HOLD_MODELS:
            raise ValueError(f"hold_model must be one of {', '.join(self.HOLD_MODELS)}, got {self.hold_model!r}")

    @property
    def system_id(self) -> int:
        return self.instance + 1

    @property
    def component_id(self) -> int:
        return 1


def _finite(*xs: float) -> bool:
    return all(math.isfinite(x) for x in xs)


_F = PositionTargetTypeMask
_X_IGNORE, _Y_IGNORE, _VX_IGNORE, _VY_IGNORE, _AX_IGNORE, _AY_IGNORE = (
    int(_F.X_IGNORE), int(_F.Y_IGNORE), int(_F.VX_IGNORE), int(_F.VY_IGNORE), int(_F.AX_IGNORE), int(_F.AY_IGNORE))  # plain ints: IntFlag costs a call per bit


class MockVehicle(LifecycleMixin, TelemetryMixin):
    """The PX4-like vehicle (see module docstring). ``send(msg, port)``: port None = all;
    ``send_batch(msgs, port)``, if given, sends several in order (e.g. in one datagram)."""

    def __init__(
        self,
        cfg: VehicleConfig,
        send: Callable[[Message, object | None], None],
        clock: Callable[[], float] = time.monotonic,
        require_signed: bool = False,
        send_batch: Callable[[list[Message], object | None], None] | None = None,
    ) -> None:
        self.cfg = cfg
        self._send_batch = send_batch   # optional: several messages at once, in order (fewer datagrams)
        self.require_signed = bool(require_signed)
        self._errors_logged: set[tuple[str, str]] = set()
        self._send = send
        self._clock = clock
        self.sysid = cfg.system_id
        self.compid = cfg.component_id
        v = cfg.wind.V_o
        self.params = ParamTable(
            {
                "COM_OF_LOSS_T": cfg.com_of_loss_t_s,
                "MPC_ACC_HOR_MAX": cfg.acc_limit_m_s2,
                "SIM_WIND_C0": cfg.wind.c0_per_s,
                "SIM_WIND_VN": cfg.wind.mean_wind_m_s[0],
                "SIM_WIND_VE": cfg.wind.mean_wind_m_s[1],
                "SIM_WIND_V11": v[0, 0],
                "SIM_WIND_V12": v[0, 1],
                "SIM_WIND_V21": v[1, 0],
                "SIM_WIND_V22": v[1, 1],
                "SIM_ACC_TAU": cfg.acc_lag_s,
                "SIM_ARM_DENY": 1.0 if cfg.deny_arming else 0.0,
                **dict(cfg.params),
            }
        )
        self.plant = SwarmPlant(
            np.array([cfg.initial_pos_m], dtype=float),
            PlantParams(wind=cfg.wind, acc_limit_m_s2=cfg.acc_limit_m_s2, physics_dt_s=cfg.physics_dt_s,
                        acc_lag_s=cfg.acc_lag_s),
            seed=cfg.seed,
            vehicle_ids=np.array([cfg.instance]),
            initial_vel_m_s=None if cfg.initial_vel_m_s is None else np.array([cfg.initial_vel_m_s], dtype=float),
        )
        if cfg.params:
            self._apply_params()          # a SIM_WIND_* or MPC_ACC_HOR_MAX given as a parameter reaches the plant
        self.rejects = RejectLog(log)
        self.frame = LocalFrame(cfg.home_lat_deg, cfg.home_lon_deg, cfg.home_alt_amsl_m, cfg.origin)
        self.armed = False
        self.mode: Px4Mode = PX4_HOLD
        self.flying = False  # False until the first OFFBOARD entry (or takeoff): plant frozen
        self.landed = bool(cfg.start_on_ground)
        self.z_m = 0.0 if self.landed else -float(cfg.altitude_m)      # world z: down from the home's altitude
        self.vz_m_s = 0.0
        self.z_target_m = self.z_m
        self._landed_since_s: float | None = 0.0 if self.landed else None
        self._vert_wall_s = 0.0          # lockstep: wall time the AUTO modes' vertical motion was integrated to
        self._armed_at_s = 0.0           # wall time of the last arming (COM_DISARM_PRFLT)
        self._taken_off_since_arming = False
        self._takeoff_accept_m = self.params["NAV_MC_ALT_RAD"]   # AUTO.TAKEOFF ends within this of its altitude
        if self.landed:
            self.plant.states[0, 2:4] = 0.0
        self.home = self._here()         # (lat, lon, alt, x, y, z local): set at boot and at arming, as PX4
        self._origin_sent = cfg.origin is None
        self.hold_pos_m = np.array(cfg.initial_pos_m, dtype=float)
        self.posctl_path: tuple[float, np.ndarray] | None = None    # Position mode: (t0, setpoint velocities)
        self.setpoint: SetPositionTargetLocalNed | None = None
        self._setpoint_flyable = True    # False: PX4's position controller refuses the held setpoint (stop and wait)
        self.applied_acc_m_s2 = np.zeros(2)
        self._px4_auto: Px4AutoXY | None = None     # hold_model "px4": the auto mode's trajectory and position loop
        self._px4_auto_key: tuple | None = None     # (mode, Hold point) it was activated for
        self._t0 = clock()
        self._phys_t_s = 0.0  # real time: simulated time integrated so far
        self.step_index = 0  # lockstep: control steps taken
        self._dt_ms = int(round(cfg.dt_s * 1000))
        if cfg.lockstep and abs(self._dt_ms - cfg.dt_s * 1000) > 1e-6:
            raise ValueError(f"lockstep dt_s must be a whole number of ms, got {cfg.dt_s}")
        self._last_sp_wall = -math.inf
        self._last_sp_sim_s = 0.0
        self._intervals_s = {k: (1.0 / hz if hz > 0 else math.inf) for k, hz in cfg.rates_hz.items()}
        self._next_due = {k: self._t0 for k in self._intervals_s}
        self._update_telemetry_due()
        self._next_resend = self._t0
        # proximity sensor (docs/proximity.md): set by attach_world
        self._world_report: Callable[[int, np.ndarray], None] | None = None
        self._world_pending_ms: int | None = None   # lockstep: time reported, its sensed set not yet answered
        self._world_reported_at = -math.inf
        self._traffic: tuple[int, list[Message]] | None = None   # (time_boot_ms, ADSB_VEHICLE... + marker)
        self._next_traffic = self._t0
        self._traffic_resend_s = self._traffic_period_s()   # lockstep: idle re-send interval, backs off

    # ------------------------------------------------------------------ clocks
    def wall_s(self) -> float:
        return self._clock() - self._t0

    def sim_time_s(self) -> float:
        """Simulated time: lockstep steps * dt_s, or integrated wall time in real time."""
        return self.step_index * self._dt_ms / 1000.0 if self.cfg.lockstep else self.wall_s()

    def time_boot_ms(self) -> int:
        if self.cfg.lockstep:
            return self.step_index * self._dt_ms
        return int(self.wall_s() * 1000)

    @property
    def state(self) -> np.ndarray:
        """[x_m, y_m, vx_m_s, vy_m_s] (north, east)."""
        return self.plant.states[0]

    # ------------------------------------------------------------------ input
    def handle(self, r: Received, port: object | None = None) -> None:
        """Process one received message; never raises on bad input."""
        msg = r.msg
        try:
            if self.require_signed and not isinstance(msg, BadData) and r.signature != "valid":
                what = msg.MSG_NAME if isinstance(msg, SIGNED_COMMAND_MESSAGES) else "other message"
                self.rejects.reject(f"{r.signature} {what}", f"{msg.MSG_NAME} from {r.src_system}/{r.src_component}")
                return
            if isinstance(msg, SetPositionTargetLocalNed):
                self._on_setpoint(msg, port)
            elif isinstance(msg, CommandLong):
                self._on_command(msg.target_system, msg.target_component, msg.command, msg.params, r, port)
            elif isinstance(msg, CommandInt):
                p = tuple(msg.params) + (float(msg.x), float(msg.y), float(msg.z))
                self._on_command(msg.target_system, msg.target_component, msg.command, p, r, port)
            elif isinstance(msg, SetMode):
                self._on_set_mode_msg(msg)
            elif isinstance(msg, (ParamRequestList, ParamRequestRead, ParamSet)):
                self._on_param(msg, port)
            elif isinstance(msg, BadData):
                self.rejects.reject("bad packet", f"{msg.reason} ({msg.n_bytes} bytes)")
            elif isinstance(msg, UnknownMessage):
                self.rejects.reject("unknown message", f"id {msg.msg_id} ({msg.name}) from {r.src_system}/{r.src_component}")
        except Exception as exc:  # a bug must not kill the vehicle; say so loudly, once per kind
            kind = (type(msg).__name__, type(exc).__name__)
            self.rejects.reject(f"internal error {kind[1]} handling {kind[0]}", str(exc))
            if kind not in self._errors_logged:
                self._errors_logged.add(kind)
                log.exception("error handling %s from %d/%d", type(msg).__name__, r.src_system, r.src_component)

    def _for_me(self, target_system: int, target_component: int) -> bool:
        return target_system in (0, self.sysid) and target_component in (0, self.compid)

    def _on_setpoint(self, sp: SetPositionTargetLocalNed, port: object | None) -> None:
        """PX4's receiver gate drops a setpoint outright; one only its position controller refuses is
        still an offboard heartbeat and is held, flown as "stop and wait" (``setpoint.classify_setpoint``)."""
        verdict = classify_setpoint(sp, self.sysid, self.compid)
        if verdict is not None:
            self.rejects.reject(verdict.kind, verdict.detail)
            if not verdict.keeps_offboard:
                return
        flyable = verdict is None
        if self.cfg.lockstep and self.armed and self.mode == PX4_OFFBOARD:
            if sp.time_boot_ms == self.time_boot_ms():
                self.setpoint, self._setpoint_flyable = sp, flyable
                self._lockstep_step()
            elif self._world_pending_ms is None:  # idempotent retry answer (none while the world has not answered)
                self._send_many(self._traffic_msgs() + [self._local_position()], port)
            return
        self._last_sp_wall = self.wall_s()
        self._last_sp_sim_s = self.sim_time_s()
        self.setpoint, self._setpoint_flyable = sp, flyable

    def _offboard_stream_ok(self) -> bool:
        """PX4's offboard check (commander/HealthAndArmingChecks/checks/offboardCheck.cpp): an offboard
        setpoint arrived within COM_OF_LOSS_T. A timeout, not a stream duration: MAVSDK's
        set_*() then start() at once is accepted."""
        return self.wall_s() - self._last_sp_wall <= self.params["COM_OF_LOSS_T"]

    def _on_command(self, target_system, target_component, command, params, r: Received, port) -> None:
        if not self._for_me(target_system, target_component):
            self.rejects.reject("command for another system", f"command {command} to {target_system}/{target_component}")
            return
        p = [float(x) for x in params] + [0.0] * (7 - len(params))
        result = MavResult.UNSUPPORTED
        after: list[Message] = []
        if command == MavCmd.COMPONENT_ARM_DISARM:
            result = self._arm_disarm(p[0], p[1])
        elif command == MavCmd.DO_SET_MODE:
            if not all(_finite(x) and 0 <= x <= 255 for x in p[:3]) or not (int(p[0]) & MavModeFlag.CUSTOM_MODE_ENABLED):
                result = MavResult.DENIED
            else:
                result = self._request_mode(Px4Mode(int(p[1]), int(p[2])))
        elif command == MavCmd.NAV_LAND:
            result = self._request_mode(PX4_LAND)
        elif command == MavCmd.NAV_TAKEOFF:
            result = self._takeoff(p[6])
        elif command == MavCmd.SET_MESSAGE_INTERVAL:
            result = self._set_interval(p[0], p[1])
        elif command in (MavCmd.REQUEST_MESSAGE, MavCmd.GET_HOME_POSITION, MavCmd.REQUEST_AUTOPILOT_CAPABILITIES):
            msg_id = {MavCmd.GET_HOME_POSITION: _ID["HOME_POSITION"], MavCmd.REQUEST_AUTOPILOT_CAPABILITIES: _ID["AUTOPILOT_VERSION"]}.get(
                command, int(p[0]) if _finite(p[0]) else -1
            )
            m = self._message_by_id(msg_id)
            result = MavResult.ACCEPTED if m is not None else MavResult.DENIED
            after = [m] if m is not None else []
        if result == MavResult.UNSUPPORTED:
            self.rejects.reject("unsupported command", f"command {command} from {r.src_system}/{r.src_component}")
        self._send(CommandAck(int(command), int(result), r.src_system, r.src_component), port)
        for m in after:
            self._send(m, port)

    def _set_interval(self, msg_id_f: float, interval_us: float) -> MavResult:
        if not _finite(msg_id_f, interval_us):
            return MavResult.DENIED
        kind = TELEMETRY_IDS.get(int(msg_id_f))
        if kind is None:
            return MavResult.DENIED
        if interval_us < 0:
            self._intervals_s[kind] = math.inf
        elif interval_us == 0:
            hz = VehicleConfig().rates_hz[kind]
            self._intervals_s[kind] = 1.0 / hz
        else:
            self._intervals_s[kind] = max(interval_us * 1e-6, 1e-3)
        self._next_due[kind] = self._clock()
        self._update_telemetry_due()
        return MavResult.ACCEPTED

    def _on_param(self, m, port) -> None:
        if not self._for_me(m.target_system, m.target_component):
            return
        if isinstance(m, ParamRequestList):
            for name in self.params.names:
                self._send(self._param_value(name), port)
        elif isinstance(m, ParamRequestRead):
            if m.param_index >= 0:
                name = self.params.names[m.param_index] if m.param_index < len(self.params.names) else None
            else:
                name = m.param_id if m.param_id in self.params.values else None
            if name is None:
                self.rejects.reject("unknown parameter", f"{m.param_id!r} / index {m.param_index}")
                return
            self._send(self._param_value(name), port)
        elif isinstance(m, ParamSet):
            err = self.params.set(m.param_id, m.value)
            if err is not None:
                self.rejects.reject("PARAM_SET refused", err)
                if m.param_id not in self.params.values:
                    return
            else:
                log.info("param %s = %g", m.param_id, m.value)
                self._apply_params()
            self._send(self._param_value(m.param_id), None)

    def _param_value(self, name: str) -> ParamValue:
        return ParamValue(name, self.params[name], MavParamType.REAL32, len(self.params.names), self.params.index(name))

    def _apply_params(self) -> None:
        p = self.params
        wind = WindParams(
            c0_per_s=p["SIM_WIND_C0"],
            mean_wind_m_s=(p["SIM_WIND_VN"], p["SIM_WIND_VE"]),
            wind_diffusion_m_s=((p["SIM_WIND_V11"], p["SIM_WIND_V12"]), (p["SIM_WIND_V21"], p["SIM_WIND_V22"])),
        )
        self.plant.params = PlantParams(wind=wind, acc_limit_m_s2=p["MPC_ACC_HOR_MAX"], physics_dt_s=self.cfg.physics_dt_s,
                                        acc_lag_s=p["SIM_ACC_TAU"])

    # ------------------------------------------------------------------ dynamics
    def _setpoint_acc_m_s2(self) -> np.ndarray:
        """Horizontal acceleration the held setpoint asks for (float32 from the wire, as
        float64). Acceleration is used as is (feed-forward); velocity and position
        setpoints (masks PX4 also accepts) go through a PD like PX4's position loop.
        (Per axis on Python floats: the same IEEE operations in the same order as the
        elementwise numpy formula acc_sp + (where(use_pos, 1.0 (pos_sp - r), 0) + 2.0 (vel_sp - v)),
        a field the mask ignores counting as 0.)"""
        sp = self.setpoint
        if sp is None:
            return np.zeros(2)
        m = sp.type_mask
        afx, afy, vx_sp, vy_sp, x_sp, y_sp = (float(sp.afx_m_s2), float(sp.afy_m_s2), float(sp.vx_m_s), float(sp.vy_m_s),
                                              float(sp.x_m), float(sp.y_m))
        acc_x = 0.0 if m & _AX_IGNORE else afx
        acc_y = 0.0 if m & _AY_IGNORE else afy
        use_vx, use_vy = not m & _VX_IGNORE, not m & _VY_IGNORE
        use_px, use_py = not m & _X_IGNORE, not m & _Y_IGNORE
        vel_x = vx_sp if use_vx else 0.0
        vel_y = vy_sp if use_vy else 0.0
        x, y, vx, vy = self.plant.states[0].tolist()
        if use_px or use_py:
            acc_x = acc_x + ((1.0 * (x_sp - x) if use_px else 0.0) + 2.0 * (vel_x - vx))
            acc_y = acc_y + ((1.0 * (y_sp - y) if use_py else 0.0) + 2.0 * (vel_y - vy))
        elif use_vx or use_vy:
            acc_x = acc_x + 2.0 * (vel_x - vx)
            acc_y = acc_y + 2.0 * (vel_y - vy)
        # sp.coordinate_frame BODY_NED: yaw is held at 0 (north), so body and local NED coincide
        if self.cfg.origin is not None:
            acc_x, acc_y = self.frame.local_vec_to_world(acc_x, acc_y)
        return np.array([acc_x, acc_y])

    def _current_acc_m_s2(self) -> np.ndarray:
        if self.mode == PX4_OFFBOARD:
            if not self._setpoint_flyable:        # PX4's "stop and wait": velocity setpoint 0 (the PD's velocity gain)
                return -2.0 * self.plant.states[:, 2:4]
            return self._setpoint_acc_m_s2().reshape(1, 2)
        if self.mode == PX4_POSCTL and self.posctl_path is not None:
            # Position mode: PX4's velocity controller follows the braking velocity setpoint (lifecycle,
            # plant.position_brake_path_m) with its acceleration fed forward, within the airframe's limit; once the
            # setpoint is zero the position locks where the vehicle is then (StickAccelerationXY::lockPosition), and a
            # vehicle that lagged behind the setpoint flies back to it, as PX4's does
            t0, vs = self.posctl_path
            k = int((self.sim_time_s() - t0) / POSCTL_DT_S)
            if k < vs.shape[0] - 1:
                k = max(k, 0)
                a_ref = (vs[k + 1] - vs[k]) / POSCTL_DT_S
                acc = a_ref + 2.0 * (vs[k] - self.plant.states[0, 2:4])
                return saturate_norm(acc.reshape(1, 2), self.plant.params.acc_limit_m_s2)
            self.hold_pos_m = self.plant.states[0, 0:2].copy()
            self.posctl_path = None
        return hold_acc_m_s2(self.plant.states, self.hold_pos_m.reshape(1, 2), self.plant.params.acc_limit_m_s2)

    def _moving(self) -> bool:
        return self.flying and self.armed and not self.landed

    AUTO_MODES = (PX4_TAKEOFF, PX4_HOLD, PX4_LAND)
    """PX4 flies these with ``FlightTaskAuto``, whose setpoints come from the jerk-limited ``PositionSmoothing``."""

    def _step(self, dt_s: float) -> None:
        """Advance the horizontal plant by ``dt_s`` (in an auto mode sub-step by sub-step: with ``hold_model`` "pd" the
        acceleration jerk-limited from the one flown before, ``plant.jerk_limited_m_s2``; with "px4" PX4's trajectory
        and position loop, ``smoothing.Px4AutoXY``), then the altitude loop."""
        if self.mode in self.AUTO_MODES:
            jerk, k = self.params["MPC_JERK_AUTO"], self.plant.params.substeps(dt_s)
            for _ in range(k):
                self._step_horizontal(dt_s / k, jerk)
        else:
            self._px4_auto_key = None
            self._step_horizontal(dt_s, None)
        self._vertical(dt_s)

    def _px4_auto_acc_m_s2(self, dt_s: float) -> np.ndarray:
        """hold_model "px4": the auto mode's acceleration over the next ``dt_s`` (1, 2). PX4 constructs a new flight
        task at the mode switch and activates it from the last setpoint (``FlightTaskAuto::activate``): here when the
        mode or its Hold point changes (a lift-off re-activates it, as ``reActivate`` does on the ground), from the
        state and the acceleration flown until then; the last setpoint's position and velocity count as NaN (the
        controller's offboard setpoints are accelerations), so the vehicle's are used."""
        key = (self.mode, self.hold_pos_m.tobytes())
        if self._px4_auto is None or self._px4_auto_key != key:
            params = AutoParams(mpc_jerk_auto_m_s3=self.params["MPC_JERK_AUTO"], mpc_acc_hor_m_s2=self.params["MPC_ACC_HOR"])
            self._px4_auto = Px4AutoXY(params)
            self._px4_auto.activate(self.plant.states[0], self.hold_pos_m, self.applied_acc_m_s2)
            self._px4_auto_key = key
        return self._px4_auto.acc_m_s2(self.plant.states[0], dt_s, self.plant.params.acc_limit_m_s2).reshape(1, 2)

    def _step_horizontal(self, dt_s: float, jerk_m_s3: float | None) -> None:
        px4_auto = jerk_m_s3 is not None and self.cfg.hold_model == "px4"
        acc = self._px4_auto_acc_m_s2(dt_s) if px4_auto else self._current_acc_m_s2()
        if not np.isfinite(acc).all():
            self.rejects.reject("non-finite acceleration", f"{acc}: holding instead")
            acc = hold_acc_m_s2(self.plant.states, self.hold_pos_m.reshape(1, 2), self.plant.params.acc_limit_m_s2)
        if jerk_m_s3 is not None and not px4_auto:
            acc = jerk_limited_m_s2(self.applied_acc_m_s2.reshape(1, 2), acc, jerk_m_s3, dt_s)
        before = self.plant.states.copy()
        self.applied_acc_m_s2 = self.plant.step(acc, dt_s)[0]
        if not np.isfinite(self.plant.states).all():
            self.rejects.reject("non-finite plant state", "restoring the previous state")
            self.plant.states = before

    def _lockstep_step(self) -> None:
        """Lockstep: one control step of dt_s with the setpoint just received, then telemetry.
        With a world, the telemetry waits for the world's answer (``on_world_answer``)."""
        self._step(self._dt_ms / 1000.0)
        self.step_index += 1
        self._last_sp_sim_s = self.sim_time_s()
        self._stepped_now()
        if self._world_report is not None:
            self._report_to_world()
            return
        self._send_many(self._fast_telemetry(), None)

    def _resend_allowed(self) -> bool:
        """Lockstep: the current position may be re-sent unless a step's telemetry waits for
        the world's answer (t = 0, the frozen initial state, may always be re-sent)."""
        return self._world_pending_ms is None or self._world_pending_ms == 0

    def _stepped_now(self) -> None:
        """Lockstep: a step just happened, so its telemetry (and traffic set) goes out now: the
        wall-clock re-sends are only for a vehicle that is idle (docs/lockstep.md)."""
        now = self._clock()
        if self.cfg.lockstep_resend_hz > 0:
            self._next_resend = now + 1.0 / self.cfg.lockstep_resend_hz
        self._traffic_resend_s = self._traffic_period_s()
        self._next_traffic = now + self._traffic_resend_s

    def _traffic_period_s(self) -> float:
        return 1.0 / self.cfg.traffic_rate_hz if self.cfg.traffic_rate_hz > 0 else math.inf

    # ------------------------------------------------------------------ proximity sensor (docs/proximity.md)
    WORLD_RETRY_S = 0.5
    LOCKSTEP_TRAFFIC_RESEND_MAX_S = 2.0
    """Lockstep: an idle vehicle re-sends its current traffic set at ``traffic_rate_hz``, the
    interval doubling up to this (a set is up to N ADSB_VEHICLE messages; a swarm waiting
    minutes for its slowest member must not fill every tlog with copies)."""

    def attach_world(self, report: Callable[[int, np.ndarray], None]) -> None:
        """Give the vehicle a proximity sensor: ``report(time_boot_ms, state_f32 (4,))`` sends
        its true state to the world; the world's answers come back through ``on_world_answer``."""
        self._world_report = report
        if self.cfg.lockstep:
            self._report_to_world()

    def _report_to_world(self) -> None:
        t = self.time_boot_ms()
        if self.cfg.lockstep:
            self._world_pending_ms = t
        self._world_reported_at = self._clock()
        self._world_report(t, np.asarray(self.state, dtype=np.float32))  # type: ignore[misc]

    def on_world_answer(self, time_boot_ms: int, ids: np.ndarray, states: np.ndarray) -> None:
        """The vehicles sensed at ``time_boot_ms``: send them as ADSB_VEHICLE plus the marker
        (lockstep: only the answer to the pending step, followed by that step's telemetry)."""
        if self.cfg.lockstep and time_boot_ms != self._world_pending_ms:
            return  # a duplicate or stale answer
        msgs: list[Message] = list(traffic_reports(ids, states, time_boot_ms, (self.cfg.home_lat_deg, self.cfg.home_lon_deg),
                                                   self.cfg.home_alt_amsl_m + self.cfg.altitude_m))
        msgs.append(NamedValueInt(time_boot_ms & 0xFFFFFFFF, TRAFFIC_MARKER_NAME, len(msgs)))
        self._traffic = (time_boot_ms, msgs)
        if self.cfg.lockstep:
            self._stepped_now()
            self._world_pending_ms = None
            self._send_many(msgs + self._fast_telemetry(), None)   # the set, its marker, then the step's telemetry
        else:
            self._send_many(msgs, None)

    def _traffic_msgs(self) -> list[Message]:
        return [] if self._traffic is None else list(self._traffic[1])

    def _send_traffic(self, port: object | None) -> None:
        self._send_many(self._traffic_msgs(), port)

    def _send_many(self, msgs: list[Message], port: object | None) -> None:
        """Send ``msgs`` in order; the I/O loop may pack them into few datagrams (PX4 also
        fills a UDP datagram with several MAVLink packets)."""
        if self._send_batch is not None:
            self._send_batch(msgs, port)
        else:
            for m in msgs:
                self._send(m, port)

    def _world_tick(self, now: float) -> None:
        if self._world_report is None:
            return
        if self.cfg.lockstep:
            if self._world_pending_ms is not None and now - self._world_reported_at > self.WORLD_RETRY_S:
                self._report_to_world()  # no answer yet: the world answers duplicates again
            elif self._world_pending_ms is None and self.cfg.traffic_rate_hz > 0 and now >= self._next_traffic:
                # idle (no step for a while): re-send the current set, a controller may have missed it
                self._traffic_resend_s = min(2.0 * self._traffic_resend_s, max(self.LOCKSTEP_TRAFFIC_RESEND_MAX_S, self._traffic_period_s()))
                self._next_traffic = now + self._traffic_resend_s
                self._send_traffic(None)
        elif self.cfg.traffic_rate_hz > 0 and now >= self._next_traffic:
            self._next_traffic = now + 1.0 / self.cfg.traffic_rate_hz
            self._report_to_world()

    def tick(self) -> None:
        """Advance the clocks: real-time physics, failsafe, periodic telemetry."""
        now = self._clock()
        self._offboard_loss_tick()
        self._ground_tick()
        if not self._origin_sent:
            self._origin_sent = True
            self._send(self._origin_msg(), None)          # PX4 announces its EKF origin when it is set
        if not self.cfg.lockstep:
            elapsed = self.wall_s()
            h = self.cfg.physics_dt_s
            n = 0
            while self._phys_t_s + h <= elapsed:
                if self._moving():
                    self._step(h)
                self._phys_t_s += h
                n += 1
                if n > 200:
                    log.warning("physics fell %.2f s behind the wall clock; skipping ahead", elapsed - self._phys_t_s)
                    self._phys_t_s = elapsed
                    break
        self._periodic(now)

    def _update_telemetry_due(self) -> None:
        """``_telemetry_due``: when the next periodic telemetry message is due (the earliest
        ``_next_due`` of the kinds ``_periodic`` sends on their own clock), kept up to date
        wherever ``_next_due`` or ``_intervals_s`` change, so an idle tick costs one comparison."""
        lockstep = self.cfg.lockstep
        self._telemetry_due = min((self._next_due[k] for k, iv in self._intervals_s.items()
                                   if iv != math.inf and not (lockstep and k in FAST_TELEMETRY)), default=math.inf)

    def _periodic(self, now: float) -> None:
        lockstep = self.cfg.lockstep
        if now >= self._telemetry_due:
            for kind, interval in self._intervals_s.items():
                if interval == math.inf or now < self._next_due[kind]:
                    continue
                if lockstep and kind in FAST_TELEMETRY:
                    continue  # in lockstep these follow the steps (plus the slow re-send below)
                self._next_due[kind] = max(self._next_due[kind] + interval, now - interval)
                self._send(self._telemetry(kind), None)
            self._update_telemetry_due()
        self._world_tick(now)
        if lockstep and self._resend_allowed() and self.cfg.lockstep_resend_hz > 0 and now >= self._next_resend:
            self._next_resend = now + 1.0 / self.cfg.lockstep_resend_hz
            self._send_many(self._fast_telemetry(), None)

    def next_deadline(self) -> float:
        """Monotonic time of the next periodic event (for the I/O loop's select timeout): the
        loop sleeps until then or until a packet arrives, so an idle or lockstep vehicle does not
        spin. Every event ``tick`` acts on has its deadline here."""
        t = self._telemetry_due
        if not self.cfg.lockstep:
            t = min(t, self._t0 + self._phys_t_s + self.cfg.physics_dt_s)
            if self.mode == PX4_OFFBOARD:  # the offboard-loss failsafe, on time
                t = min(t, self._t0 + self._last_sp_sim_s + self.params["COM_OF_LOSS_T"] + 1e-4)
        if self.cfg.lockstep and self._resend_allowed() and self.cfg.lockstep_resend_hz > 0:
            t = min(t, self._next_resend)
        if self.cfg.lockstep and self._auto_vertical_pending():
            t = min(t, self._t0 + self._vert_wall_s + self.cfg.physics_dt_s)   # the AUTO modes' climb or descent, on time
        if self._world_report is not None:
            if self.cfg.lockstep and self._world_pending_ms is not None:
                t = min(t, self._world_reported_at + self.WORLD_RETRY_S)
            elif self.cfg.traffic_rate_hz > 0:
                t = min(t, self._next_traffic)
        return t
