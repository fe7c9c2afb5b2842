"""Typed errors of the MAVLink bridge. Every wait raises one of these, naming what failed."""

from __future__ import annotations

__all__ = [
    "BridgeError",
    "ConnectionStringError",
    "LinkClosed",
    "HeartbeatTimeout",
    "TelemetryTimeout",
    "CommandTimeout",
    "CommandDenied",
    "ModeNotConfirmed",
    "ArmNotConfirmed",
]


class BridgeError(Exception):
    """Base class of every error raised by ``mavlink_bridge``."""


class ConnectionStringError(BridgeError, ValueError):
    """A connection string the bridge cannot open (unknown scheme, bad address)."""


class LinkClosed(BridgeError):
    """The link was closed while waiting or sending."""


class HeartbeatTimeout(BridgeError, TimeoutError):
    """No HEARTBEAT from the target system/component within ``timeout_s``."""

    def __init__(self, target_system: int, target_component: int, timeout_s: float, what: str = "HEARTBEAT") -> None:
        self.target_system = target_system
        self.target_component = target_component
        self.timeout_s = timeout_s
        super().__init__(f"no {what} from system {target_system} component {target_component} within {timeout_s:.3g} s")


class TelemetryTimeout(BridgeError, TimeoutError):
    """A telemetry message (e.g. LOCAL_POSITION_NED) did not arrive within ``timeout_s``."""

    def __init__(self, message: str, target_system: int, timeout_s: float) -> None:
        self.message = message
        self.target_system = target_system
        self.timeout_s = timeout_s
        super().__init__(f"no {message} from system {target_system} within {timeout_s:.3g} s")


class CommandTimeout(BridgeError, TimeoutError):
    """No COMMAND_ACK for a COMMAND_LONG within ``timeout_s`` (after retransmissions)."""

    def __init__(self, command: int, target_system: int, timeout_s: float) -> None:
        from .px4 import command_name

        self.command = command
        self.target_system = target_system
        self.timeout_s = timeout_s
        super().__init__(f"no COMMAND_ACK for {command_name(command)} from system {target_system} within {timeout_s:.3g} s")


class CommandDenied(BridgeError):
    """The vehicle answered a COMMAND_LONG with a result other than ACCEPTED."""

    def __init__(self, command: int, result: int, target_system: int | None = None) -> None:
        from .px4 import command_name, result_name

        self.command = command
        self.result = result
        self.target_system = target_system
        who = "" if target_system is None else f" by system {target_system}"
        super().__init__(f"{command_name(command)} refused{who}: {result_name(result)}")


class ModeNotConfirmed(BridgeError, TimeoutError):
    """The mode change was ACKed but no HEARTBEAT confirmed the new mode within ``timeout_s``."""

    def __init__(self, mode: str, last_mode: str | None, timeout_s: float) -> None:
        self.mode = mode
        self.last_mode = last_mode
        self.timeout_s = timeout_s
        super().__init__(f"mode {mode} not confirmed by HEARTBEAT within {timeout_s:.3g} s (last seen: {last_mode})")


class ArmNotConfirmed(BridgeError, TimeoutError):
    """Arm/disarm was ACKed but no HEARTBEAT showed the new arming state within ``timeout_s``."""

    def __init__(self, armed: bool, timeout_s: float) -> None:
        self.armed = armed
        self.timeout_s = timeout_s
        super().__init__(f"{'arming' if armed else 'disarming'} not confirmed by HEARTBEAT within {timeout_s:.3g} s")
