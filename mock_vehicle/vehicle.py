"""A PX4-like vehicle: mode machine, setpoint filter, failsafe, telemetry and parameters
around the eq. 9 plant (issue 3; SPEC section 4). No sockets here: ``MockVehicle.handle``
takes a decoded message, ``MockVehicle.tick`` advances the clocks; both send through the
``send(msg, port)`` callback given at construction (``port=None`` means every port).

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
Hold (``hold_acc_m_s2`` around where it began).

Ground start (``start_on_ground``, issue 19): the vehicle boots ON_GROUND, disarmed, at its launch
point, and does what PX4 does: arm; MAV_CMD_NAV_TAKEOFF climbs at MPC_TKO_SPEED to the commanded
altitude (or MIS_TAKEOFF_ALT) in AUTO.TAKEOFF, then holds in AUTO.LOITER; OFFBOARD from the ground
leaves it only when the setpoint asks to climb (a z position above, or vz < 0); MAV_CMD_NAV_LAND
descends at MPC_LAND_SPEED, touches down and disarms COM_DISARM_LAND later. EXTENDED_SYS_STATE
reports ON_GROUND -> TAKEOFF -> IN_AIR -> LANDING -> ON_GROUND.

Altitude: a setpoint with a z position (type_mask 3387: z + ax, ay) is tracked like PX4's
altitude loop (vz = clip(z_sp - z, -MPC_Z_VEL_MAX_UP, MPC_Z_VEL_MAX_DN)); Hold keeps the altitude it
began at; an acceleration-only setpoint (3135) keeps the altitude constant (a real PX4 would hover
on its thrust estimate and drift slowly: docs/mavlink.md). In lockstep the vertical manoeuvres
of the AUTO modes (takeoff, land) run on the wall clock with the horizontal plant frozen, since
lockstep time advances only with OFFBOARD setpoints.

Frames (``geo.LocalFrame``): the plant flies in the world frame (the tangent plane at the home);
with ``origin`` (its EKF origin, issue 19) the vehicle reports LOCAL_POSITION_NED relative to it,
GLOBAL_POSITION_INT and HOME_POSITION in WGS84 (pymap3d), and GPS_GLOBAL_ORIGIN at boot and on
request, as a real PX4 does.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from mavlink_bridge import (
    PX4_HOLD,
    PX4_LAND,
    PX4_OFFBOARD,
    PX4_POSCTL,
    PX4_TAKEOFF,
    Attitude,
    AutopilotVersion,
    BadData,
    CommandAck,
    CommandInt,
    CommandLong,
    ExtendedSysState,
    GlobalPositionInt,
    GpsGlobalOrigin,
    Heartbeat,
    HomePosition,
    LocalPositionNed,
    MavAutopilot,
    NamedValueInt,
    MavCmd,
    MavFrame,
    MavLandedState,
    MavModeFlag,
    MavParamType,
    MavResult,
    MavSeverity,
    MavState,
    MavType,
    Message,
    ParamRequestList,
    ParamRequestRead,
    ParamSet,
    ParamValue,
    PositionTargetTypeMask,
    Px4MainMode,
    Px4Mode,
    Received,
    SetMode,
    SetPositionTargetLocalNed,
    StatusText,
    SysStatus,
    UnknownMessage,
)
from mavlink_bridge import MSG_ID_BY_NAME
from mavlink_bridge.ratelog import RejectLog

from mavlink_bridge.adsb import TRAFFIC_MARKER_NAME

from .geo import LocalFrame
from .params import ParamTable
from .plant import PlantParams, SwarmPlant, WindParams, hold_acc_m_s2
from .proximity import traffic_reports

__all__ = ["VehicleConfig", "MockVehicle", "RejectLog", "check_setpoint", "SETPOINT_LIMITS", "SIGNED_COMMAND_MESSAGES"]

log = logging.getLogger("mock_vehicle")

EARTH_RADIUS_M = 6_378_137.0
GRAVITY_M_S2 = 9.80665
HOLD_LIKE = (PX4_HOLD, PX4_POSCTL)
Z_GAIN_PER_S = 1.0              # altitude loop: vz = clip(Z_GAIN (z_sp - z), ...), like MPC_Z_P's default
TAKEOFF_DONE_M = 0.05           # AUTO.TAKEOFF is over within this of its altitude
LIFTOFF_M = 0.1                 # OFFBOARD from the ground: a z setpoint this far above the ground lifts off
CAPABILITIES = 2 | 8 | 128 | 8192  # PARAM_FLOAT | COMMAND_INT | SET_POSITION_TARGET_LOCAL_NED | MAVLINK2

SETPOINT_LIMITS = {"position_m": 1.0e5, "velocity_m_s": 100.0, "acceleration_m_s2": 100.0, "yaw_rad": 100.0, "yaw_rate_rad_s": 100.0}
"""Largest magnitude of a used SET_POSITION_TARGET_LOCAL_NED field; beyond it the setpoint
is rejected ("setpoint out of range") before it can reach the plant. (The plant also
saturates the acceleration at MPC_ACC_HOR_MAX.)"""

SIGNED_COMMAND_MESSAGES = (CommandLong, CommandInt, SetMode, SetPositionTargetLocalNed, ParamSet)
"""Messages that command the vehicle; with signing on, each has its own rejection kind."""

_ID = MSG_ID_BY_NAME
FAST_TELEMETRY = ("local_position", "attitude", "global_position")
"""In lockstep these follow the steps (plus ``lockstep_resend_hz`` re-sends while idle)
instead of their wall-clock rates: between steps the state does not change."""
TELEMETRY_IDS = {
    _ID["HEARTBEAT"]: "heartbeat",
    _ID["SYS_STATUS"]: "sys_status",
    _ID["ATTITUDE"]: "attitude",
    _ID["LOCAL_POSITION_NED"]: "local_position",
    _ID["GLOBAL_POSITION_INT"]: "global_position",
    _ID["HOME_POSITION"]: "home_position",
    _ID["EXTENDED_SYS_STATE"]: "extended_sys_state",
}


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
    dt_s: float = 1.0
    lockstep: bool = False
    com_of_loss_t_s: float = 1.0
    deny_arming: bool = False
    start_on_ground: bool = False                          # boot ON_GROUND, disarmed, at initial_pos_m (z = 0)
    origin: tuple[float, float, float] | None = None       # EKF origin (lat_deg, lon_deg, alt_amsl_m); None: the home
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

    @property
    def system_id(self) -> int:
        return self.instance + 1

    @property
    def component_id(self) -> int:
        return 1


def _finite(*xs: float) -> bool:
    return all(math.isfinite(x) for x in xs)


_F = PositionTargetTypeMask
_FORCE_SET = int(_F.FORCE_SET)          # the mask bits as plain ints: IntFlag arithmetic costs a Python call per bit
_POSITION_IGNORE, _VELOCITY_IGNORE, _ACCELERATION_IGNORE = int(_F.POSITION_IGNORE), int(_F.VELOCITY_IGNORE), int(_F.ACCELERATION_IGNORE)
_X_IGNORE, _Y_IGNORE, _VX_IGNORE, _VY_IGNORE, _AX_IGNORE, _AY_IGNORE = (
    int(_F.X_IGNORE), int(_F.Y_IGNORE), int(_F.VX_IGNORE), int(_F.VY_IGNORE), int(_F.AX_IGNORE), int(_F.AY_IGNORE))
_SETPOINT_FIELDS = (
    (_X_IGNORE, "x_m", "position_m"), (_Y_IGNORE, "y_m", "position_m"), (int(_F.Z_IGNORE), "z_m", "position_m"),
    (_VX_IGNORE, "vx_m_s", "velocity_m_s"), (_VY_IGNORE, "vy_m_s", "velocity_m_s"), (int(_F.VZ_IGNORE), "vz_m_s", "velocity_m_s"),
    (_AX_IGNORE, "afx_m_s2", "acceleration_m_s2"), (_AY_IGNORE, "afy_m_s2", "acceleration_m_s2"),
    (int(_F.AZ_IGNORE), "afz_m_s2", "acceleration_m_s2"),
    (int(_F.YAW_IGNORE), "yaw_rad", "yaw_rad"), (int(_F.YAW_RATE_IGNORE), "yaw_rate_rad_s", "yaw_rate_rad_s"),
)  # fmt: skip
"""(ignore bit, field, SETPOINT_LIMITS key) of every field a mask can use."""


def check_setpoint(sp: SetPositionTargetLocalNed, system_id: int, component_id: int) -> tuple[str, str] | None:
    """PX4's filter for SET_POSITION_TARGET_LOCAL_NED (SPEC 4). Returns None if usable, or
    (kind, detail) of the rejection: wrong target, frame other than LOCAL_NED/BODY_NED,
    FORCE_SET bit, a mask ignoring position, velocity and acceleration alike, or a
    non-finite value in a field the mask uses."""
    if sp.target_system not in (0, system_id):
        return "setpoint wrong target system", f"target_system {sp.target_system}, this vehicle is {system_id}"
    if sp.target_component not in (0, component_id):
        return "setpoint wrong target component", f"target_component {sp.target_component}"
    if sp.coordinate_frame not in (MavFrame.LOCAL_NED, MavFrame.BODY_NED):
        return "setpoint unsupported frame", f"coordinate_frame {sp.coordinate_frame} (LOCAL_NED=1 or BODY_NED=8 only)"
    mask = sp.type_mask
    if mask & _FORCE_SET:
        return "setpoint FORCE_SET bit", f"type_mask {mask:#06x}"
    use_pos = (mask & _POSITION_IGNORE) != _POSITION_IGNORE
    use_vel = (mask & _VELOCITY_IGNORE) != _VELOCITY_IGNORE
    use_acc = (mask & _ACCELERATION_IGNORE) != _ACCELERATION_IGNORE
    if not (use_pos or use_vel or use_acc):
        return "setpoint ignores everything", f"type_mask {mask:#06x} ignores position, velocity and acceleration"
    L = SETPOINT_LIMITS
    used = [(getattr(sp, name), L[key]) for bit, name, key in _SETPOINT_FIELDS if not mask & bit]
    if not _finite(*(v for v, _ in used)):
        return "setpoint non-finite field", f"NaN/inf in a used field (type_mask {mask:#06x})"
    if any(abs(v) > limit for v, limit in used):
        return "setpoint out of range", f"a used field beyond its limit {SETPOINT_LIMITS} (type_mask {mask:#06x})"
    return None


class MockVehicle:
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
                "SIM_ARM_DENY": 1.0 if cfg.deny_arming else 0.0,
            }
        )
        self.plant = SwarmPlant(
            np.array([cfg.initial_pos_m], dtype=float),
            PlantParams(wind=cfg.wind, acc_limit_m_s2=cfg.acc_limit_m_s2, physics_dt_s=cfg.physics_dt_s),
            seed=cfg.seed,
            vehicle_ids=np.array([cfg.instance]),
            initial_vel_m_s=None if cfg.initial_vel_m_s is None else np.array([cfg.initial_vel_m_s], dtype=float),
        )
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
        if self.landed:
            self.plant.states[0, 2:4] = 0.0
        self.home = self._here()         # (lat, lon, alt, x, y, z local): set at boot and at arming, as PX4
        self._origin_sent = cfg.origin is None
        self.hold_pos_m = np.array(cfg.initial_pos_m, dtype=float)
        self.setpoint: SetPositionTargetLocalNed | None = None
        self.applied_acc_m_s2 = np.zeros(2)
        self._t0 = clock()
        self._phys_t_s = 0.0  # real time: simulated time integrated so far
        self.step_index = 0  # lockstep: control steps taken
        self._dt_ms = int(round(cfg.dt_s * 1000))
        if cfg.lockstep and abs(self._dt_ms - cfg.dt_s * 1000) > 1e-6:
            raise ValueError(f"lockstep dt_s must be a whole number of ms, got {cfg.dt_s}")
        self._stream_start_wall: float | None = None
        self._last_sp_wall = -math.inf
        self._last_sp_sim_s = 0.0
        self._intervals_s = {k: (1.0 / hz if hz > 0 else math.inf) for k, hz in cfg.rates_hz.items()}
        self._next_due = {k: self._t0 for k in self._intervals_s}
        self._update_telemetry_due()
        self._next_resend = self._t0
        self.n_steps_failsafe = 0
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
        bad = check_setpoint(sp, self.sysid, self.compid)
        if bad is not None:
            self.rejects.reject(*bad)
            return
        if self.cfg.lockstep and self.armed and self.mode == PX4_OFFBOARD:
            if sp.time_boot_ms == self.time_boot_ms():
                self.setpoint = sp
                self._lockstep_step()
            elif self._world_pending_ms is None:  # idempotent retry answer (none while the world has not answered)
                self._send_many(self._traffic_msgs() + [self._local_position()], port)
            return
        self._last_sp_wall = self.wall_s()
        self._last_sp_sim_s = self.sim_time_s()
        self.setpoint = sp

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

    def _arm_disarm(self, p1: float, p2: float) -> MavResult:
        if p1 == 1.0:
            if self.params["SIM_ARM_DENY"] >= 0.5 and p2 != 21196.0:
                self._statustext(MavSeverity.CRITICAL, "Preflight Fail: SIM_ARM_DENY set")
                self.rejects.reject("arming denied", "SIM_ARM_DENY set")
                return MavResult.DENIED
            if not self.armed:
                self.armed = True
                self.home = self._here()          # PX4 sets home where it arms
                self._landed_since_s = None       # COM_DISARM_LAND counts from a touchdown, not from arming
                log.info("armed")
                self._send_heartbeat()
            return MavResult.ACCEPTED
        if p1 == 0.0:
            if self.armed:
                self.armed = False
                log.info("disarmed")
                self._send_heartbeat()
            return MavResult.ACCEPTED
        return MavResult.DENIED

    def _takeoff(self, alt_amsl_m: float) -> MavResult:
        """MAV_CMD_NAV_TAKEOFF: climb at MPC_TKO_SPEED to ``alt_amsl_m`` (NaN: MIS_TAKEOFF_ALT above
        home) in AUTO.TAKEOFF, then AUTO.LOITER. Denied while disarmed (PX4 needs an armed vehicle)."""
        if not self.armed:
            self._statustext(MavSeverity.CRITICAL, "Takeoff denied! Please arm first")
            self.rejects.reject("takeoff denied", "vehicle disarmed")
            return MavResult.DENIED
        home_alt = self.home[2]
        agl = alt_amsl_m - home_alt if math.isfinite(alt_amsl_m) else self.params["MIS_TAKEOFF_ALT"]
        if not (0.0 < agl <= 1000.0):
            self.rejects.reject("takeoff denied", f"takeoff altitude {agl:.1f} m above home out of (0, 1000]")
            return MavResult.DENIED
        self.z_target_m = self.frame.local_z_to_world(self.home[5]) - agl
        self._lift_off()
        self._set_mode(PX4_TAKEOFF, reason="takeoff command")
        return MavResult.ACCEPTED

    def _lift_off(self) -> None:
        if self.landed:
            self.landed = False
            self._landed_since_s = None
            self.plant.states[0, 2:4] = 0.0
            self.hold_pos_m = self.state[0:2].copy()
            log.info("lift-off")
        self.flying = True
        self._vert_wall_s = self.wall_s()

    def _request_mode(self, mode: Px4Mode) -> MavResult:
        if mode.main_mode == Px4MainMode.OFFBOARD:
            mode = PX4_OFFBOARD
            if self.mode != PX4_OFFBOARD and not self._offboard_stream_ok():
                self._statustext(MavSeverity.CRITICAL, "Switching to Offboard is currently not available")
                self.rejects.reject("OFFBOARD refused", f"no offboard setpoint within COM_OF_LOSS_T = {self.params['COM_OF_LOSS_T']:g} s")
                return MavResult.TEMPORARILY_REJECTED
        elif mode == PX4_TAKEOFF:
            return self._takeoff(math.nan)
        elif mode.main_mode == Px4MainMode.AUTO and mode.sub_mode in (0, PX4_HOLD.sub_mode):
            mode = PX4_HOLD
        elif mode not in (PX4_LAND, PX4_POSCTL):
            self.rejects.reject("unsupported mode", f"mode {mode} not supported by the mock")
            return MavResult.TEMPORARILY_REJECTED
        self._set_mode(mode, reason="commanded")
        return MavResult.ACCEPTED

    def _set_mode(self, mode: Px4Mode, reason: str) -> None:
        if mode == self.mode:
            return
        log.info("mode %s -> %s (%s)", self.mode, mode, reason)
        self.mode = mode
        if mode == PX4_OFFBOARD:
            if not self.landed:
                self.flying = True
            self._last_sp_sim_s = self.sim_time_s()
        elif mode in HOLD_LIKE or mode == PX4_LAND:
            self.hold_pos_m = self.state[0:2].copy()
            self.z_target_m = self.z_m
        self._vert_wall_s = self.wall_s()
        self._send_heartbeat()

    def _on_set_mode_msg(self, m: SetMode) -> None:
        if m.target_system not in (0, self.sysid):
            self.rejects.reject("SET_MODE for another system", f"target_system {m.target_system}")
            return
        if not m.base_mode & MavModeFlag.CUSTOM_MODE_ENABLED:
            self.rejects.reject("SET_MODE without custom mode", f"base_mode {m.base_mode}")
            return
        self._request_mode(Px4Mode.from_custom_mode(m.custom_mode))

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
        self.plant.params = PlantParams(wind=wind, acc_limit_m_s2=p["MPC_ACC_HOR_MAX"], physics_dt_s=self.cfg.physics_dt_s)

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
            return self._setpoint_acc_m_s2().reshape(1, 2)
        return hold_acc_m_s2(self.plant.states, self.hold_pos_m.reshape(1, 2), self.plant.params.acc_limit_m_s2)

    def _moving(self) -> bool:
        return self.flying and self.armed and not self.landed

    def _step(self, dt_s: float) -> None:
        acc = self._current_acc_m_s2()
        if not np.isfinite(acc).all():
            self.rejects.reject("non-finite acceleration", f"{acc}: holding instead")
            acc = hold_acc_m_s2(self.plant.states, self.hold_pos_m.reshape(1, 2), self.plant.params.acc_limit_m_s2)
        before = self.plant.states.copy()
        self.applied_acc_m_s2 = self.plant.step(acc, dt_s)[0]
        if not np.isfinite(self.plant.states).all():
            self.rejects.reject("non-finite plant state", "restoring the previous state")
            self.plant.states = before
        self._vertical(dt_s)

    # ------------------------------------------------------------------ altitude and the ground
    def _z_setpoint_world(self) -> tuple[float | None, float | None]:
        """(z, vz) the OFFBOARD setpoint asks for in the world frame, None where the mask ignores it."""
        sp = self.setpoint
        if sp is None:
            return None, None
        m = sp.type_mask
        z = None if m & int(_F.Z_IGNORE) else self.frame.local_z_to_world(float(sp.z_m))
        vz = None if m & int(_F.VZ_IGNORE) else float(sp.vz_m_s)
        return z, vz

    def _vertical(self, dt_s: float) -> None:
        """z over dt_s in the current mode (module docstring); touchdown, takeoff completion."""
        p = self.params
        up, dn = p["MPC_Z_VEL_MAX_UP"], p["MPC_Z_VEL_MAX_DN"]
        vz = 0.0
        if self.mode == PX4_LAND:
            vz = p["MPC_LAND_SPEED"]
        elif self.mode == PX4_TAKEOFF:
            vz = -min(p["MPC_TKO_SPEED"], max(0.0, self.z_m - self.z_target_m) / dt_s)
        elif self.mode == PX4_OFFBOARD:
            z_sp, vz_sp = self._z_setpoint_world()
            if z_sp is not None:
                vz = min(max(Z_GAIN_PER_S * (z_sp - self.z_m) + (vz_sp or 0.0), -up), dn)
            elif vz_sp is not None:
                vz = min(max(vz_sp, -up), dn)
        elif self.mode in HOLD_LIKE:
            vz = min(max(Z_GAIN_PER_S * (self.z_target_m - self.z_m), -up), dn)
        if self.landed:
            vz = 0.0                                # on the ground until a takeoff or a climbing setpoint lifts it off
        self.vz_m_s = vz
        self.z_m = min(0.0, self.z_m + vz * dt_s) if (self.cfg.start_on_ground or self.mode == PX4_LAND) else self.z_m + vz * dt_s
        if self.mode == PX4_TAKEOFF and self.z_m - self.z_target_m <= TAKEOFF_DONE_M:
            self.z_target_m = self.z_m
            log.info("takeoff done at %.2f m above home", -self.z_m)
            self._set_mode(PX4_HOLD, reason="takeoff done")
        if not self.landed and self.z_m >= 0.0 and vz >= 0.0 and (self.mode == PX4_LAND or self.cfg.start_on_ground):
            self._touch_down()

    def _touch_down(self) -> None:
        self.landed = True
        self.flying = False
        self.vz_m_s = 0.0
        self.z_m = 0.0
        self.plant.states[0, 2:4] = 0.0
        self._landed_since_s = self.wall_s()
        log.info("landed")
        if self.params["COM_DISARM_LAND"] == 0.0 or not self.cfg.start_on_ground:
            self._disarm_landed()

    def _disarm_landed(self) -> None:
        if self.armed:
            self.armed = False
            log.info("landed: disarmed")
            self._send_heartbeat()

    def _ground_tick(self) -> None:
        """PX4's auto-disarm COM_DISARM_LAND after touchdown; the AUTO modes' vertical motion in lockstep."""
        now = self.wall_s()
        if self.cfg.lockstep and (self.mode in (PX4_TAKEOFF, PX4_LAND) or (self.mode in HOLD_LIKE and self.z_m != self.z_target_m)):
            while self._vert_wall_s + self.cfg.physics_dt_s <= now:
                self._vertical(self.cfg.physics_dt_s)
                self._vert_wall_s += self.cfg.physics_dt_s
        else:
            self._vert_wall_s = now
        t = self.params["COM_DISARM_LAND"]
        if self.landed and self.armed and self._landed_since_s is not None and t >= 0 and now - self._landed_since_s >= t:
            self._disarm_landed()
        if self.landed and self.mode == PX4_OFFBOARD and self.armed:
            z_sp, vz_sp = self._z_setpoint_world()
            if (z_sp is not None and z_sp < -LIFTOFF_M) or (vz_sp is not None and vz_sp < 0.0):
                self._lift_off()            # PX4 leaves idle in OFFBOARD only when the setpoint asks to climb

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
        if self.mode == PX4_OFFBOARD and self.sim_time_s() - self._last_sp_sim_s > self.params["COM_OF_LOSS_T"]:
            self._statustext(MavSeverity.WARNING, "Failsafe: offboard setpoints lost, Hold")
            log.warning("offboard setpoint stream lost for > COM_OF_LOSS_T = %g s: failsafe to HOLD", self.params["COM_OF_LOSS_T"])
            self._set_mode(PX4_HOLD, reason="offboard loss failsafe")
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
        if self._world_report is not None:
            if self.cfg.lockstep and self._world_pending_ms is not None:
                t = min(t, self._world_reported_at + self.WORLD_RETRY_S)
            elif self.cfg.traffic_rate_hz > 0:
                t = min(t, self._next_traffic)
        return t

    # ------------------------------------------------------------------ output
    def _statustext(self, severity: int, text: str) -> None:
        self._send(StatusText(int(severity), text[:50]), None)

    def _send_heartbeat(self) -> None:
        self._send(self._heartbeat(), None)

    def _heartbeat(self) -> Heartbeat:
        base = MavModeFlag.CUSTOM_MODE_ENABLED | (MavModeFlag.SAFETY_ARMED if self.armed else 0)
        if self.mode == PX4_OFFBOARD:
            base |= MavModeFlag.GUIDED_ENABLED | MavModeFlag.STABILIZE_ENABLED
        elif self.mode.main_mode == Px4MainMode.AUTO:
            base |= MavModeFlag.AUTO_ENABLED | MavModeFlag.GUIDED_ENABLED | MavModeFlag.STABILIZE_ENABLED
        return Heartbeat(
            type=MavType.QUADROTOR,
            autopilot=MavAutopilot.PX4,
            base_mode=int(base),
            custom_mode=self.mode.custom_mode,
            system_status=MavState.ACTIVE if self.armed else MavState.STANDBY,
        )

    def _local_position(self) -> LocalPositionNed:
        x, y, vx, vy = self.state.tolist()
        if self.cfg.origin is None:
            return LocalPositionNed(self.time_boot_ms(), x, y, self.z_m, vx, vy, self.vz_m_s)
        lx, ly, lz, lvx, lvy = self.frame.world_to_local(x, y, self.z_m, vx, vy)
        return LocalPositionNed(self.time_boot_ms(), lx, ly, lz, lvx, lvy, self.vz_m_s)

    def _here(self) -> tuple[float, float, float, float, float, float]:
        """(lat, lon, alt AMSL, and x, y, z in LOCAL_NED) of where the vehicle is: PX4's home."""
        x, y = self.state[0:2].tolist()
        if self.cfg.origin is None:
            return (self.cfg.home_lat_deg, self.cfg.home_lon_deg, self.cfg.home_alt_amsl_m, 0.0, 0.0, 0.0)
        lat, lon, _ = self.frame.world_to_geodetic(x, y, 0.0)
        lx, ly, lz, _, _ = self.frame.world_to_local(x, y, 0.0, 0.0, 0.0)
        return (lat, lon, self.cfg.home_alt_amsl_m, lx, ly, lz)

    def _origin_msg(self) -> GpsGlobalOrigin:
        lat, lon, alt = self.frame.origin_lat_lon_alt
        return GpsGlobalOrigin(lat, lon, alt, 0)

    def _attitude(self) -> Attitude:
        an, ae = self.applied_acc_m_s2.tolist() if self._moving() else (0.0, 0.0)
        return Attitude(self.time_boot_ms(), math.atan2(ae, GRAVITY_M_S2), math.atan2(-an, GRAVITY_M_S2), 0.0)

    def _global_position(self) -> GlobalPositionInt:
        x, y, vx, vy = self.state.tolist()
        if self.cfg.origin is not None:
            lat, lon, alt = self.frame.world_to_geodetic(x, y, self.z_m)
            return GlobalPositionInt(self.time_boot_ms(), lat, lon, alt, -self.z_m, vx, vy, self.vz_m_s, 0.0)
        lat0 = self.cfg.home_lat_deg
        lat = lat0 + math.degrees(x / EARTH_RADIUS_M)
        lon = self.cfg.home_lon_deg + math.degrees(y / (EARTH_RADIUS_M * math.cos(math.radians(lat0))))
        return GlobalPositionInt(
            self.time_boot_ms(), lat, lon, self.cfg.home_alt_amsl_m - self.z_m, -self.z_m, vx, vy, self.vz_m_s, 0.0
        )

    def _telemetry(self, kind: str) -> Message:
        if kind == "heartbeat":
            return self._heartbeat()
        if kind == "local_position":
            return self._local_position()
        if kind == "attitude":
            return self._attitude()
        if kind == "global_position":
            return self._global_position()
        if kind == "home_position":
            if self.cfg.origin is None:
                return HomePosition(self.cfg.home_lat_deg, self.cfg.home_lon_deg, self.cfg.home_alt_amsl_m)
            return HomePosition(*self.home)
        if kind == "sys_status":
            return SysStatus(load_permille=100, voltage_battery_v=16.2, battery_remaining_pct=100)
        if kind == "extended_sys_state":
            if self.cfg.start_on_ground:
                landed = (MavLandedState.ON_GROUND if self.landed else MavLandedState.TAKEOFF if self.mode == PX4_TAKEOFF
                          else MavLandedState.LANDING if self.mode == PX4_LAND else MavLandedState.IN_AIR)
                return ExtendedSysState(0, int(landed))
            landed = MavLandedState.IN_AIR if self.armed else MavLandedState.ON_GROUND
            if self.mode == PX4_LAND and self.armed:
                landed = MavLandedState.LANDING
            return ExtendedSysState(0, int(landed))
        raise KeyError(kind)

    def _fast_telemetry(self) -> list[Message]:
        return [self._local_position(), self._attitude(), self._global_position()]

    def _message_by_id(self, msg_id: int) -> Message | None:
        if msg_id == _ID["GPS_GLOBAL_ORIGIN"]:
            return self._origin_msg()
        if msg_id == _ID["AUTOPILOT_VERSION"]:
            return AutopilotVersion(CAPABILITIES, flight_sw_version=(1 << 24) | (14 << 16), uid=self.sysid)
        kind = TELEMETRY_IDS.get(msg_id)
        return None if kind is None else self._telemetry(kind)
