"""mavlink_bridge without any vehicle process: codec, masks, modes, connection strings,
tlog, target filtering of setpoints, and the typed errors of waits."""

from __future__ import annotations

import math
import socket
import time

import pytest

from _net import free_udp_port
from mavlink_bridge import (
    ACC_ONLY_TYPE_MASK,
    PX4_HOLD,
    PX4_LAND,
    PX4_OFFBOARD,
    Attitude,
    BadData,
    CommandAck,
    CommandLong,
    CommandTimeout,
    ConnectionStringError,
    GlobalPositionInt,
    Heartbeat,
    HeartbeatTimeout,
    GpsGlobalOrigin,
    HomePosition,
    LocalPositionNed,
    MavlinkPort,
    ParamValue,
    PositionTargetTypeMask,
    Px4Mode,
    SetPositionTargetLocalNed,
    StatusText,
    TelemetryTimeout,
    TlogWriter,
    UnknownMessage,
    VehicleLink,
    acceleration_setpoint,
    altitude_hold_setpoint,
    parse_connection_string,
    read_tlog,
)
from mavlink_bridge.codec import MavCodec


def test_acc_only_mask_is_3135_built_from_named_flags():
    F = PositionTargetTypeMask
    assert int(ACC_ONLY_TYPE_MASK) == 3135 == 0x0C3F
    assert ACC_ONLY_TYPE_MASK == F.X_IGNORE | F.Y_IGNORE | F.Z_IGNORE | F.VX_IGNORE | F.VY_IGNORE | F.VZ_IGNORE | F.YAW_IGNORE | F.YAW_RATE_IGNORE
    assert not ACC_ONLY_TYPE_MASK & F.FORCE_SET


def test_px4_custom_modes_match_spec():
    # SPEC 4: custom_mode = main_mode << 16; OFFBOARD = 6 -> 0x00060000
    assert PX4_OFFBOARD.custom_mode == 0x00060000
    assert PX4_HOLD.custom_mode == (4 << 16) | (3 << 24)
    assert PX4_LAND.custom_mode == (4 << 16) | (6 << 24)
    assert Px4Mode.from_custom_mode(0x00060000) == PX4_OFFBOARD
    hb = Heartbeat(base_mode=1 | 128, custom_mode=0x00060000)
    assert hb.armed and hb.is_offboard and hb.px4_mode.name == "OFFBOARD"
    assert not Heartbeat(base_mode=1, custom_mode=PX4_HOLD.custom_mode).is_offboard


@pytest.mark.parametrize(
    "msg",
    [
        Heartbeat(base_mode=129, custom_mode=0x60000),
        LocalPositionNed(123, 1.5, -2.25, -10.0, 0.5, -0.5, 0.0),
        Attitude(5, 0.125, -0.25, 0.0),
        acceleration_setpoint(3, 1, (1.0, -0.5, 0.0), 4000),
        CommandLong(1, 1, 176, (1.0, 6.0, 0.0, 0.0, 0.0, 0.0, 0.0), 2),
        CommandAck(400, 2, 1, 191),
        ParamValue("COM_OF_LOSS_T", 1.5, 9, 10, 0),
        StatusText(4, "Failsafe"),
        HomePosition(47.5, 8.5, 488.0),
        HomePosition(47.5, 8.5, 488.0, 1.5, -2.0, 0.0),
        GpsGlobalOrigin(47.25, 8.5, 501.5, 1234567),
        altitude_hold_setpoint(3, 1, (0.5, -0.25), -20.0, 4000),
    ],
)
def test_codec_round_trip(msg):
    packet = MavCodec(7, 191).encode(msg)
    assert packet[0] == 0xFD  # MAVLink 2
    (r,) = MavCodec(1, 1).decode(packet)
    assert (r.src_system, r.src_component) == (7, 191)
    assert r.msg == msg
    assert r.raw == packet


def test_global_position_int_units():
    msg = GlobalPositionInt(10, 47.3977421, 8.5455941, 498.0, 10.0, 1.25, -0.5, 0.0, None)
    (r,) = MavCodec(1, 1).decode(MavCodec(1, 1).encode(msg))
    assert r.msg.lat_deg == pytest.approx(47.3977421, abs=1e-7)
    assert r.msg.alt_amsl_m == pytest.approx(498.0) and r.msg.vx_m_s == pytest.approx(1.25)


def test_garbage_decodes_to_bad_data_never_raises():
    codec = MavCodec(1, 1)
    good = MavCodec(2, 1).encode(Heartbeat())
    out = codec.decode_datagram(b"\x00garbage\xfd\x05" + bytes(range(40)))
    # pymavlink cannot check the CRC of an unknown message id, so garbage may also
    # surface as UnknownMessage; never as a modelled message, never as an exception
    assert any(isinstance(r.msg, BadData) for r in out)
    assert all(isinstance(r.msg, (BadData, UnknownMessage)) for r in out)
    (r,) = codec.decode_datagram(good)  # the parser recovered
    assert isinstance(r.msg, Heartbeat)


def test_setpoint_rejects_non_finite():
    with pytest.raises(ValueError, match="finite"):
        acceleration_setpoint(1, 1, (math.nan, 0.0, 0.0), 0)


@pytest.mark.parametrize(
    "url, scheme, host, port",
    [
        ("udpin:127.0.0.1:14540", "udpin", "127.0.0.1", 14540),
        ("udpin://127.0.0.1:14541", "udpin", "127.0.0.1", 14541),
        ("udp:0.0.0.0:14550", "udpin", "0.0.0.0", 14550),
        ("udpout:127.0.0.1:14550", "udpout", "127.0.0.1", 14550),
        ("tcp:127.0.0.1:5760", "tcp", "127.0.0.1", 5760),
    ],
)
def test_parse_connection_string(url, scheme, host, port):
    ep = parse_connection_string(url)
    assert (ep.scheme, ep.host, ep.port) == (scheme, host, port)


def test_parse_serial_and_errors():
    assert parse_connection_string("/dev/ttyUSB0:921600").device == "/dev/ttyUSB0"
    assert parse_connection_string("serial:/dev/ttyACM0,57600").baud == 57600
    with pytest.raises(ConnectionStringError, match="unknown connection string"):
        parse_connection_string("bogus")
    with pytest.raises(ConnectionStringError, match="port"):
        parse_connection_string("udpout:127.0.0.1:notaport")


def test_tlog_is_readable_by_pymavlink(tmp_path):
    path = tmp_path / "x.tlog"
    codec = MavCodec(1, 1)
    msgs = [Heartbeat(), LocalPositionNed(1, 1.0, 2.0, -10.0, 0.0, 0.0, 0.0), StatusText(6, "hi")]
    with TlogWriter(path) as tlog:
        for i, m in enumerate(msgs):
            tlog.write(codec.encode(m), unix_time_s=1_700_000_000.0 + i)
    records = read_tlog(path)
    assert [r.msg for _, r in records] == msgs
    assert records[0][0] == pytest.approx(1_700_000_000.0)


def test_wait_heartbeat_times_out_with_typed_error():
    with VehicleLink.open(f"udpin:127.0.0.1:{free_udp_port()}", target_system=3) as link:
        t0 = time.monotonic()
        with pytest.raises(HeartbeatTimeout, match="no HEARTBEAT from system 3 component 1 within 0.3 s"):
            link.wait_heartbeat(timeout_s=0.3)
        assert time.monotonic() - t0 < 1.0
        with pytest.raises(TelemetryTimeout, match="LOCAL_POSITION_NED"):
            link.wait_local_position(None, timeout_s=0.1)
        assert link.heartbeat_age_s() == math.inf and link.telemetry_age_s() == math.inf


def test_target_system_zero_is_refused():
    with pytest.raises(ValueError, match="never broadcast"):
        VehicleLink.open(f"udpin:127.0.0.1:{free_udp_port()}", target_system=0)


class _FakeVehicle:
    """A UDP socket standing in for vehicle ``sysid``: records what the link sends."""

    def __init__(self, sysid: int):
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.05)
        self.codec = MavCodec(sysid, 1)
        self.port = self.sock.getsockname()[1]

    def received(self, duration_s: float):
        out, end = [], time.monotonic() + duration_s
        while time.monotonic() < end:
            try:
                data, addr = self.sock.recvfrom(65535)
            except socket.timeout:
                continue
            self.addr = addr
            out += self.codec.decode_datagram(data)
        return out

    def close(self):
        self.sock.close()


def test_setpoints_go_only_to_the_target_system(tmp_path):
    fake = _FakeVehicle(sysid=4)
    try:
        with VehicleLink.open(f"udpout:127.0.0.1:{fake.port}", target_system=4, target_component=1, tlog_path=str(tmp_path / "c.tlog")) as link:
            link.send_acc_setpoint((0.5, -0.25, 0.0), time_boot_ms=1000)
            link.start_setpoint_stream(rate_hz=50, acc_ned_m_s2=(1.0, 0.0, 0.0))
            got = fake.received(0.4)
            link.stop_setpoint_stream()
        sps = [r for r in got if isinstance(r.msg, SetPositionTargetLocalNed)]
        assert len(sps) >= 10
        for r in sps:
            assert (r.msg.target_system, r.msg.target_component) == (4, 1)
            assert r.msg.type_mask == 3135 and r.msg.coordinate_frame == 1
            assert (r.src_system, r.src_component) == (1, 191)
        assert sps[0].msg.time_boot_ms == 1000 and sps[0].msg.acc_ned_m_s2 == (0.5, -0.25, 0.0)
        assert any(isinstance(r.msg, Heartbeat) for r in got)  # companion heartbeat
        logged = [r.msg for _, r in read_tlog(tmp_path / "c.tlog") if isinstance(r.msg, SetPositionTargetLocalNed)]
        assert logged and all(m.target_system == 4 for m in logged)
    finally:
        fake.close()


def test_command_without_ack_times_out_after_retransmissions():
    fake = _FakeVehicle(sysid=2)
    try:
        with VehicleLink.open(f"udpout:127.0.0.1:{fake.port}", target_system=2) as link:
            with pytest.raises(CommandTimeout, match="COMPONENT_ARM_DISARM.*system 2"):
                link.arm(timeout_s=1.2)
    finally:
        fake.close()


def test_link_ignores_other_systems():
    """Telemetry from system 9 must not pass for the target's (system 2)."""
    port = free_udp_port()
    with VehicleLink.open(f"udpin:127.0.0.1:{port}", target_system=2) as link:
        other = MavlinkPort.open(f"udpout:127.0.0.1:{port}", 9, 1)
        me = MavlinkPort.open(f"udpout:127.0.0.1:{port}", 2, 1)
        try:
            other.send(Heartbeat())
            other.send(LocalPositionNed(5, 9.0, 9.0, 0.0, 0.0, 0.0, 0.0))
            time.sleep(0.2)
            assert link.latest_heartbeat() is None and link.latest_local_position() is None
            assert link.n_ignored_other_system >= 2
            me.send(LocalPositionNed(6, 1.0, 2.0, -10.0, 0.0, 0.0, 0.0))
            p = link.wait_local_position(5, timeout_s=1.0)
            assert (p.x_m, p.y_m) == (1.0, 2.0) and not math.isnan(p.received_monotonic_s)
        finally:
            other.close()
            me.close()


def test_mode_change_acked_but_never_seen_is_mode_not_confirmed():
    """A vehicle that ACKs DO_SET_MODE but keeps reporting HOLD in its HEARTBEAT."""
    import threading

    from mavlink_bridge import ModeNotConfirmed

    fake = _FakeVehicle(sysid=1)
    stop = threading.Event()

    def serve():
        while not stop.is_set():
            for r in fake.received(0.05):
                if isinstance(r.msg, CommandLong):
                    fake.sock.sendto(fake.codec.encode(CommandAck(r.msg.command, 0, r.src_system, r.src_component)), fake.addr)
            if hasattr(fake, "addr"):
                fake.sock.sendto(fake.codec.encode(Heartbeat(base_mode=1, custom_mode=PX4_HOLD.custom_mode)), fake.addr)

    th = threading.Thread(target=serve, daemon=True)
    th.start()
    try:
        with VehicleLink.open(f"udpout:127.0.0.1:{fake.port}", target_system=1) as link:
            link.wait_heartbeat(timeout_s=3.0)
            with pytest.raises(ModeNotConfirmed, match="OFFBOARD not confirmed.*last seen: AUTO.LOITER"):
                link.set_mode(PX4_OFFBOARD, timeout_s=0.8)
    finally:
        stop.set()
        th.join(2.0)
        fake.close()


# ---------------------------------------------------------------- hot-path I/O (issue 8)
def _telemetry_mix(seed: int):
    import numpy as np

    from mavlink_bridge import ExtendedSysState, NamedValueInt, SysStatus
    from mock_vehicle.proximity import traffic_reports

    rng = np.random.default_rng(seed)
    msgs = list(traffic_reports(np.arange(30), rng.normal(size=(30, 4)) * 50, 1500, (47.397742, 8.545594), 498.0))
    return msgs + [NamedValueInt(1500, "TRAFFIC_N", 30), LocalPositionNed(1500, 1.5, -2.25, -10.0, 0.1, 0.0, 0.0),
                   Attitude(1500, 0.1, -0.2, 0.0), GlobalPositionInt(1500, 47.4, 8.5, 498.0, 10.0, 1.0, -1.0, 0.0, None),
                   Heartbeat(), acceleration_setpoint(7, 1, (0.5, -0.25, 0.0), 1500), ExtendedSysState(0, 2),
                   SysStatus(load_permille=100, voltage_battery_v=16.2, battery_remaining_pct=100),
                   GpsGlobalOrigin(47.3977419, 8.5455938, 488.125, 1234567), GpsGlobalOrigin(-33.9, 151.2, -12.5, 0)]


def test_origin_and_home_encode_byte_for_byte_as_pymavlink_packs_their_wire_values():
    """GPS_GLOBAL_ORIGIN and HOME_POSITION (issue 19): MavCodec.encode gives the bytes pymavlink's own
    encoder packs from the wire values (degE7, mm, rounded; local x, y, z as float32), for random and
    edge values, and decoding gives the typed message back within that quantisation."""
    import random

    from mavlink_bridge import codec as C

    rng = random.Random(19)
    fast, ref = MavCodec(9, 1), MavCodec(9, 1)
    for i in range(300):
        lat, lon = rng.uniform(-90.0, 90.0), rng.uniform(-180.0, 180.0)
        alt = rng.choice((0.0, -0.0004, 488.0005, 8848.86, -430.5, rng.uniform(-500.0, 9000.0)))
        x, y, z = (rng.choice((0.0, -1e-7, rng.uniform(-3000.0, 3000.0))) for _ in range(3))
        t_us = rng.choice((0, 1, 2**63 - 1, rng.randrange(2**40)))
        for m, wire in (
            (GpsGlobalOrigin(lat, lon, alt, t_us), ref._tx.gps_global_origin_encode(round(lat * 1e7), round(lon * 1e7), round(alt * 1e3), t_us)),
            (HomePosition(lat, lon, alt, x, y, z), ref._tx.home_position_encode(round(lat * 1e7), round(lon * 1e7), round(alt * 1e3), x, y, z,
                                                                                [1.0, 0.0, 0.0, 0.0], 0.0, 0.0, 0.0)),
        ):
            packet = fast.encode(m)
            assert packet == bytes(wire.pack(ref._tx)), (i, m)
            ref._tx.seq = (ref._tx.seq + 1) % 256
            (r,) = MavCodec(1, 1).decode(packet)
            assert type(r.msg) is type(m) and (r.msg.lat_deg, r.msg.lon_deg) == pytest.approx((lat, lon), abs=1e-7)
            assert r.msg.alt_amsl_m == pytest.approx(alt, abs=1e-3)
    assert C.MAVLINK_MSG_ID["GPS_GLOBAL_ORIGIN"] in C._RX        # on the fast receive path too (test above)


def test_fast_datagram_decoding_equals_pymavlink():
    """Given datagrams of several telemetry packets, decode_datagram's fast path gives exactly
    what pymavlink's parser gives (message, ids, raw bytes, signature status, stamp); a
    datagram with a bad CRC or a type off the fast path still goes through pymavlink."""
    import random

    from mavlink_bridge import codec as C

    packets = [MavCodec(7, 1).encode(m) for m in _telemetry_mix(1)]
    for trial in range(100):
        sel = random.Random(trial).sample(packets, random.Random(trial).randint(1, 25))
        data = b"".join(sel)
        fast = C._decode_fast(data, 5.0)
        ref = MavCodec(1, 1).decode(data, 5.0)
        assert fast is not None and len(fast) == len(ref) == len(sel)
        for a, b in zip(fast, ref):
            assert (a.msg, a.src_system, a.src_component, a.raw, a.signature) == (b.msg, b.src_system, b.src_component, b.raw, b.signature)
            assert a.msg.received_monotonic_s == b.msg.received_monotonic_s == 5.0
    bad = bytearray(packets[0])
    bad[-1] ^= 1
    assert C._decode_fast(bytes(bad), 0.0) is None
    assert isinstance(MavCodec(1, 1).decode_datagram(bytes(bad))[0].msg, BadData)
    assert C._decode_fast(MavCodec(1, 1).encode(StatusText(4, "hello")), 0.0) is None
    assert C._decode_fast(packets[0][:-3], 0.0) is None


def test_fast_encoding_equals_pymavlink_byte_for_byte():
    """Given the hot telemetry types (random values, all-zero payloads, sequence numbers
    wrapping past 255), MavCodec.encode's own packer gives exactly the bytes of pymavlink's
    ``pack``; a signing codec still packs with pymavlink."""
    import random

    import numpy as np

    from mavlink_bridge import NamedValueInt
    from mavlink_bridge import codec as C
    from mavlink_bridge.signing import SigningConfig

    msgs = _telemetry_mix(2) + [LocalPositionNed(0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0), NamedValueInt(0, "", 0),
                                Heartbeat(type=0, autopilot=0, base_mode=0, custom_mode=0, system_status=0, mavlink_version=0)]
    rng = random.Random(3)
    msgs += [LocalPositionNed(rng.randrange(2**32), *(rng.uniform(-1e4, 1e4) for _ in range(6))) for _ in range(50)]
    assert {C.MAVLINK_MSG_ID[n] for n in ("ADSB_VEHICLE", "LOCAL_POSITION_NED", "SET_POSITION_TARGET_LOCAL_NED")} <= set(C._FAST_ENCODE)
    fast, ref = MavCodec(9, 1), MavCodec(9, 1)
    for i in range(600):
        m = msgs[i % len(msgs)]
        expected = bytes(C._ENCODERS[type(m)](ref._tx, m).pack(ref._tx))
        ref._tx.seq = (ref._tx.seq + 1) % 256
        assert fast.encode(m) == expected, (i, m)
    signed = MavCodec(9, 1, SigningConfig(bytes(range(32)), 0))
    packet = signed.encode(LocalPositionNed(5, 1.0, 2.0, 3.0, 0.0, 0.0, 0.0))
    assert packet[2] & 0x01 and len(packet) == 12 + packet[1] + 13     # signed: pymavlink's path
    assert np.all([isinstance(r.msg, LocalPositionNed) for r in MavCodec(1, 1).decode_datagram(fast.encode(msgs[-1]))])


def test_selective_tlog_read_equals_the_full_read(tmp_path):
    """read_tlog(only=...) returns the same records as the pymavlink read, filtered, also when
    the last record was cut short by a killed writer."""
    path = tmp_path / "t.tlog"
    codec = MavCodec(3, 1)
    with TlogWriter(path) as tlog:
        for i, m in enumerate(_telemetry_mix(2) * 3):
            tlog.write(codec.encode(m), unix_time_s=1_700_000_000.0 + 0.01 * i)
    with open(path, "ab") as fh:
        fh.write(b"\x00" * 8 + codec.encode(LocalPositionNed(9, 1.0, 2.0, 3.0, 0.0, 0.0, 0.0))[:7])
    only = ("LOCAL_POSITION_NED", "SET_POSITION_TARGET_LOCAL_NED")
    got = read_tlog(path, only=only)
    ref = [(t, r) for t, r in read_tlog(path) if r.msg.MSG_NAME in only]
    assert len(got) == len(ref) == 6
    assert [(t, r.msg, r.src_system, r.raw) for t, r in got] == [(t, r.msg, r.src_system, r.raw) for t, r in ref]


def test_send_many_packs_datagrams_in_order_and_logs_every_packet(tmp_path):
    rx_port = free_udp_port()
    rx = MavlinkPort.open(f"udpin:127.0.0.1:{rx_port}", 2, 1)
    with TlogWriter(tmp_path / "tx.tlog") as tlog:
        tx = MavlinkPort.open(f"udpout:127.0.0.1:{rx_port}", 1, 1, tlog)
        msgs = _telemetry_mix(3)
        tx.send_many(msgs)
        got, datagrams = [], 0
        while len(got) < len(msgs):
            r = rx.recv(2.0)
            assert r, "datagram lost on loopback"
            datagrams += 1
            got += [x.msg for x in r]
        tx.close()
    rx.close()
    logged = [r.msg for _, r in read_tlog(tmp_path / "tx.tlog")]
    assert got == logged and [type(m) for m in got] == [type(m) for m in msgs]   # in order (floats as float32)
    assert 2 <= datagrams < len(msgs) // 4                  # packed, each below MAX_DATAGRAM_BYTES


def test_received_stamp_is_the_arrival_not_the_read():
    """A datagram read 50 ms after it arrived carries its arrival time (kernel timestamp).

    Linux turns arrival stamping on for the whole host when the first socket asks for it, through deferred work
    (net_enable_timestamp): until that has run, a datagram is stamped when it is read (measured: the first datagram
    of a fresh process carried its read time in 3 of 30 runs; seen in CI). One datagram is exchanged first, and the
    measured one is sent 20 ms later. Arrival is when the socket became readable."""
    import select

    from mavlink_bridge.transport import open_transport

    a = open_transport("udpin:127.0.0.1:0")
    b = open_transport(f"udpout:127.0.0.1:{a.local_address[1]}")
    try:
        b.send(MavCodec(1, 1).encode(Heartbeat()))
        assert a.recv(1.0) is not None
        time.sleep(0.02)
        b.send(MavCodec(1, 1).encode(Heartbeat()))
        assert select.select([a], [], [], 1.0)[0], "the datagram never arrived"
        arrived = time.monotonic()
        time.sleep(0.05)
        assert a.recv(1.0) is not None
        read = time.monotonic()
        if a._kernel_stamps:
            assert a.last_rx_monotonic_s < arrived + 0.005 and read - a.last_rx_monotonic_s >= 0.045
        else:
            assert a.last_rx_monotonic_s <= read
    finally:
        a.close()
        b.close()
