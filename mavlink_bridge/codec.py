"""The project's only pymavlink import (SPEC section 4: pymavlink facts).

``MAVLINK20=1`` is set before pymavlink is imported so that ``mavutil`` (used only
to read tlogs back) also speaks MAVLink 2 with the common dialect; packing and
parsing use ``pymavlink.dialects.v20.common`` directly, which is MAVLink 2 whatever
the environment says. MAVLink 1 packets are still parsed on input.
"""

from __future__ import annotations

import collections
import math
import os
import struct
import time
from dataclasses import replace
from typing import Callable

os.environ["MAVLINK20"] = "1"  # must precede any pymavlink import (SPEC 4)

from pymavlink.dialects.v20 import common as _mavlink  # noqa: E402

from .messages import (  # noqa: E402
    AdsbVehicle,
    Attitude,
    AutopilotVersion,
    BadData,
    CommandAck,
    CommandInt,
    CommandLong,
    ExtendedSysState,
    GlobalPositionInt,
    Heartbeat,
    HomePosition,
    GpsGlobalOrigin,
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
)
from .signing import SIG_UNCHECKED, SIG_UNSIGNED, IFLAG_SIGNED, SignatureVerifier, SigningConfig, signing_timestamp_now  # noqa: E402

__all__ = ["MavCodec", "MAVLINK_MSG_ID"]

MAVLINK_MSG_ID = {
    name[len("MAVLINK_MSG_ID_") :]: value
    for name, value in vars(_mavlink).items()
    if name.startswith("MAVLINK_MSG_ID_") and isinstance(value, int)
}
"""MAVLink message name -> numeric id (common dialect)."""


def _clip_i(value: float, lo: int, hi: int) -> int:
    if not math.isfinite(value):
        return 0
    return int(min(max(round(value), lo), hi))


def _s(text: str | bytes) -> bytes:
    return text if isinstance(text, bytes) else text.encode("ascii", "replace")


def _str(value) -> str:
    if isinstance(value, (bytes, bytearray)):
        value = value.decode("ascii", "replace")
    return str(value).split("\x00", 1)[0]


# --- encoders: typed message -> pymavlink message -------------------------------------

_ENCODERS: dict[type, Callable] = {
    Heartbeat: lambda mav, m: mav.heartbeat_encode(
        m.type, m.autopilot, m.base_mode & 0xFF, m.custom_mode & 0xFFFFFFFF, m.system_status, m.mavlink_version
    ),
    LocalPositionNed: lambda mav, m: mav.local_position_ned_encode(
        m.time_boot_ms & 0xFFFFFFFF, m.x_m, m.y_m, m.z_m, m.vx_m_s, m.vy_m_s, m.vz_m_s
    ),
    Attitude: lambda mav, m: mav.attitude_encode(
        m.time_boot_ms & 0xFFFFFFFF, m.roll_rad, m.pitch_rad, m.yaw_rad, m.rollspeed_rad_s, m.pitchspeed_rad_s, m.yawspeed_rad_s
    ),
    GlobalPositionInt: lambda mav, m: mav.global_position_int_encode(
        m.time_boot_ms & 0xFFFFFFFF,
        _clip_i(m.lat_deg * 1e7, -(2**31), 2**31 - 1),
        _clip_i(m.lon_deg * 1e7, -(2**31), 2**31 - 1),
        _clip_i(m.alt_amsl_m * 1e3, -(2**31), 2**31 - 1),
        _clip_i(m.relative_alt_m * 1e3, -(2**31), 2**31 - 1),
        _clip_i(m.vx_m_s * 100, -(2**15), 2**15 - 1),
        _clip_i(m.vy_m_s * 100, -(2**15), 2**15 - 1),
        _clip_i(m.vz_m_s * 100, -(2**15), 2**15 - 1),
        65535 if m.heading_deg is None else _clip_i((m.heading_deg % 360.0) * 100, 0, 35999),
    ),
    HomePosition: lambda mav, m: mav.home_position_encode(
        _clip_i(m.lat_deg * 1e7, -(2**31), 2**31 - 1),
        _clip_i(m.lon_deg * 1e7, -(2**31), 2**31 - 1),
        _clip_i(m.alt_amsl_m * 1e3, -(2**31), 2**31 - 1),
        m.x_m,
        m.y_m,
        m.z_m,
        [1.0, 0.0, 0.0, 0.0],
        0.0,
        0.0,
        0.0,
    ),
    GpsGlobalOrigin: lambda mav, m: mav.gps_global_origin_encode(
        _clip_i(m.lat_deg * 1e7, -(2**31), 2**31 - 1),
        _clip_i(m.lon_deg * 1e7, -(2**31), 2**31 - 1),
        _clip_i(m.alt_amsl_m * 1e3, -(2**31), 2**31 - 1),
        int(m.time_usec),
    ),
    SysStatus: lambda mav, m: mav.sys_status_encode(
        m.sensors_present,
        m.sensors_enabled,
        m.sensors_health,
        m.load_permille,
        _clip_i(m.voltage_battery_v * 1e3, 0, 65535),
        -1 if m.current_battery_a is None else _clip_i(m.current_battery_a * 100, -1, 32767),
        m.battery_remaining_pct,
        0,
        0,
        0,
        0,
        0,
        0,
    ),
    ExtendedSysState: lambda mav, m: mav.extended_sys_state_encode(m.vtol_state, m.landed_state),
    CommandLong: lambda mav, m: mav.command_long_encode(m.target_system, m.target_component, m.command, m.confirmation, *m.params),
    CommandInt: lambda mav, m: mav.command_int_encode(
        m.target_system, m.target_component, m.frame, m.command, 0, 0, *m.params, m.x, m.y, m.z
    ),
    CommandAck: lambda mav, m: mav.command_ack_encode(
        m.command, m.result, m.progress, m.result_param2, m.target_system, m.target_component
    ),
    SetMode: lambda mav, m: mav.set_mode_encode(m.target_system, m.base_mode, m.custom_mode),
    SetPositionTargetLocalNed: lambda mav, m: mav.set_position_target_local_ned_encode(
        m.time_boot_ms & 0xFFFFFFFF,
        m.target_system,
        m.target_component,
        m.coordinate_frame,
        m.type_mask,
        m.x_m,
        m.y_m,
        m.z_m,
        m.vx_m_s,
        m.vy_m_s,
        m.vz_m_s,
        m.afx_m_s2,
        m.afy_m_s2,
        m.afz_m_s2,
        m.yaw_rad,
        m.yaw_rate_rad_s,
    ),
    ParamValue: lambda mav, m: mav.param_value_encode(_s(m.param_id), m.value, m.param_type, m.param_count, m.param_index),
    ParamSet: lambda mav, m: mav.param_set_encode(m.target_system, m.target_component, _s(m.param_id), m.value, m.param_type),
    ParamRequestRead: lambda mav, m: mav.param_request_read_encode(
        m.target_system, m.target_component, _s(m.param_id), m.param_index
    ),
    ParamRequestList: lambda mav, m: mav.param_request_list_encode(m.target_system, m.target_component),
    StatusText: lambda mav, m: mav.statustext_encode(m.severity, _s(m.text[:50])),
    AutopilotVersion: lambda mav, m: mav.autopilot_version_encode(
        m.capabilities, m.flight_sw_version, 0, 0, 0, [0] * 8, [0] * 8, [0] * 8, 0, 0, m.uid
    ),
    AdsbVehicle: lambda mav, m: mav.adsb_vehicle_encode(
        m.icao_address & 0xFFFFFFFF,
        m.lat_e7,
        m.lon_e7,
        m.altitude_type,
        m.altitude_mm,
        m.heading_cdeg,
        m.hor_velocity_cm_s,
        m.ver_velocity_cm_s,
        _s(m.callsign[:8]),
        m.emitter_type,
        m.tslc_s,
        m.flags,
        m.squawk,
    ),
    NamedValueInt: lambda mav, m: mav.named_value_int_encode(m.time_boot_ms & 0xFFFFFFFF, _s(m.name[:10]), m.value),
}


# --- decoders: pymavlink message -> typed message -------------------------------------

_DECODERS: dict[str, Callable] = {
    "HEARTBEAT": lambda p: Heartbeat(p.type, p.autopilot, p.base_mode, p.custom_mode, p.system_status, p.mavlink_version),
    "LOCAL_POSITION_NED": lambda p: LocalPositionNed(p.time_boot_ms, p.x, p.y, p.z, p.vx, p.vy, p.vz),
    "ATTITUDE": lambda p: Attitude(p.time_boot_ms, p.roll, p.pitch, p.yaw, p.rollspeed, p.pitchspeed, p.yawspeed),
    "GLOBAL_POSITION_INT": lambda p: GlobalPositionInt(
        p.time_boot_ms,
        p.lat * 1e-7,
        p.lon * 1e-7,
        p.alt * 1e-3,
        p.relative_alt * 1e-3,
        p.vx * 1e-2,
        p.vy * 1e-2,
        p.vz * 1e-2,
        None if p.hdg == 65535 else p.hdg * 1e-2,
    ),
    "GPS_GLOBAL_ORIGIN": lambda p: GpsGlobalOrigin(p.latitude * 1e-7, p.longitude * 1e-7, p.altitude * 1e-3, p.time_usec),
    "HOME_POSITION": lambda p: HomePosition(p.latitude * 1e-7, p.longitude * 1e-7, p.altitude * 1e-3, p.x, p.y, p.z),
    "SYS_STATUS": lambda p: SysStatus(
        p.onboard_control_sensors_present,
        p.onboard_control_sensors_enabled,
        p.onboard_control_sensors_health,
        p.load,
        p.voltage_battery * 1e-3,
        None if p.current_battery == -1 else p.current_battery * 1e-2,
        p.battery_remaining,
    ),
    "EXTENDED_SYS_STATE": lambda p: ExtendedSysState(p.vtol_state, p.landed_state),
    "COMMAND_LONG": lambda p: CommandLong(
        p.target_system,
        p.target_component,
        p.command,
        (p.param1, p.param2, p.param3, p.param4, p.param5, p.param6, p.param7),
        p.confirmation,
    ),
    "COMMAND_INT": lambda p: CommandInt(
        p.target_system, p.target_component, p.command, p.frame, (p.param1, p.param2, p.param3, p.param4), p.x, p.y, p.z
    ),
    "COMMAND_ACK": lambda p: CommandAck(
        p.command, p.result, p.target_system, p.target_component, p.progress, p.result_param2
    ),
    "SET_MODE": lambda p: SetMode(p.target_system, p.base_mode, p.custom_mode),
    "SET_POSITION_TARGET_LOCAL_NED": lambda p: SetPositionTargetLocalNed(
        p.time_boot_ms,
        p.target_system,
        p.target_component,
        p.coordinate_frame,
        p.type_mask,
        p.x,
        p.y,
        p.z,
        p.vx,
        p.vy,
        p.vz,
        p.afx,
        p.afy,
        p.afz,
        p.yaw,
        p.yaw_rate,
    ),
    "PARAM_VALUE": lambda p: ParamValue(_str(p.param_id), p.param_value, p.param_type, p.param_count, p.param_index),
    "PARAM_SET": lambda p: ParamSet(p.target_system, p.target_component, _str(p.param_id), p.param_value, p.param_type),
    "PARAM_REQUEST_READ": lambda p: ParamRequestRead(p.target_system, p.target_component, _str(p.param_id), p.param_index),
    "PARAM_REQUEST_LIST": lambda p: ParamRequestList(p.target_system, p.target_component),
    "STATUSTEXT": lambda p: StatusText(p.severity, _str(p.text)),
    "AUTOPILOT_VERSION": lambda p: AutopilotVersion(p.capabilities, p.flight_sw_version, p.uid),
    "ADSB_VEHICLE": lambda p: AdsbVehicle(
        p.ICAO_address,
        p.lat,
        p.lon,
        p.altitude_type,
        p.altitude,
        p.heading,
        p.hor_velocity,
        p.ver_velocity,
        _str(p.callsign),
        p.emitter_type,
        p.tslc,
        p.flags,
        p.squawk,
    ),
    "NAMED_VALUE_INT": lambda p: NamedValueInt(p.time_boot_ms, _str(p.name), p.value),
}


class MavCodec:
    """Packs typed messages as MAVLink 2 packets from one (system, component) and parses
    a byte stream into ``Received`` messages. Not thread-safe: use one per stream
    direction, or guard it (``MavlinkPort`` does)."""

    def __init__(self, source_system: int, source_component: int, signing: SigningConfig | None = None) -> None:
        if not (0 < source_system < 256 and 0 <= source_component < 256):
            raise ValueError(f"bad MAVLink source ids {source_system}/{source_component}")
        self.source_system = source_system
        self.source_component = source_component
        self.signing = signing
        self._tx = _mavlink.MAVLink(None, source_system, source_component)
        self._rx = _mavlink.MAVLink(None, 0, 0)  # no key here: signatures are checked by _verifier
        self._rx.robust_parsing = True
        self._verifier: SignatureVerifier | None = None
        if signing is not None:
            self._tx.signing.secret_key = bytes(signing.key)
            self._tx.signing.link_id = signing.link_id
            self._tx.signing.sign_outgoing = True
            self._tx.signing.timestamp = signing_timestamp_now()
            self._verifier = SignatureVerifier(signing.key)

    def encode(self, msg: Message) -> bytes:
        """One MAVLink 2 packet carrying ``msg`` (sequence number advances)."""
        typed = _TYPED_PACKERS.get(type(msg))
        if typed is not None and self.signing is None:   # the hot types: no pymavlink object (_FAST_TYPED)
            tx = self._tx
            seq = tx.seq
            pack, values, msg_id, crc_extra_byte = typed
            packet = _frame(pack(*values(msg)), msg_id, crc_extra_byte, seq, self.source_system, self.source_component)
            tx.seq = (seq + 1) % 256
            return packet
        try:
            enc = _ENCODERS[type(msg)]
        except KeyError:
            raise TypeError(f"cannot encode {type(msg).__name__}") from None
        if self.signing is not None:  # spec: timestamp = max(last + 1, now); pymavlink adds the + 1
            self._tx.signing.timestamp = max(self._tx.signing.timestamp, signing_timestamp_now())
            packet = bytes(enc(self._tx, msg).pack(self._tx))
        else:
            m = enc(self._tx, msg)
            spec = _FAST_ENCODE.get(type(m).id)        # (the class constant: STATUSTEXT has a field named id)
            packet = (bytes(m.pack(self._tx)) if spec is None
                      else _pack_fast(spec, m, self._tx.seq, self.source_system, self.source_component))
        self._tx.seq = (self._tx.seq + 1) % 256
        return packet

    def reset_parser(self) -> int:
        """Drop any partial packet held by the parser; returns how many bytes were dropped."""
        dropped = len(self._rx.buf) - self._rx.buf_index
        self._rx.buf = bytearray()
        self._rx.buf_index = 0
        self._rx.expected_length = _mavlink.HEADER_LEN_V1 + 2
        self._rx.have_prefix_error = False
        return max(0, dropped)

    def decode_datagram(self, data: bytes, received_monotonic_s: float | None = None) -> list[Received]:
        """Parse one UDP datagram, which holds whole packets only: a trailing partial
        packet is reported as ``BadData`` instead of swallowing the next datagram.

        A datagram of unsigned MAVLink 2 packets of the hot telemetry types only (``_FAST``:
        what a vehicle streams, and setpoints) is framed and unpacked here with pymavlink's own
        struct layouts and CRC, giving the same messages as pymavlink's parser at a fraction
        of its per-packet cost (a traffic set is up to N packets per control step); anything
        else, or anything that does not check out, goes through pymavlink."""
        now = time.monotonic() if received_monotonic_s is None or not math.isfinite(received_monotonic_s) else received_monotonic_s
        if self._verifier is None and len(self._rx.buf) == self._rx.buf_index:
            fast = _decode_fast(data, now)
            if fast is not None:
                return fast
        out = self.decode(data, received_monotonic_s)
        dropped = self.reset_parser()
        if dropped:
            out.append(Received(BadData("truncated packet", dropped, time.monotonic()), 0, 0, b""))
        return out

    def decode(self, data: bytes, received_monotonic_s: float | None = None) -> list[Received]:
        """Parse ``data`` (any chunking; state is kept between calls). Bad bytes come back
        as ``BadData`` messages, never as an exception. Messages are stamped
        ``received_monotonic_s`` (when the bytes arrived, if the caller knows) or now."""
        now = time.monotonic() if received_monotonic_s is None or not math.isfinite(received_monotonic_s) else received_monotonic_s
        out: list[Received] = []
        try:
            parsed = self._rx.parse_buffer(data) or []
        except Exception as exc:  # pymavlink raises on some malformed input even when robust
            self.reset_parser()
            return [Received(BadData(f"parser error: {exc}", len(data), now), 0, 0, b"")]
        for p in parsed:
            r = self._typed(p, now)
            if r.raw:
                r = replace(r, signature=self._signature_status(r))
            out.append(r)
        return out

    def _signature_status(self, r: Received) -> str:
        if self._verifier is not None:
            return self._verifier.verify(r.raw, r.src_system, r.src_component)
        signed = len(r.raw) > 2 and r.raw[0] == 0xFD and r.raw[2] & IFLAG_SIGNED
        return SIG_UNCHECKED if signed else SIG_UNSIGNED

    @staticmethod
    def _typed(p, now: float) -> Received:
        name = p.get_type()
        if name == "BAD_DATA":
            return Received(BadData(str(p.reason), len(p.data), now), 0, 0, bytes(p.data))
        raw = bytes(p.get_msgbuf())
        src_sys, src_comp = p.get_srcSystem(), p.get_srcComponent()
        dec = _DECODERS.get(name)
        if dec is None:
            return Received(UnknownMessage(p.get_msgId(), name, now), src_sys, src_comp, raw)
        try:
            msg = dec(p)
        except Exception as exc:
            return Received(BadData(f"cannot decode {name}: {exc}", len(raw), now), src_sys, src_comp, raw)
        return Received(replace(msg, received_monotonic_s=now), src_sys, src_comp, raw)


def read_tlog_raw(path: str):
    """Yield ``(timestamp_s, Received)`` for every packet of a tlog, read with pymavlink's
    own ``mavutil.mavlink_connection`` (proves the file is readable by pymavlink tools)."""
    from pymavlink import mavutil

    mlog = mavutil.mavlink_connection(str(path), dialect="common")
    try:
        while True:
            p = mlog.recv_match()
            if p is None:
                return
            ts = getattr(p, "_timestamp", math.nan)
            yield ts, MavCodec._typed(p, math.nan)
    finally:
        mlog.close()


_TLOG_STAMP_BYTES = 8


def read_tlog_selected(path: str, msg_ids: frozenset[int]):
    """Yield ``(timestamp_s, Received)`` for the packets of a tlog whose message id is in
    ``msg_ids``, in file order. Records (8-byte stamp + one MAVLink 1/2 packet, as
    ``TlogWriter`` writes them) are framed from their headers and only the selected packets
    are parsed (by pymavlink), so a tlog full of other traffic is read in a fraction of
    ``read_tlog_raw``'s time. Returns None (the caller falls back to ``read_tlog_raw``) if a
    record does not frame, e.g. a tlog written by another tool."""
    data = open(path, "rb").read()
    out: list = []
    parser = _mavlink.MAVLink(None, 0, 0)
    parser.robust_parsing = True
    i, n = 0, len(data)
    while i < n:
        j = i + _TLOG_STAMP_BYTES
        if j + 10 > n:                    # a record cut short by a killed writer: stop there
            break
        magic = data[j]
        if magic == 0xFD:
            plen, incompat = data[j + 1], data[j + 2]
            msg_id = data[j + 7] | (data[j + 8] << 8) | (data[j + 9] << 16)
            size = 10 + plen + 2 + (13 if incompat & 0x01 else 0)
        elif magic == 0xFE:
            plen = data[j + 1]
            msg_id = data[j + 5]
            size = 6 + plen + 2
        else:
            return None
        if j + size > n:
            break
        if msg_id in msg_ids:
            ts = int.from_bytes(data[i:j], "big") * 1e-6
            packet = data[j : j + size]
            fast = _decode_fast(packet, math.nan) if magic == 0xFD else None
            if fast is not None:
                out += [(ts, r) for r in fast]
            else:
                try:
                    parsed = parser.parse_buffer(packet) or []
                except Exception:
                    parsed = []
                out += [(ts, MavCodec._typed(m, math.nan)) for m in parsed]
        i = j + size
    return out


def _crc_x25(buf: bytes, crc_extra_byte: bytes) -> int:
    """MAVLink's CRC-16/MCRF4XX of ``buf`` followed by the CRC extra byte (pymavlink's x25crc)."""
    if _MCRF4XX is not None:
        return _MCRF4XX(crc_extra_byte, _MCRF4XX(buf, 0xFFFF))
    return _mavlink.x25crc(buf + crc_extra_byte).crc


_MCRF4XX = getattr(_mavlink, "mcrf4xx", None)    # fastcrc's C implementation, when pymavlink found it


def _fast_specs(names: tuple[str, ...]) -> dict[int, tuple]:
    """msg id -> (struct, CRC extra byte, field-tuple type, decoder) for the fast decoder: the
    unpacked payload becomes a named tuple with pymavlink's field names (what ``_DECODERS`` read)."""
    specs = {}
    for name in names:
        msg_id = MAVLINK_MSG_ID[name]
        cls = _mavlink.mavlink_map[msg_id]
        if len(cls.unpacker.unpack(bytes(cls.unpacker.size))) != len(cls.ordered_fieldnames):
            continue  # a numeric array field (pymavlink regroups it): not on the fast path
        fields = collections.namedtuple(f"_{name}", cls.ordered_fieldnames, rename=True)
        if list(fields._fields) != list(cls.ordered_fieldnames):
            continue  # a field name a named tuple cannot carry
        specs[msg_id] = (cls.unpacker, bytes((cls.crc_extra,)), fields._make, _DECODERS[name])
    return specs


def _encode_specs(names: tuple[str, ...]) -> dict[int, tuple]:
    """msg id -> (struct, CRC extra byte, attribute names in wire order) for ``_pack_fast``: the
    attributes pymavlink's own ``pack`` reads (``_<name>_raw`` for char arrays)."""
    specs = {}
    for name in names:
        msg_id = MAVLINK_MSG_ID[name]
        cls = _mavlink.mavlink_map[msg_id]
        if len(cls.unpacker.unpack(bytes(cls.unpacker.size))) != len(cls.ordered_fieldnames):
            continue  # an array field: pymavlink packs it element by element
        attrs = tuple(f"_{f}_raw" if t == "char" else f for f, t in zip(cls.fieldnames, cls.fieldtypes))
        order = [cls.fieldnames.index(f) for f in cls.ordered_fieldnames]
        specs[msg_id] = (cls.unpacker, bytes((cls.crc_extra,)), tuple(attrs[i] for i in order))
    return specs


_I32_MIN, _I32_MAX, _I16_MIN, _I16_MAX = -(2**31), 2**31 - 1, -(2**15), 2**15 - 1

_FAST_TYPED: dict[type, tuple[int, Callable]] = {
    # what a vehicle sends every lockstep step (its traffic set, the marker, its telemetry): typed
    # message -> payload values in wire order, exactly the arguments ``_ENCODERS`` gives pymavlink's
    # ``*_encode`` as its ``pack`` passes them to the struct; no pymavlink object
    AdsbVehicle: (MAVLINK_MSG_ID["ADSB_VEHICLE"], lambda m: (
        m.icao_address & 0xFFFFFFFF, m.lat_e7, m.lon_e7, m.altitude_mm, m.heading_cdeg, m.hor_velocity_cm_s,
        m.ver_velocity_cm_s, m.flags, m.squawk, m.altitude_type, _s(m.callsign[:8]), m.emitter_type, m.tslc_s)),
    NamedValueInt: (MAVLINK_MSG_ID["NAMED_VALUE_INT"], lambda m: (m.time_boot_ms & 0xFFFFFFFF, m.value, _s(m.name[:10]))),
    LocalPositionNed: (MAVLINK_MSG_ID["LOCAL_POSITION_NED"], lambda m: (
        m.time_boot_ms & 0xFFFFFFFF, m.x_m, m.y_m, m.z_m, m.vx_m_s, m.vy_m_s, m.vz_m_s)),
    Attitude: (MAVLINK_MSG_ID["ATTITUDE"], lambda m: (
        m.time_boot_ms & 0xFFFFFFFF, m.roll_rad, m.pitch_rad, m.yaw_rad, m.rollspeed_rad_s, m.pitchspeed_rad_s, m.yawspeed_rad_s)),
    GlobalPositionInt: (MAVLINK_MSG_ID["GLOBAL_POSITION_INT"], lambda m: (
        m.time_boot_ms & 0xFFFFFFFF,
        _clip_i(m.lat_deg * 1e7, _I32_MIN, _I32_MAX),
        _clip_i(m.lon_deg * 1e7, _I32_MIN, _I32_MAX),
        _clip_i(m.alt_amsl_m * 1e3, _I32_MIN, _I32_MAX),
        _clip_i(m.relative_alt_m * 1e3, _I32_MIN, _I32_MAX),
        _clip_i(m.vx_m_s * 100, _I16_MIN, _I16_MAX),
        _clip_i(m.vy_m_s * 100, _I16_MIN, _I16_MAX),
        _clip_i(m.vz_m_s * 100, _I16_MIN, _I16_MAX),
        65535 if m.heading_deg is None else _clip_i((m.heading_deg % 360.0) * 100, 0, 35999))),
    Heartbeat: (MAVLINK_MSG_ID["HEARTBEAT"], lambda m: (
        m.custom_mode & 0xFFFFFFFF, m.type, m.autopilot, m.base_mode & 0xFF, m.system_status, m.mavlink_version)),
}


def _frame(payload: bytes, msg_id: int, crc_extra_byte: bytes, seq: int, src_system: int, src_component: int) -> bytes:
    trimmed = payload.rstrip(b"\x00") or payload[:1]    # trailing zero bytes trimmed, at least one kept
    body = _HEADER_V2.pack(len(trimmed), 0, 0, seq, src_system, src_component, msg_id & 0xFFFF, msg_id >> 16) + trimmed
    return b"\xfd" + body + _CRC.pack(_crc_x25(body, crc_extra_byte))


def _pack_fast(spec: tuple, m, seq: int, src_system: int, src_component: int) -> bytes:
    """An unsigned MAVLink 2 packet of pymavlink message ``m``, byte for byte what
    ``m.pack(mav)`` gives (trailing zero bytes of the payload trimmed, at least one kept; CRC with
    the message's CRC extra), without pymavlink's per-packet header object and bytearray copies."""
    unpacker, crc_extra_byte, attrs = spec
    return _frame(unpacker.pack(*[getattr(m, a) for a in attrs]), type(m).id, crc_extra_byte, seq, src_system, src_component)


_HEADER_V2 = struct.Struct("<BBBBBBHB")     # after the 0xFD marker: len, incompat, compat, seq, sysid, compid, msgid (24 bit)
_CRC = struct.Struct("<H")


_FAST = _fast_specs(("ADSB_VEHICLE", "NAMED_VALUE_INT", "LOCAL_POSITION_NED", "ATTITUDE", "GLOBAL_POSITION_INT",
                     "HEARTBEAT", "SET_POSITION_TARGET_LOCAL_NED", "SYS_STATUS", "EXTENDED_SYS_STATE", "HOME_POSITION",
                     "GPS_GLOBAL_ORIGIN"))
_FAST_ENCODE = _encode_specs(("ADSB_VEHICLE", "NAMED_VALUE_INT", "LOCAL_POSITION_NED", "ATTITUDE", "GLOBAL_POSITION_INT",
                              "HEARTBEAT", "SET_POSITION_TARGET_LOCAL_NED", "SYS_STATUS", "EXTENDED_SYS_STATE"))
_TYPED_PACKERS: dict[type, tuple] = {
    # typed message type -> (struct pack, wire-order values, message id, CRC extra byte): what ``MavCodec.encode`` frames
    t: (_FAST_ENCODE[msg_id][0].pack, values, msg_id, _FAST_ENCODE[msg_id][1]) for t, (msg_id, values) in _FAST_TYPED.items()
}
_new_object = object.__new__
_set_attr = object.__setattr__
_ZERO_PAD = tuple(bytes(k) for k in range(256))
"""``_ZERO_PAD[k]``: the k zero bytes a MAVLink 2 payload trimmed by k bytes lacks."""


def _message_builder(msg_id: int, fields: Callable, dec: Callable) -> Callable:
    """``build(values, now)``: the typed message of an unpacked payload (``values`` in wire
    order), stamped ``now``; the same message as ``dec(fields(values))`` (``_DECODERS``).

    A frozen dataclass's ``__init__`` sets each field through ``object.__setattr__`` (~2.5 us
    for ADSB_VEHICLE's 14 fields); the types whose decoder only renames (and, for character
    arrays, ``_str``-converts) wire fields are built with their instance dict in one step, in
    the dataclass's field order, which is what ``__init__`` leaves. Others keep the decoder."""
    cls = _mavlink.mavlink_map[msg_id]
    wire = tuple(cls.ordered_fieldnames)
    if wire == ("time_boot_ms", "x", "y", "z", "vx", "vy", "vz") and msg_id == MAVLINK_MSG_ID["LOCAL_POSITION_NED"]:
        def build(v, now, _cls=LocalPositionNed):
            t, x, y, z, vx, vy, vz = v
            msg = _new_object(_cls)
            _set_attr(msg, "__dict__", {"time_boot_ms": t, "x_m": x, "y_m": y, "z_m": z, "vx_m_s": vx, "vy_m_s": vy,
                                        "vz_m_s": vz, "received_monotonic_s": now})
            return msg
        return build
    if wire == ("time_boot_ms", "roll", "pitch", "yaw", "rollspeed", "pitchspeed", "yawspeed") and msg_id == MAVLINK_MSG_ID["ATTITUDE"]:
        def build(v, now, _cls=Attitude):
            t, r, p, y, rs, ps, ys = v
            msg = _new_object(_cls)
            _set_attr(msg, "__dict__", {"time_boot_ms": t, "roll_rad": r, "pitch_rad": p, "yaw_rad": y, "rollspeed_rad_s": rs,
                                        "pitchspeed_rad_s": ps, "yawspeed_rad_s": ys, "received_monotonic_s": now})
            return msg
        return build
    if wire == ("time_boot_ms", "value", "name") and msg_id == MAVLINK_MSG_ID["NAMED_VALUE_INT"]:
        def build(v, now, _cls=NamedValueInt):
            t, value, name = v
            msg = _new_object(_cls)
            _set_attr(msg, "__dict__", {"time_boot_ms": t, "name": name.split(b"\0", 1)[0].decode("ascii", "replace"),
                                        "value": value, "received_monotonic_s": now})
            return msg
        return build

    if wire == ("time_boot_ms", "lat", "lon", "alt", "relative_alt", "vx", "vy", "vz", "hdg") and msg_id == MAVLINK_MSG_ID["GLOBAL_POSITION_INT"]:
        def build(v, now, _cls=GlobalPositionInt):      # the scaling of _DECODERS["GLOBAL_POSITION_INT"], same expressions
            t, lat, lon, alt, rel, vx, vy, vz, hdg = v
            msg = _new_object(_cls)
            _set_attr(msg, "__dict__", {"time_boot_ms": t, "lat_deg": lat * 1e-7, "lon_deg": lon * 1e-7, "alt_amsl_m": alt * 1e-3,
                                        "relative_alt_m": rel * 1e-3, "vx_m_s": vx * 1e-2, "vy_m_s": vy * 1e-2, "vz_m_s": vz * 1e-2,
                                        "heading_deg": None if hdg == 65535 else hdg * 1e-2, "received_monotonic_s": now})
            return msg
        return build

    def build(v, now):
        msg = dec(fields(v))
        # built just now and not shared yet: stamped in place (replace() would re-run __init__)
        _set_attr(msg, "received_monotonic_s", now)
        return msg
    return build


_ADSB_WIRE = ("ICAO_address", "lat", "lon", "altitude", "heading", "hor_velocity", "ver_velocity", "flags", "squawk",
              "altitude_type", "callsign", "emitter_type", "tslc")


def _rx_specs() -> dict[int, tuple]:
    """msg id -> (payload size, CRC extra byte, unpack, unpack_from, build) for ``_decode_fast``;
    build is None for ADSB_VEHICLE (the bulk of a traffic set), which the loop builds inline."""
    specs = {}
    for msg_id, (unpacker, crc_extra_byte, fields, dec) in _FAST.items():
        build = _message_builder(msg_id, fields, dec)
        if msg_id == MAVLINK_MSG_ID["ADSB_VEHICLE"] and tuple(_mavlink.mavlink_map[msg_id].ordered_fieldnames) == _ADSB_WIRE:
            build = None
        specs[msg_id] = (unpacker.size, crc_extra_byte, unpacker.unpack, unpacker.unpack_from, build)
    return specs


def _decode_fast(data: bytes, now: float) -> list[Received] | None:
    """Every packet of ``data`` if all are unsigned MAVLink 2 packets of ``_FAST`` types with
    a good CRC; else None (the caller uses pymavlink).

    The same ``Received`` messages as pymavlink's parser gives (ids, raw bytes, values; see
    ``_message_builder``), at a fraction of its cost: this runs for every frame of a traffic
    set, ~28 per control step, on the controller's receive thread."""
    out: list[Received] = []
    append = out.append
    crc_x25, new, set_attr, pad = _crc_x25, _new_object, _set_attr, _ZERO_PAD
    cs_raw = cs_str = None              # the callsign last decoded (a traffic set's reports share one tag)
    i, n = 0, len(data)
    while i < n:
        if data[i] != 0xFD or i + 12 > n or data[i + 2] != 0:
            return None
        plen = data[i + 1]
        end = i + 12 + plen
        if end > n:
            return None
        spec = _RX.get(data[i + 7] | (data[i + 8] << 8) | (data[i + 9] << 16))
        if spec is None:
            return None
        size, crc_extra_byte, unpack, unpack_from, build = spec
        if plen > size or crc_x25(data[i + 1 : end - 2], crc_extra_byte) != (data[end - 2] | (data[end - 1] << 8)):
            return None
        # MAVLink 2 trims trailing zero bytes of the payload: put them back
        v = unpack_from(data, i + 10) if plen == size else unpack(data[i + 10 : end - 2] + pad[size - plen])
        if build is None:               # ADSB_VEHICLE: _DECODERS["ADSB_VEHICLE"], field by field
            icao, lat, lon, alt, hdg, hvel, vvel, flags, squawk, alt_type, cs, emitter, tslc = v
            if cs != cs_raw:
                cs_raw, cs_str = cs, cs.split(b"\0", 1)[0].decode("ascii", "replace")   # = _str(cs)
            msg = new(AdsbVehicle)
            set_attr(msg, "__dict__", {
                "icao_address": icao, "lat_e7": lat, "lon_e7": lon, "altitude_type": alt_type, "altitude_mm": alt,
                "heading_cdeg": hdg, "hor_velocity_cm_s": hvel, "ver_velocity_cm_s": vvel, "callsign": cs_str,
                "emitter_type": emitter, "tslc_s": tslc, "flags": flags, "squawk": squawk, "received_monotonic_s": now})
        else:
            try:
                msg = build(v, now)
            except Exception:
                return None
        r = new(Received)               # Received(msg, sysid, compid, raw, SIG_UNSIGNED) without its __init__
        set_attr(r, "__dict__", {"msg": msg, "src_system": data[i + 5], "src_component": data[i + 6], "raw": data[i:end],
                                 "signature": SIG_UNSIGNED})
        append(r)
        i = end
    return out


_RX = _rx_specs()
