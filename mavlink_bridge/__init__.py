"""MAVLink bridge: the project's only pymavlink import (SPEC section 4, issue 4).

Both sides use it: the controller opens a ``VehicleLink``; the mock vehicle uses
``MavlinkPort`` and the typed messages for its wire I/O and tlog.
"""

from .errors import (
    ArmNotConfirmed,
    BridgeError,
    CommandDenied,
    CommandTimeout,
    ConnectionStringError,
    HeartbeatTimeout,
    LinkClosed,
    ModeNotConfirmed,
    TelemetryTimeout,
)
from .link import COMPANION_COMPONENT_ID, VehicleLink
from .messages import (
    AdsbVehicle,
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
    Message,
    NamedValueInt,
    ParamRequestList,
    ParamRequestRead,
    ParamSet,
    ParamValue,
    Received,
    SetMode,
    SetPositionTargetLocalNed,
    StatusText,
    SysStatus,
    UnknownMessage,
    acceleration_setpoint,
    altitude_hold_setpoint,
)
from .port import MavlinkPort
from .px4 import (
    ACC_ONLY_TYPE_MASK,
    ALT_HOLD_ACC_TYPE_MASK,
    PX4_HOLD,
    PX4_LAND,
    PX4_OFFBOARD,
    PX4_POSCTL,
    PX4_TAKEOFF,
    MavAutopilot,
    MavCmd,
    MavFrame,
    MavLandedState,
    MavModeFlag,
    MavParamType,
    MavResult,
    MavSeverity,
    MavState,
    MavType,
    PositionTargetTypeMask,
    Px4AutoSubMode,
    Px4MainMode,
    Px4Mode,
)
from .ratelog import RejectLog
from .signing import SignatureVerifier, SigningConfig, SigningKeyError, load_signing_key, write_signing_key
from .tlog import TlogCheck, TlogError, TlogWriter, check_tlog, read_tlog
from .transport import Endpoint, open_transport, parse_connection_string

AccelerationSetpoint = SetPositionTargetLocalNed
"""Alias: an acceleration setpoint is a SET_POSITION_TARGET_LOCAL_NED with mask 3135."""

MSG_ID_BY_NAME: dict[str, int]
from .codec import MAVLINK_MSG_ID as MSG_ID_BY_NAME  # noqa: E402

__all__ = [name for name in dir() if not name.startswith("_")]
