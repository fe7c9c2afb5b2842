"""What the mock vehicle reports: HEARTBEAT, LOCAL_POSITION_NED, GLOBAL_POSITION_INT, ATTITUDE,
HOME_POSITION, GPS_GLOBAL_ORIGIN, SYS_STATUS, EXTENDED_SYS_STATE, STATUSTEXT, AUTOPILOT_VERSION.

``TelemetryMixin`` is a part of ``MockVehicle`` (mock_vehicle/vehicle.py), split out where the reader
pauses: it builds typed messages from the vehicle's state (``state``, ``z_m``, ``vz_m_s``, ``armed``,
``mode``, ``landed``, ``home``, ``frame``) and sends them through the vehicle's ``_send``.

Frames (``geo.LocalFrame``, SPEC 4b): the plant flies in the world frame (the tangent plane at the
world's home); with ``VehicleConfig.origin`` LOCAL_POSITION_NED is relative to the vehicle's own EKF
origin and GLOBAL_POSITION_INT / HOME_POSITION come from pymap3d, as on a real PX4 (whose
GPS_GLOBAL_ORIGIN stream, mavlink/streams/GPS_GLOBAL_ORIGIN.hpp, sends the origin when it is set or
changes, and on MAV_CMD_REQUEST_MESSAGE 49). Without an origin the local frame is the world frame and
the global position a flat earth around the home, as before issue 19.
"""

from __future__ import annotations

import math

from mavlink_bridge import (
    MSG_ID_BY_NAME,
    PX4_LAND,
    PX4_OFFBOARD,
    PX4_TAKEOFF,
    Attitude,
    AutopilotVersion,
    ExtendedSysState,
    GlobalPositionInt,
    GpsGlobalOrigin,
    Heartbeat,
    HomePosition,
    LocalPositionNed,
    MavAutopilot,
    MavLandedState,
    MavModeFlag,
    MavState,
    MavType,
    Message,
    Px4MainMode,
    StatusText,
    SysStatus,
)

from .lifecycle import GRAVITY_M_S2

__all__ = ["TelemetryMixin", "TELEMETRY_IDS", "FAST_TELEMETRY", "CAPABILITIES", "EARTH_RADIUS_M"]

EARTH_RADIUS_M = 6_378_137.0
CAPABILITIES = 2 | 8 | 128 | 8192  # PARAM_FLOAT | COMMAND_INT | SET_POSITION_TARGET_LOCAL_NED | MAVLINK2

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


class TelemetryMixin:
    """The messages of ``MockVehicle`` (module docstring)."""

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
        """(lat, lon, alt AMSL, and x, y, z in LOCAL_NED) of where the vehicle is: PX4's home (set on the
        ground before arming and at arming, commander/HomePosition.cpp). Without an origin: the world's
        home at ground level, as before issue 19."""
        if self.cfg.origin is None:
            return (self.cfg.home_lat_deg, self.cfg.home_lon_deg, self.cfg.home_alt_amsl_m, 0.0, 0.0, 0.0)
        x, y = self.state[0:2].tolist()
        lat, lon, alt = self.frame.world_to_geodetic(x, y, self.z_m)
        lx, ly, lz, _, _ = self.frame.world_to_local(x, y, self.z_m, 0.0, 0.0)
        return (lat, lon, alt, lx, ly, lz)

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
            rel = self.frame.local_z_to_world(self.home[5]) - self.z_m          # above home, as PX4's relative_alt
            return GlobalPositionInt(self.time_boot_ms(), lat, lon, alt, rel, vx, vy, self.vz_m_s, 0.0)
        lat0 = self.cfg.home_lat_deg
        lat = lat0 + math.degrees(x / EARTH_RADIUS_M)
        lon = self.cfg.home_lon_deg + math.degrees(y / (EARTH_RADIUS_M * math.cos(math.radians(lat0))))
        return GlobalPositionInt(
            self.time_boot_ms(), lat, lon, self.cfg.home_alt_amsl_m - self.z_m, -self.z_m, vx, vy, self.vz_m_s, 0.0
        )

    def _landed_state(self) -> int:
        """EXTENDED_SYS_STATE landed_state as PX4's stream has it (mavlink/streams/EXTENDED_SYS_STATE.hpp):
        ON_GROUND while the land detector says landed, else TAKEOFF / LANDING while the AUTO setpoint is
        a takeoff / land, else IN_AIR. The air start keeps its old rule (armed = in the air)."""
        if self.cfg.start_on_ground:
            if self.landed:
                return MavLandedState.ON_GROUND
            return (MavLandedState.TAKEOFF if self.mode == PX4_TAKEOFF else MavLandedState.LANDING if self.mode == PX4_LAND
                    else MavLandedState.IN_AIR)
        if not self.armed:
            return MavLandedState.ON_GROUND
        return MavLandedState.LANDING if self.mode == PX4_LAND else MavLandedState.IN_AIR

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
            return ExtendedSysState(0, int(self._landed_state()))
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
