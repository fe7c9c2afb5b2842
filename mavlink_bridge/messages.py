"""Typed MAVLink messages: frozen dataclasses with units in field names.

These are the contract between the bridge and its users (controller and mock
vehicle); nothing outside ``mavlink_bridge`` sees a pymavlink object. Field
conventions follow MAVLink common.xml, converted to SI units where the wire
uses scaled integers (GLOBAL_POSITION_INT: degE7 -> deg, mm -> m, cm/s -> m/s).
``received_monotonic_s`` (``time.monotonic()`` at decode; NaN for messages built
locally) is excluded from equality so that telemetry compares by content.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import ClassVar

from .px4 import (
    ACC_ONLY_TYPE_MASK,
    ALT_HOLD_ACC_TYPE_MASK,
    MavAutopilot,
    MavFrame,
    MavModeFlag,
    MavParamType,
    MavState,
    MavType,
    PositionTargetTypeMask,
    Px4MainMode,
    Px4Mode,
)

__all__ = [
    "Message",
    "Heartbeat",
    "LocalPositionNed",
    "Attitude",
    "GlobalPositionInt",
    "HomePosition",
    "GpsGlobalOrigin",
    "SysStatus",
    "ExtendedSysState",
    "CommandLong",
    "CommandInt",
    "CommandAck",
    "SetMode",
    "SetPositionTargetLocalNed",
    "ParamValue",
    "ParamSet",
    "ParamRequestRead",
    "ParamRequestList",
    "StatusText",
    "AutopilotVersion",
    "AdsbVehicle",
    "NamedValueInt",
    "BadData",
    "UnknownMessage",
    "Received",
    "acceleration_setpoint",
    "altitude_hold_setpoint",
]

_NAN = math.nan


class Message:
    """Marker base of every typed message; ``MSG_NAME`` is the MAVLink name."""

    MSG_NAME: ClassVar[str] = ""


@dataclass(frozen=True)
class Heartbeat(Message):
    """HEARTBEAT (#0). For PX4: custom_mode = main_mode << 16 | sub_mode << 24 (SPEC 4)."""

    MSG_NAME: ClassVar[str] = "HEARTBEAT"
    type: int = MavType.QUADROTOR
    autopilot: int = MavAutopilot.PX4
    base_mode: int = 0
    custom_mode: int = 0
    system_status: int = MavState.STANDBY
    mavlink_version: int = 3
    received_monotonic_s: float = field(default=_NAN, compare=False)

    @property
    def armed(self) -> bool:
        return bool(self.base_mode & MavModeFlag.SAFETY_ARMED)

    @property
    def px4_mode(self) -> Px4Mode:
        return Px4Mode.from_custom_mode(self.custom_mode)

    @property
    def custom_main_mode(self) -> int:
        return (self.custom_mode >> 16) & 0xFF

    @property
    def custom_sub_mode(self) -> int:
        return (self.custom_mode >> 24) & 0xFF

    @property
    def is_offboard(self) -> bool:
        return bool(self.base_mode & MavModeFlag.CUSTOM_MODE_ENABLED) and self.custom_main_mode == Px4MainMode.OFFBOARD


@dataclass(frozen=True)
class LocalPositionNed(Message):
    """LOCAL_POSITION_NED (#32): position and velocity in the local NED frame."""

    MSG_NAME: ClassVar[str] = "LOCAL_POSITION_NED"
    time_boot_ms: int
    x_m: float
    y_m: float
    z_m: float
    vx_m_s: float
    vy_m_s: float
    vz_m_s: float
    received_monotonic_s: float = field(default=_NAN, compare=False)


@dataclass(frozen=True)
class Attitude(Message):
    """ATTITUDE (#30)."""

    MSG_NAME: ClassVar[str] = "ATTITUDE"
    time_boot_ms: int
    roll_rad: float
    pitch_rad: float
    yaw_rad: float
    rollspeed_rad_s: float = 0.0
    pitchspeed_rad_s: float = 0.0
    yawspeed_rad_s: float = 0.0
    received_monotonic_s: float = field(default=_NAN, compare=False)


@dataclass(frozen=True)
class GlobalPositionInt(Message):
    """GLOBAL_POSITION_INT (#33) in SI units (wire: degE7, mm, cm/s, cdeg)."""

    MSG_NAME: ClassVar[str] = "GLOBAL_POSITION_INT"
    time_boot_ms: int
    lat_deg: float
    lon_deg: float
    alt_amsl_m: float
    relative_alt_m: float
    vx_m_s: float
    vy_m_s: float
    vz_m_s: float
    heading_deg: float | None = None
    received_monotonic_s: float = field(default=_NAN, compare=False)


@dataclass(frozen=True)
class HomePosition(Message):
    """HOME_POSITION (#242): home in WGS84 and in the local frame."""

    MSG_NAME: ClassVar[str] = "HOME_POSITION"
    lat_deg: float
    lon_deg: float
    alt_amsl_m: float
    x_m: float = 0.0
    y_m: float = 0.0
    z_m: float = 0.0
    received_monotonic_s: float = field(default=_NAN, compare=False)


@dataclass(frozen=True)
class GpsGlobalOrigin(Message):
    """GPS_GLOBAL_ORIGIN (#49): the EKF origin, which the vehicle's LOCAL_NED is relative to."""

    MSG_NAME: ClassVar[str] = "GPS_GLOBAL_ORIGIN"
    lat_deg: float
    lon_deg: float
    alt_amsl_m: float
    time_usec: int = 0
    received_monotonic_s: float = field(default=_NAN, compare=False)


@dataclass(frozen=True)
class SysStatus(Message):
    """SYS_STATUS (#1), reduced to what a mock vehicle can honestly report."""

    MSG_NAME: ClassVar[str] = "SYS_STATUS"
    sensors_present: int = 0
    sensors_enabled: int = 0
    sensors_health: int = 0
    load_permille: int = 0
    voltage_battery_v: float = 16.0
    current_battery_a: float | None = None
    battery_remaining_pct: int = 100
    received_monotonic_s: float = field(default=_NAN, compare=False)


@dataclass(frozen=True)
class ExtendedSysState(Message):
    """EXTENDED_SYS_STATE (#245)."""

    MSG_NAME: ClassVar[str] = "EXTENDED_SYS_STATE"
    vtol_state: int = 0
    landed_state: int = 0
    received_monotonic_s: float = field(default=_NAN, compare=False)


@dataclass(frozen=True)
class CommandLong(Message):
    """COMMAND_LONG (#76). ``params`` are param1..param7."""

    MSG_NAME: ClassVar[str] = "COMMAND_LONG"
    target_system: int
    target_component: int
    command: int
    params: tuple[float, float, float, float, float, float, float] = (0.0,) * 7
    confirmation: int = 0
    received_monotonic_s: float = field(default=_NAN, compare=False)


@dataclass(frozen=True)
class CommandInt(Message):
    """COMMAND_INT (#75). ``params`` are param1..param4; x, y are scaled integers."""

    MSG_NAME: ClassVar[str] = "COMMAND_INT"
    target_system: int
    target_component: int
    command: int
    frame: int = 0
    params: tuple[float, float, float, float] = (0.0,) * 4
    x: int = 0
    y: int = 0
    z: float = 0.0
    received_monotonic_s: float = field(default=_NAN, compare=False)


@dataclass(frozen=True)
class CommandAck(Message):
    """COMMAND_ACK (#77)."""

    MSG_NAME: ClassVar[str] = "COMMAND_ACK"
    command: int
    result: int
    target_system: int = 0
    target_component: int = 0
    progress: int = 0
    result_param2: int = 0
    received_monotonic_s: float = field(default=_NAN, compare=False)


@dataclass(frozen=True)
class SetMode(Message):
    """SET_MODE (#11), deprecated by DO_SET_MODE but still honoured by PX4."""

    MSG_NAME: ClassVar[str] = "SET_MODE"
    target_system: int
    base_mode: int
    custom_mode: int
    received_monotonic_s: float = field(default=_NAN, compare=False)


@dataclass(frozen=True)
class SetPositionTargetLocalNed(Message):
    """SET_POSITION_TARGET_LOCAL_NED (#84). A set bit of ``type_mask`` ignores that field
    (PositionTargetTypeMask); ``afx/afy/afz`` are accelerations in m/s^2."""

    MSG_NAME: ClassVar[str] = "SET_POSITION_TARGET_LOCAL_NED"
    time_boot_ms: int
    target_system: int
    target_component: int
    coordinate_frame: int = MavFrame.LOCAL_NED
    type_mask: int = int(ACC_ONLY_TYPE_MASK)
    x_m: float = 0.0
    y_m: float = 0.0
    z_m: float = 0.0
    vx_m_s: float = 0.0
    vy_m_s: float = 0.0
    vz_m_s: float = 0.0
    afx_m_s2: float = 0.0
    afy_m_s2: float = 0.0
    afz_m_s2: float = 0.0
    yaw_rad: float = 0.0
    yaw_rate_rad_s: float = 0.0
    received_monotonic_s: float = field(default=_NAN, compare=False)

    @property
    def mask(self) -> PositionTargetTypeMask:
        return PositionTargetTypeMask(self.type_mask & 0xFFFF)

    @property
    def acc_ned_m_s2(self) -> tuple[float, float, float]:
        return (self.afx_m_s2, self.afy_m_s2, self.afz_m_s2)


def altitude_hold_setpoint(
    target_system: int,
    target_component: int,
    acc_ne_m_s2: tuple[float, float],
    z_m: float,
    time_boot_ms: int,
) -> SetPositionTargetLocalNed:
    """Horizontal acceleration with altitude hold (LOCAL_NED, type_mask 3387 = ALT_HOLD_ACC_TYPE_MASK):
    ax, ay feed-forward, z a position (down, relative to the vehicle's EKF origin)."""
    ax, ay, z = float(acc_ne_m_s2[0]), float(acc_ne_m_s2[1]), float(z_m)
    if not all(math.isfinite(a) for a in (ax, ay, z)):
        raise ValueError(f"altitude-hold setpoint must be finite, got acc {acc_ne_m_s2}, z {z_m}")
    return SetPositionTargetLocalNed(
        time_boot_ms=int(time_boot_ms) & 0xFFFFFFFF,
        target_system=target_system,
        target_component=target_component,
        coordinate_frame=MavFrame.LOCAL_NED,
        type_mask=int(ALT_HOLD_ACC_TYPE_MASK),
        z_m=z,
        afx_m_s2=ax,
        afy_m_s2=ay,
    )


def acceleration_setpoint(
    target_system: int,
    target_component: int,
    acc_ned_m_s2: tuple[float, float, float],
    time_boot_ms: int,
) -> SetPositionTargetLocalNed:
    """An acceleration-only setpoint (LOCAL_NED, type_mask 3135 = ACC_ONLY_TYPE_MASK)."""
    ax, ay, az = (float(a) for a in acc_ned_m_s2)
    if not all(math.isfinite(a) for a in (ax, ay, az)):
        raise ValueError(f"acceleration setpoint must be finite, got {acc_ned_m_s2}")
    return SetPositionTargetLocalNed(
        time_boot_ms=int(time_boot_ms) & 0xFFFFFFFF,
        target_system=target_system,
        target_component=target_component,
        coordinate_frame=MavFrame.LOCAL_NED,
        type_mask=int(ACC_ONLY_TYPE_MASK),
        afx_m_s2=ax,
        afy_m_s2=ay,
        afz_m_s2=az,
    )


@dataclass(frozen=True)
class ParamValue(Message):
    """PARAM_VALUE (#22)."""

    MSG_NAME: ClassVar[str] = "PARAM_VALUE"
    param_id: str
    value: float
    param_type: int = MavParamType.REAL32
    param_count: int = 0
    param_index: int = 0
    received_monotonic_s: float = field(default=_NAN, compare=False)


@dataclass(frozen=True)
class ParamSet(Message):
    """PARAM_SET (#23)."""

    MSG_NAME: ClassVar[str] = "PARAM_SET"
    target_system: int
    target_component: int
    param_id: str
    value: float
    param_type: int = MavParamType.REAL32
    received_monotonic_s: float = field(default=_NAN, compare=False)


@dataclass(frozen=True)
class ParamRequestRead(Message):
    """PARAM_REQUEST_READ (#20): by ``param_id``, or by ``param_index`` when it is >= 0."""

    MSG_NAME: ClassVar[str] = "PARAM_REQUEST_READ"
    target_system: int
    target_component: int
    param_id: str = ""
    param_index: int = -1
    received_monotonic_s: float = field(default=_NAN, compare=False)


@dataclass(frozen=True)
class ParamRequestList(Message):
    """PARAM_REQUEST_LIST (#21)."""

    MSG_NAME: ClassVar[str] = "PARAM_REQUEST_LIST"
    target_system: int
    target_component: int
    received_monotonic_s: float = field(default=_NAN, compare=False)


@dataclass(frozen=True)
class StatusText(Message):
    """STATUSTEXT (#253), up to 50 characters."""

    MSG_NAME: ClassVar[str] = "STATUSTEXT"
    severity: int
    text: str
    received_monotonic_s: float = field(default=_NAN, compare=False)


@dataclass(frozen=True)
class AutopilotVersion(Message):
    """AUTOPILOT_VERSION (#148), answered to REQUEST_MESSAGE(148) as PX4 does."""

    MSG_NAME: ClassVar[str] = "AUTOPILOT_VERSION"
    capabilities: int
    flight_sw_version: int = 0
    uid: int = 0
    received_monotonic_s: float = field(default=_NAN, compare=False)


@dataclass(frozen=True)
class AdsbVehicle(Message):
    """ADSB_VEHICLE (#246): one traffic report, as PX4 forwards it for traffic avoidance.
    Kept in wire units (degE7, mm, cdeg, cm/s) so that nothing is lost in a conversion;
    ``mavlink_bridge.adsb`` turns a set of them into local NED states (docs/proximity.md)."""

    MSG_NAME: ClassVar[str] = "ADSB_VEHICLE"
    icao_address: int
    lat_e7: int
    lon_e7: int
    altitude_type: int = 1             # ADSB_ALTITUDE_TYPE_GEOMETRIC
    altitude_mm: int = 0
    heading_cdeg: int = 0              # course over ground, 0..35999, clockwise from north
    hor_velocity_cm_s: int = 0
    ver_velocity_cm_s: int = 0         # positive up
    callsign: str = ""
    emitter_type: int = 14             # ADSB_EMITTER_TYPE_UAV
    tslc_s: int = 0
    flags: int = 0
    squawk: int = 0
    received_monotonic_s: float = field(default=_NAN, compare=False)


@dataclass(frozen=True)
class NamedValueInt(Message):
    """NAMED_VALUE_INT (#252): a named integer (name up to 10 characters)."""

    MSG_NAME: ClassVar[str] = "NAMED_VALUE_INT"
    time_boot_ms: int
    name: str
    value: int
    received_monotonic_s: float = field(default=_NAN, compare=False)


@dataclass(frozen=True)
class BadData(Message):
    """Bytes that did not parse as MAVLink (bad CRC, garbage, truncated packet)."""

    MSG_NAME: ClassVar[str] = "BAD_DATA"
    reason: str
    n_bytes: int
    received_monotonic_s: float = field(default=_NAN, compare=False)


@dataclass(frozen=True)
class UnknownMessage(Message):
    """A valid MAVLink packet of a type the bridge does not model."""

    MSG_NAME: ClassVar[str] = "UNKNOWN"
    msg_id: int
    name: str
    received_monotonic_s: float = field(default=_NAN, compare=False)


@dataclass(frozen=True)
class Received:
    """A decoded message with its MAVLink header: who sent it, and the raw packet."""

    msg: Message
    src_system: int
    src_component: int
    raw: bytes = field(default=b"", repr=False, compare=False)
    signature: str = "unsigned"
    """MAVLink 2 signature status (``mavlink_bridge.signing``): "unsigned", "valid",
    "bad signature", "replayed timestamp", or "unchecked" (signed, but no key here)."""

    @property
    def signed_ok(self) -> bool:
        """True if the packet carried a valid, fresh signature under this endpoint's key."""
        return self.signature == "valid"
