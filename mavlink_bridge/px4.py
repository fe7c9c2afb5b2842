"""MAVLink/PX4 constants as named enums (SPEC section 4; MAVLink common.xml; PX4
``px4_custom_mode.h``). No pymavlink import here: these are plain values."""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum, IntFlag

__all__ = [
    "MavCmd",
    "MavResult",
    "MavFrame",
    "MavType",
    "MavAutopilot",
    "MavModeFlag",
    "MavState",
    "MavLandedState",
    "MavParamType",
    "MavSeverity",
    "PositionTargetTypeMask",
    "ACC_ONLY_TYPE_MASK",
    "ALT_HOLD_ACC_TYPE_MASK",
    "Px4MainMode",
    "Px4AutoSubMode",
    "Px4Mode",
    "PX4_OFFBOARD",
    "PX4_HOLD",
    "PX4_LAND",
    "PX4_POSCTL",
    "PX4_TAKEOFF",
    "command_name",
    "result_name",
]


class MavCmd(IntEnum):
    NAV_LAND = 21
    NAV_TAKEOFF = 22
    DO_SET_MODE = 176
    COMPONENT_ARM_DISARM = 400
    GET_HOME_POSITION = 410
    SET_MESSAGE_INTERVAL = 511
    REQUEST_MESSAGE = 512
    REQUEST_PROTOCOL_VERSION = 519
    REQUEST_AUTOPILOT_CAPABILITIES = 520


class MavResult(IntEnum):
    ACCEPTED = 0
    TEMPORARILY_REJECTED = 1
    DENIED = 2
    UNSUPPORTED = 3
    FAILED = 4
    IN_PROGRESS = 5
    CANCELLED = 6


class MavFrame(IntEnum):
    GLOBAL = 0
    LOCAL_NED = 1
    MISSION = 2
    GLOBAL_RELATIVE_ALT = 3
    LOCAL_ENU = 4
    LOCAL_OFFSET_NED = 7
    BODY_NED = 8
    BODY_OFFSET_NED = 9
    BODY_FRD = 12


class MavType(IntEnum):
    GENERIC = 0
    QUADROTOR = 2
    GCS = 6
    ONBOARD_CONTROLLER = 18


class MavAutopilot(IntEnum):
    GENERIC = 0
    PX4 = 12
    INVALID = 8


class MavModeFlag(IntFlag):
    CUSTOM_MODE_ENABLED = 1
    TEST_ENABLED = 2
    AUTO_ENABLED = 4
    GUIDED_ENABLED = 8
    STABILIZE_ENABLED = 16
    HIL_ENABLED = 32
    MANUAL_INPUT_ENABLED = 64
    SAFETY_ARMED = 128


class MavState(IntEnum):
    UNINIT = 0
    BOOT = 1
    CALIBRATING = 2
    STANDBY = 3
    ACTIVE = 4
    CRITICAL = 5
    EMERGENCY = 6


class MavLandedState(IntEnum):
    UNDEFINED = 0
    ON_GROUND = 1
    IN_AIR = 2
    TAKEOFF = 3
    LANDING = 4


class MavParamType(IntEnum):
    INT32 = 6
    REAL32 = 9


class MavSeverity(IntEnum):
    EMERGENCY = 0
    ALERT = 1
    CRITICAL = 2
    ERROR = 3
    WARNING = 4
    NOTICE = 5
    INFO = 6
    DEBUG = 7


class PositionTargetTypeMask(IntFlag):
    """POSITION_TARGET_TYPEMASK of SET_POSITION_TARGET_LOCAL_NED (a set bit = ignore)."""

    X_IGNORE = 1
    Y_IGNORE = 2
    Z_IGNORE = 4
    VX_IGNORE = 8
    VY_IGNORE = 16
    VZ_IGNORE = 32
    AX_IGNORE = 64
    AY_IGNORE = 128
    AZ_IGNORE = 256
    FORCE_SET = 512
    YAW_IGNORE = 1024
    YAW_RATE_IGNORE = 2048

    POSITION_IGNORE = X_IGNORE | Y_IGNORE | Z_IGNORE
    VELOCITY_IGNORE = VX_IGNORE | VY_IGNORE | VZ_IGNORE
    ACCELERATION_IGNORE = AX_IGNORE | AY_IGNORE | AZ_IGNORE


ACC_ONLY_TYPE_MASK = (
    PositionTargetTypeMask.POSITION_IGNORE
    | PositionTargetTypeMask.VELOCITY_IGNORE
    | PositionTargetTypeMask.YAW_IGNORE
    | PositionTargetTypeMask.YAW_RATE_IGNORE
)
"""Acceleration-only setpoint: ignore position, velocity, yaw and yaw rate (3135 = 0x0C3F)."""
assert int(ACC_ONLY_TYPE_MASK) == 3135

ALT_HOLD_ACC_TYPE_MASK = (
    PositionTargetTypeMask.X_IGNORE
    | PositionTargetTypeMask.Y_IGNORE
    | PositionTargetTypeMask.VELOCITY_IGNORE
    | PositionTargetTypeMask.AZ_IGNORE
    | PositionTargetTypeMask.YAW_IGNORE
    | PositionTargetTypeMask.YAW_RATE_IGNORE
)
"""Altitude hold with horizontal acceleration: z position, ax, ay; ignore x, y, velocity, az, yaw,
yaw rate (3387 = 0x0D3B). PX4 runs z through its position loop and takes ax, ay as feed-forward
(docs/mavlink.md)."""
assert int(ALT_HOLD_ACC_TYPE_MASK) == 3387


class Px4MainMode(IntEnum):
    """PX4 ``custom_main_mode`` (px4_custom_mode.h)."""

    MANUAL = 1
    ALTCTL = 2
    POSCTL = 3
    AUTO = 4
    ACRO = 5
    OFFBOARD = 6
    STABILIZED = 7


class Px4AutoSubMode(IntEnum):
    """PX4 ``custom_sub_mode_auto``."""

    NONE = 0
    READY = 1
    TAKEOFF = 2
    LOITER = 3
    MISSION = 4
    RTL = 5
    LAND = 6


@dataclass(frozen=True)
class Px4Mode:
    """A PX4 flight mode: HEARTBEAT.custom_mode = main_mode << 16 | sub_mode << 24."""

    main_mode: int
    sub_mode: int = 0

    @property
    def custom_mode(self) -> int:
        return (int(self.main_mode) << 16) | (int(self.sub_mode) << 24)

    @classmethod
    def from_custom_mode(cls, custom_mode: int) -> "Px4Mode":
        main = (custom_mode >> 16) & 0xFF
        sub = (custom_mode >> 24) & 0xFF
        if main != Px4MainMode.AUTO:
            sub = 0
        return cls(main, sub)

    @property
    def name(self) -> str:
        try:
            main = Px4MainMode(self.main_mode).name
        except ValueError:
            return f"MAIN{self.main_mode}.{self.sub_mode}"
        if self.main_mode == Px4MainMode.AUTO:
            try:
                return f"AUTO.{Px4AutoSubMode(self.sub_mode).name}"
            except ValueError:
                return f"AUTO.{self.sub_mode}"
        return main

    def __str__(self) -> str:
        return self.name


PX4_OFFBOARD = Px4Mode(Px4MainMode.OFFBOARD)
PX4_HOLD = Px4Mode(Px4MainMode.AUTO, Px4AutoSubMode.LOITER)
PX4_LAND = Px4Mode(Px4MainMode.AUTO, Px4AutoSubMode.LAND)
PX4_POSCTL = Px4Mode(Px4MainMode.POSCTL)
PX4_TAKEOFF = Px4Mode(Px4MainMode.AUTO, Px4AutoSubMode.TAKEOFF)


def command_name(command: int) -> str:
    try:
        return f"MAV_CMD_{MavCmd(command).name}({int(command)})"
    except ValueError:
        return f"MAV_CMD {int(command)}"


def result_name(result: int) -> str:
    try:
        return f"MAV_RESULT_{MavResult(result).name}"
    except ValueError:
        return f"MAV_RESULT {int(result)}"
