"""The mock vehicle's per-step fast paths give exactly the bytes and numbers of the general
code they shortcut (pymavlink's packing, the numpy formulas). Pure functions, well under 1 s."""

from __future__ import annotations

import math
import random

import pytest

from mavlink_bridge import (
    AdsbVehicle,
    Attitude,
    GlobalPositionInt,
    Heartbeat,
    LocalPositionNed,
    MavModeFlag,
    MavState,
    MavType,
    NamedValueInt,
)
from mavlink_bridge import codec as C
from mavlink_bridge.codec import MavCodec
from mavlink_bridge.signing import SigningConfig

_EDGE_FLOATS = (0.0, -0.0, 1.0, -1.5, 1e-40, 3.4e38, -3.4e38, math.nan, math.inf, -math.inf, 123456.789)


def _pymavlink_packet(ref: MavCodec, m) -> bytes:
    """What pymavlink's own ``pack`` gives for ``m`` (the reference), advancing ``ref``'s sequence."""
    packet = bytes(C._ENCODERS[type(m)](ref._tx, m).pack(ref._tx))
    ref._tx.seq = (ref._tx.seq + 1) % 256
    return packet


def _typed_messages(rng: random.Random) -> list:
    f = lambda: rng.choice(_EDGE_FLOATS) if rng.random() < 0.2 else rng.uniform(-1e5, 1e5)   # noqa: E731
    g = lambda: rng.choice((math.nan, math.inf, -math.inf, 1e12, -1e12, 0.0)) if rng.random() < 0.2 else rng.uniform(-400.0, 400.0)  # noqa: E731
    t = lambda: rng.choice((0, 1, 2**32 - 1, 2**32, 2**40 + 7)) if rng.random() < 0.2 else rng.randrange(2**32)   # noqa: E731
    return [
        LocalPositionNed(t(), f(), f(), f(), f(), f(), f()),
        Attitude(t(), f(), f(), f(), f(), f(), f()),
        GlobalPositionInt(t(), g(), g(), g() * 1e3, g(), g(), g(), g(), rng.choice((None, g(), -725.5, 359.999, 0.0))),
        Heartbeat(type=rng.choice((MavType.QUADROTOR, 0, 255)), autopilot=rng.randrange(256),
                  base_mode=rng.choice((MavModeFlag.CUSTOM_MODE_ENABLED | MavModeFlag.SAFETY_ARMED, 0, 0x1FF, rng.randrange(2**16))),
                  custom_mode=rng.choice((0, 2**32 + 5, rng.randrange(2**40))),
                  system_status=rng.choice((MavState.ACTIVE, MavState.STANDBY, 0)), mavlink_version=rng.randrange(256)),
        NamedValueInt(t(), rng.choice(("", "TRAFFIC_N", "A_NAME_LONGER_THAN_TEN", "n\u00e4me", "x")),
                      rng.choice((0, -1, 2**31 - 1, -(2**31), rng.randrange(-(2**31), 2**31)))),
        AdsbVehicle(icao_address=rng.choice((1, 25, 2**32 + 3, rng.randrange(2**32))), lat_e7=rng.randrange(-(2**31), 2**31),
                    lon_e7=rng.randrange(-(2**31), 2**31), altitude_type=rng.randrange(2), altitude_mm=rng.randrange(-(2**31), 2**31),
                    heading_cdeg=rng.randrange(36000), hor_velocity_cm_s=rng.randrange(65536),
                    ver_velocity_cm_s=rng.randrange(-(2**15), 2**15), callsign=rng.choice(("", "000005DC", "TOOLONGCALLSIGN")),
                    emitter_type=rng.randrange(256), tslc_s=rng.randrange(256), flags=rng.randrange(65536), squawk=rng.randrange(65536)),
        LocalPositionNed(0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0),                 # an all-zero payload: one byte kept
        NamedValueInt(0, "", 0),
        Heartbeat(type=0, autopilot=0, base_mode=0, custom_mode=0, system_status=0, mavlink_version=0),
    ]


def test_typed_fast_encoding_equals_pymavlink_byte_for_byte():
    """Every type on ``MavCodec.encode``'s typed fast path, random and edge values (NaN, inf,
    out-of-range and clipped integers, trailing-zero payloads, long names), sequence numbers
    wrapping past 255: byte for byte pymavlink's ``pack``."""
    assert set(C._TYPED_PACKERS) == {AdsbVehicle, NamedValueInt, LocalPositionNed, Attitude, GlobalPositionInt, Heartbeat}
    rng = random.Random(5)
    fast, ref = MavCodec(9, 1), MavCodec(9, 1)
    n = 0
    for _ in range(120):
        for m in _typed_messages(rng):
            assert fast.encode(m) == _pymavlink_packet(ref, m), m
            n += 1
    assert n > 256 and fast._tx.seq == ref._tx.seq


def test_typed_fast_encoding_fails_like_pymavlink():
    """A value the wire cannot carry raises (as pymavlink's pack does) and the sequence number
    does not advance."""
    import struct

    codec = MavCodec(9, 1)
    for bad in (LocalPositionNed(-1, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0),      # & 0xFFFFFFFF keeps it in range: no error
                NamedValueInt(0, "x", 2**31), AdsbVehicle(1, 2**31, 0), Heartbeat(type=256)):
        ref = MavCodec(9, 1)
        ref._tx.seq = codec._tx.seq
        try:
            expected = _pymavlink_packet(ref, bad)
        except struct.error:
            seq = codec._tx.seq
            with pytest.raises(struct.error):
                codec.encode(bad)
            assert codec._tx.seq == seq
        else:
            assert codec.encode(bad) == expected


def test_signing_codec_keeps_pymavlink_packing():
    signed = MavCodec(9, 1, SigningConfig(bytes(range(32)), 0))
    for m in _typed_messages(random.Random(1))[:2]:
        packet = signed.encode(m)
        assert packet[2] & 0x01 and len(packet) == 12 + packet[1] + 13


def test_single_vehicle_plant_step_equals_the_vectorised_step_bit_for_bit():
    """A mock's plant (one vehicle) steps with Python floats: the same states and applied
    accelerations, bit for bit, as the vectorised numpy code, for saturated and unsaturated,
    zero and tiny accelerations, several sub-step counts and a full (non-diagonal) wind matrix."""
    import numpy as np

    from mock_vehicle.plant import PlantParams, SwarmPlant, WindParams

    rng = np.random.default_rng(2)
    for wind, limit, physics_dt in ((WindParams(), 2.0, 0.1),
                                    (WindParams(0.37, (2.5, -0.3), ((0.31, -0.07), (0.11, 0.23))), 1.3, 0.07)):
        params = PlantParams(wind=wind, acc_limit_m_s2=limit, physics_dt_s=physics_dt)
        fast, ref = (SwarmPlant(np.array([[3.0, -4.0]]), params, seed=9, vehicle_ids=np.array([6])) for _ in range(2))
        for i in range(300):
            acc = rng.normal(0.0, 2.0, (1, 2)) * rng.choice([0.0, 1e-200, 1e-3, 1.0, 5.0])
            dt = float(rng.choice([0.5, 0.1, 0.25, 1.0, 0.03]))
            a_fast, a_ref = fast.step(acc, dt), ref._step_vectorised(acc, dt)
            assert a_fast.shape == a_ref.shape == (1, 2) and a_fast.tobytes() == a_ref.tobytes(), i
            assert fast.states.tobytes() == ref.states.tobytes(), i
        assert fast.time_s == ref.time_s
    with pytest.raises(ValueError, match="finite"):
        fast.step(np.array([[math.nan, 0.0]]), 0.5)


def _setpoint_acc_numpy_reference(sp, s):
    """MockVehicle._setpoint_acc_m_s2 as it was written with numpy (the reference)."""
    import numpy as np

    from mavlink_bridge import PositionTargetTypeMask as F

    m = sp.type_mask

    def axes(bits, values):
        used = np.array([not (m & b) for b in bits])
        return used, np.where(used, np.array(values, dtype=np.float64), 0.0) if used.any() else np.zeros(2)

    use_acc, acc_sp = axes((F.AX_IGNORE, F.AY_IGNORE), (sp.afx_m_s2, sp.afy_m_s2))
    use_vel, vel_sp = axes((F.VX_IGNORE, F.VY_IGNORE), (sp.vx_m_s, sp.vy_m_s))
    use_pos, pos_sp = axes((F.X_IGNORE, F.Y_IGNORE), (sp.x_m, sp.y_m))
    acc = acc_sp.copy()
    if use_pos.any():
        acc += np.where(use_pos, 1.0 * (pos_sp - s[0:2]), 0.0) + 2.0 * (vel_sp - s[2:4])
    elif use_vel.any():
        acc += 2.0 * (vel_sp - s[2:4])
    return acc


def test_setpoint_acceleration_equals_the_numpy_formula_bit_for_bit():
    """Every combination of used/ignored x, y, vx, vy, afx, afy (NaN in ignored fields, signed
    zeros, random values and states): the float code gives the numpy formula's bits."""
    import itertools

    import numpy as np

    from mavlink_bridge import SetPositionTargetLocalNed
    from mock_vehicle.vehicle import MockVehicle, VehicleConfig

    v = MockVehicle(VehicleConfig(instance=2, initial_pos_m=(3.0, -1.0)), lambda m, p: None)
    rng = np.random.default_rng(4)
    bits = (1, 2, 8, 16, 64, 128)
    n = 0
    for used in itertools.product((False, True), repeat=6):
        mask = 0b1100_0010_0100 | sum(b for b, u in zip(bits, used) if not u)     # z, vz, az, yaw, yaw rate ignored
        for _ in range(20):
            vals = [float(x) for x in rng.normal(0.0, 30.0, 6)]
            vals = [rng.choice([x, -0.0, 0.0]) if u else rng.choice([x, math.nan, math.inf]) for x, u in zip(vals, used)]
            v.plant.states = np.array([list(rng.normal(0.0, 20.0, 4) * rng.choice([0.0, 1.0]))])
            sp = SetPositionTargetLocalNed(0, 3, 1, type_mask=mask, x_m=vals[0], y_m=vals[1], vx_m_s=vals[2], vy_m_s=vals[3],
                                           afx_m_s2=vals[4], afy_m_s2=vals[5])
            v.setpoint = sp
            got = v._setpoint_acc_m_s2()
            assert got.shape == (2,) and got.tobytes() == _setpoint_acc_numpy_reference(sp, v.state).tobytes(), (used, vals)
            n += 1
    assert n == 64 * 20


def test_traffic_reports_equal_the_numpy_encoding():
    """traffic_reports' per-vehicle scalar encoding gives the messages the numpy encode_traffic
    gives (random sets, rest, exact halves, the speed cap, values beyond the scalar range);
    non-finite states still raise."""
    import numpy as np

    from mavlink_bridge.adsb import ADSB_FLAGS_EMULATED, home_e7, icao_of_vehicle_id, metres_per_e7, traffic_tag
    from mock_vehicle.proximity import DEFAULT_HOME_DEG, encode_traffic, traffic_reports

    def reference(ids, states, t, home, alt):
        enc = encode_traffic(states, home)
        return [AdsbVehicle(icao_address=icao_of_vehicle_id(int(v)), lat_e7=int(e[0]), lon_e7=int(e[1]), altitude_type=1,
                            altitude_mm=int(round(alt * 1000.0)), heading_cdeg=int(e[3]), hor_velocity_cm_s=int(e[2]),
                            ver_velocity_cm_s=0, callsign=traffic_tag(t), emitter_type=14, tslc_s=0, flags=ADSB_FLAGS_EMULATED,
                            squawk=0) for v, e in zip(np.asarray(ids).reshape(-1).tolist(), enc)]

    rng = np.random.default_rng(8)
    m_n, m_e = metres_per_e7(home_e7(DEFAULT_HOME_DEG)[0])
    special = np.array([[0.0, 0.0, 0.0, 0.0], [1.0, 2.0, 0.0, -0.0], [0.0, 0.0, 700.0, 1.0], [0.0, 0.0, -1.0, -1e-9],
                        [2.5 * m_n, -0.5 * m_e, 0.005, 0.0], [0.0, 0.0, 0.015, 0.0], [-3.5 * m_n, 1.5 * m_e, -2.0, 3.0]])
    for trial in range(60):
        m = int(rng.integers(0, 25))
        states = rng.normal(0.0, 1.0, (m, 4)) * [500.0, 500.0, 3.0, 3.0]
        if trial % 3 == 0:
            states = np.concatenate([states, special])
        if trial % 10 == 1:
            states = np.concatenate([states, [[1e16, 0.0, 0.0, 1.0]]])          # beyond the scalar range: numpy's path
        states = states.astype(np.float32).astype(np.float64)                  # what a world answer carries
        ids = rng.permutation(60)[: states.shape[0]]
        home = DEFAULT_HOME_DEG if trial % 2 else (47.0 + rng.random(), 8.0 + rng.random())
        got = traffic_reports(ids, states, 500 * trial, home, 498.0)
        want = reference(ids, states, 500 * trial, home, 498.0)
        assert got == want and [type(x) for x in got] == [type(x) for x in want]
        assert [tuple(map(type, vars(g).values())) for g in got] == [tuple(map(type, vars(w).values())) for w in want]
        assert [list(vars(g)) for g in got] == [list(vars(w)) for w in want] and all(math.isnan(g.received_monotonic_s) for g in got)
        assert [hash(g) for g in got] == [hash(w) for w in want] and [repr(g) for g in got] == [repr(w) for w in want]
    with pytest.raises(ValueError, match="finite"):
        traffic_reports(np.array([1]), np.array([[0.0, 0.0, math.nan, 1.0]]), 0)
    from mock_vehicle import proximity

    assert proximity._ADSB_DIRECT          # the fast construction is the one tested here
