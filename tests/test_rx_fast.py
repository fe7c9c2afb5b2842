"""The controller's receive fast path (mavlink_bridge.codec._decode_fast, VehicleLink._on_messages)
gives exactly what pymavlink's parser and the per-message path give: same field values bit for
bit (ints, floats incl. signed zeros and NaN payloads, callsigns), same raw bytes and ids, the same
fallback for anything off the fast path (bad CRC, wrong length, unknown id, signed frames), and
the same stored traffic sets and counters in the link. No processes; each test well under 1 s."""

from __future__ import annotations

import dataclasses
import math
import random
import struct

import pytest

from mavlink_bridge import (
    AdsbVehicle,
    Attitude,
    BadData,
    GlobalPositionInt,
    Heartbeat,
    LocalPositionNed,
    NamedValueInt,
    Received,
    StatusText,
    VehicleLink,
)
from mavlink_bridge import codec as C
from mavlink_bridge import frames as F
from mavlink_bridge.adsb import TRAFFIC_MARKER_NAME, traffic_tag
from mavlink_bridge.codec import MavCodec
from mavlink_bridge.signing import SigningConfig

from _net import free_udp_port

ADSB = 246


def _bits(x):
    """A value as something that compares bit for bit (floats by their IEEE bytes)."""
    if isinstance(x, float):
        return ("f", struct.pack("<d", x))
    if isinstance(x, tuple):
        return tuple(_bits(v) for v in x)
    return (type(x).__name__, x)


def _fields(msg) -> list:
    """Every attribute of a typed message, in field order, bit for bit, with its type."""
    assert list(vars(msg)) == [f.name for f in dataclasses.fields(msg)]
    return [type(msg).__name__] + [(k, _bits(v)) for k, v in vars(msg).items()]


def _same(fast: list[Received], ref: list[Received]) -> None:
    assert len(fast) == len(ref)
    for a, b in zip(fast, ref):
        assert type(a) is Received
        if isinstance(a.msg, BadData):       # decode_datagram stamps a cut packet with the time it noticed it
            assert _fields(a.msg)[:-1] == _fields(b.msg)[:-1]
        else:
            assert _fields(a.msg) == _fields(b.msg)
        assert (a.src_system, a.src_component, a.raw, a.signature) == (b.src_system, b.src_component, b.raw, b.signature)
        assert type(a.raw) is bytes and type(a.src_system) is int
        assert list(vars(a)) == [f.name for f in dataclasses.fields(Received)]


def _reference(data: bytes, now: float) -> list[Received]:
    """What pymavlink's parser gives for a datagram (decode_datagram without its fast path)."""
    codec = MavCodec(1, 1)
    out = codec.decode(data, now)
    dropped = codec.reset_parser()
    if dropped:
        out.append(Received(BadData("truncated packet", dropped, now), 0, 0, b""))
    return out


def _adsb_payload(rng: random.Random) -> bytes:
    """An ADSB_VEHICLE payload of random field values (wire order), extremes included, with
    runs of trailing zero fields so that MAVLink 2 trims the payload by various lengths."""
    def u(bits):
        return rng.choice([0, 1, 2**bits - 1, rng.randrange(2**bits)])

    def i(bits):
        return rng.choice([0, -1, -(2 ** (bits - 1)), 2 ** (bits - 1) - 1, rng.randrange(-(2 ** (bits - 1)), 2 ** (bits - 1))])

    callsign = rng.choice([b"", traffic_tag(rng.randrange(2**32)).encode(), b"ABC\x00DEF", bytes(rng.randrange(256) for _ in range(9)),
                           b"123456789", b"\xc3\xa9X"])
    values = [u(32), i(32), i(32), i(32), u(16), u(16), i(16), u(16), u(16), u(8), callsign, u(8), u(8)]
    cut = rng.randrange(len(values) + 1)          # zero the last fields: the trimmed payloads
    for k in range(cut, len(values)):
        values[k] = b"" if k == 10 else 0
    return F.payload_struct(ADSB).pack(*values)


def _trim(payload: bytes) -> bytes:
    return payload.rstrip(b"\x00") or b"\x00"


def test_adsb_vehicle_frames_decode_as_pymavlink_bit_for_bit():
    """Given ADSB_VEHICLE frames of random and extreme values, trimmed by every possible length
    (also frames cut shorter than MAVLink 2 would, with a valid CRC), alone and in datagrams of
    up to 30 frames mixed with other telemetry, the fast path gives pymavlink's messages; the
    decoded fields also equal pymavlink's own message attributes."""
    rng = random.Random(246)
    frames = []
    for k in range(300):
        payload = _adsb_payload(rng)
        frames.append(F.build_v2(ADSB, _trim(payload), seq=k % 256, src_system=rng.randrange(1, 256), src_component=rng.randrange(256)))
    full = F.payload_struct(ADSB).pack(7, 1, 2, 3, 4, 5, 6, 7, 8, 9, b"ABCDEFGHI", 14, 255)
    for plen in range(1, 39):                      # any length, even cutting non-zero bytes: the receiver pads
        frames.append(F.build_v2(ADSB, full[:plen]))
    parser = C._mavlink.MAVLink(None, 0, 0)
    for fr in frames:
        fast = C._decode_fast(fr, 2.5)
        assert fast is not None
        _same(fast, _reference(fr, 2.5))
        p = parser.parse_buffer(fr)[0]
        m = fast[0].msg
        assert (m.icao_address, m.lat_e7, m.lon_e7, m.altitude_mm, m.heading_cdeg, m.hor_velocity_cm_s, m.ver_velocity_cm_s,
                m.flags, m.squawk, m.altitude_type, m.emitter_type, m.tslc_s) == (
            p.ICAO_address, p.lat, p.lon, p.altitude, p.heading, p.hor_velocity, p.ver_velocity, p.flags, p.squawk,
            p.altitude_type, p.emitter_type, p.tslc)
        cs = p.callsign if isinstance(p.callsign, str) else p.callsign.decode("ascii", "replace")
        assert m.callsign == cs.split("\x00", 1)[0]
        assert m.received_monotonic_s == 2.5
    others = [MavCodec(3, 1).encode(m) for m in (
        NamedValueInt(1500, TRAFFIC_MARKER_NAME, 24), NamedValueInt(0, "", 0), NamedValueInt(2**32 - 1, "0123456789", -(2**31)),
        LocalPositionNed(1500, -0.0, 1e-45, math.inf, -math.inf, math.nan, 3.4e38),
        LocalPositionNed(0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0), Attitude(1500, 0.1, -0.2, 0.0, -0.0, 1e-39, 7.0),
        GlobalPositionInt(1500, 47.4, 8.5, 498.0, 10.0, 1.0, -1.0, 0.0, None), Heartbeat())]
    gpi = F.payload_struct(33)
    for k in range(40):                             # GLOBAL_POSITION_INT: scaled on decode, heading 65535 = unknown
        others.append(F.build_v2(33, _trim(gpi.pack(rng.randrange(2**32), rng.randrange(-(2**31), 2**31), rng.randrange(-(2**31), 2**31),
                                                    rng.randrange(-(2**31), 2**31), rng.choice([0, -1, 2**31 - 1, rng.randrange(-(2**31), 2**31)]), rng.randrange(-(2**15), 2**15),
                                                    rng.choice([0, -(2**15), 2**15 - 1, rng.randrange(-(2**15), 2**15)]), rng.randrange(-(2**15), 2**15),
                                                    rng.choice([0, 35999, 65535, 65534, rng.randrange(65536)])))))
    nan_payload = struct.pack("<Iffffff", 5, *(struct.unpack("<f", struct.pack("<I", 0x7FC00001))[0] for _ in range(6)))
    others.append(F.build_v2(32, nan_payload))      # LOCAL_POSITION_NED of NaNs with a payload
    for fr in others:
        _same(C._decode_fast(fr, 1.0), _reference(fr, 1.0))
    for trial in range(100):
        sel = rng.sample(frames + others, rng.randint(1, 30))
        data = b"".join(sel)
        fast = C._decode_fast(data, 7.25)
        assert fast is not None and len(fast) == len(sel)
        _same(fast, _reference(data, 7.25))
        _same(MavCodec(1, 1).decode_datagram(data, 7.25), fast)


def test_frames_off_the_fast_path_fall_back_to_pymavlink_unchanged():
    """Given a traffic datagram with one frame spoiled (bad CRC, a length byte too long or too
    short, an unknown or an off-path id, a signed frame, a MAVLink 1 frame, trailing garbage,
    a frame cut short), the fast path declines and decode_datagram gives exactly pymavlink's
    result, BadData included: what the link counts and logs as a bad packet."""
    rng = random.Random(7)
    good = [F.build_v2(ADSB, _trim(_adsb_payload(rng)), src_system=2) for _ in range(10)]
    marker = MavCodec(2, 1).encode(NamedValueInt(900, TRAFFIC_MARKER_NAME, 10))
    signer = MavCodec(2, 1, SigningConfig(bytes(range(32)), 3))
    payload = F.payload_struct(ADSB).pack(1, 2, 3, 4, 5, 6, 7, 8, 9, 1, b"0000ABCD", 14, 0)
    spoiled = {
        "bad crc": bytes(good[0][:-1]) + bytes([good[0][-1] ^ 0x55]),
        "length too long": F.build_v2(ADSB, payload + b"\x01"),                     # > 38 bytes: pymavlink's call
        "length byte beyond the datagram": F.build_v2(ADSB, payload, length=60),
        "length byte too short": F.build_v2(ADSB, payload, length=20),
        "wrong crc extra": F.build_v2(ADSB, payload, extra=0),
        "unknown id": F.build_v2(60000, b"\x01\x02\x03"),
        "off-path id": MavCodec(2, 1).encode(StatusText(4, "hello")),
        "signed": signer.encode(AdsbVehicle(5, 1, 2, callsign="0000ABCD")),
        "incompat flag": F.build_v2(ADSB, payload, incompat_flags=0x02),
        "v1": F.build_v1(0, bytes(9)),
        "garbage": b"\x00\x01garbage\xfd",
        "cut short": good[1][:-3],
        "empty payload": F.build_v2(ADSB, b""),
    }
    for kind, bad in spoiled.items():
        for pos in (0, 5, 11):
            frames = good[:pos] + [bad] + good[pos:] + [marker]
            if kind == "cut short" and pos != 11:
                continue                                   # a cut frame swallows what follows: only last
            data = b"".join(frames)
            if kind != "empty payload":
                assert C._decode_fast(data, 3.0) is None, kind
            _same(MavCodec(1, 1).decode_datagram(data, 3.0), _reference(data, 3.0))
    assert C._decode_fast(b"", 1.0) == []


class _Port:
    signing = None


def _traffic_datagram(rng: random.Random, tags: list[int], n: int = 24, src: int = 3) -> list[Received]:
    msgs = []
    for tag in tags:
        for icao in rng.sample(range(1, 40), n):
            msgs.append(AdsbVehicle(icao, rng.randrange(-900_000_000, 900_000_000), rng.randrange(-10**9, 10**9),
                                    heading_cdeg=rng.randrange(36000), hor_velocity_cm_s=rng.randrange(3000),
                                    callsign=traffic_tag(tag), flags=95))
        msgs.append(NamedValueInt(tag, TRAFFIC_MARKER_NAME, n))
    msgs += [AdsbVehicle(99, 1, 2, callsign="N12345"), AdsbVehicle(98, 1, 2, callsign="")]     # untagged traffic
    rng.shuffle(msgs)
    msgs.append(LocalPositionNed(tags[-1], 1.0, 2.0, -10.0, 0.5, 0.25, 0.0))
    codec = MavCodec(src, 1)
    data = b"".join(codec.encode(m) for m in msgs)
    out = MavCodec(1, 1).decode_datagram(data, 4.0)
    assert all(r.signature == "unsigned" for r in out)
    return out


def _state(link: VehicleLink) -> tuple:
    """What the link keeps (the very message objects, by identity) and its counters."""
    fields = id
    return ({t: {i: fields(m) for i, m in d.items()} for t, d in link._traffic.items()},
            {t: fields(m) for t, m in link._traffic_markers.items()},
            {k.__name__: fields(m) for k, m in link._latest.items()},
            link.n_ignored_other_system, link.n_bad, dict(link.rejects.counts))


@pytest.mark.parametrize("signing", [False, True])
def test_link_stores_a_datagram_as_the_per_message_path_does(signing):
    """Given datagrams of traffic sets (sets split over datagrams, duplicates, more sets than the
    link keeps, untagged traffic, reports from another system, a bad packet), the link's
    batched store leaves the same traffic sets, markers, latest messages and counters as
    accepting and storing each message in turn; on a signing link (unsigned accepted) too."""
    links = [VehicleLink.open(f"udpin:127.0.0.1:{free_udp_port()}", target_system=3,
                              heartbeat_rate_hz=0, signing_key=bytes(range(32)) if signing else None, accept_unsigned=True)
             for _ in range(2)]
    fast, ref = links
    try:
        rng = random.Random(11)
        datagrams = [_traffic_datagram(rng, [1000 + 500 * k]) for k in range(40)]
        datagrams += [_traffic_datagram(rng, [100, 200]), _traffic_datagram(rng, [300], src=4), _traffic_datagram(rng, [21000, 20500]),
                      datagrams[-1], datagrams[3]]
        datagrams.append([Received(BadData("bad CRC", 40, 4.0), 0, 0, b"")] + datagrams[5])
        for received in datagrams:
            fast._on_messages(received)
            kept = [r.msg for r in received if ref._accept(r)]
            with ref._cond:
                for msg in kept:
                    ref._store(msg)
            assert _state(fast) == _state(ref)
        assert len(fast._traffic) == fast.TRAFFIC_SETS_KEPT
        assert fast.n_ignored_other_system > 0 and fast.n_bad == 1
        assert fast.sensed_traffic(21000, 0.1) == ref.sensed_traffic(21000, 0.1)
    finally:
        for link in links:
            link.close()


def test_adsb_states_equal_the_array_conversion_bit_for_bit():
    """Given traffic sets of 1..60 reports with any 32-bit wire values (headings past 35999,
    zero and maximal speeds, latitudes/longitudes at the int32 limits), in any order, adsb_states
    gives the ids and states of the array conversion traffic_to_local_ned, bit for bit."""
    import numpy as np

    from mavlink_bridge.adsb import adsb_states, home_e7, traffic_to_local_ned

    rng = random.Random(5)
    for trial in range(150):
        home = rng.choice([(47.397742, 8.545594), (-33.9, 151.2), (0.0, -179.9999999), (89.9, 0.0)])
        h_lat, h_lon = home_e7(home)
        reports = []
        for icao in rng.sample(range(1, 5000), rng.randint(1, 60)):
            def near(h):
                return rng.choice([h + rng.randrange(-20000, 20000), -(2**31), 2**31 - 1, h, rng.randrange(-(2**31), 2**31)])
            reports.append(AdsbVehicle(rng.choice([icao, 2**32 - 1 - icao]), near(h_lat), near(h_lon),
                                       heading_cdeg=rng.choice([0, 35999, 36000, 65535, rng.randrange(65536)]),
                                       hor_velocity_cm_s=rng.choice([0, 1, 65535, rng.randrange(65536)])))
        ids, states = adsb_states(reports, home)
        ref = sorted(reports, key=lambda r: r.icao_address)
        wire = np.array([(r.icao_address, r.lat_e7, r.lon_e7, r.hor_velocity_cm_s, r.heading_cdeg) for r in ref], dtype=np.int64)
        ref_states = traffic_to_local_ned(wire[:, 1], wire[:, 2], wire[:, 3], wire[:, 4], h_lat, h_lon)
        assert ids.dtype == np.int64 and states.dtype == np.float64 and states.shape == ref_states.shape
        assert ids.tobytes() == (wire[:, 0] - 1).tobytes() and states.tobytes() == ref_states.tobytes()
    ids, states = adsb_states([], (47.4, 8.5))
    assert ids.shape == (0,) and states.shape == (0, 4) and ids.dtype == np.int64
