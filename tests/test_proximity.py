"""The emulated proximity sensor (docs/proximity.md), without processes: ADS-B encode in
the mock -> MAVLink wire -> decode in the bridge equals the simulator's quantiser bit for
bit; the world's barrier; the mock's lockstep order (traffic, marker, then
LOCAL_POSITION_NED); the link's traffic sets (loopback UDP)."""

from __future__ import annotations

import math
import random
import socket
import threading
import time

import numpy as np
import pytest
from _net import free_udp_port, wait_until
from scipy.spatial import cKDTree

from mavlink_bridge import (
    PX4_OFFBOARD,
    AdsbVehicle,
    CommandLong,
    HomePosition,
    LocalPositionNed,
    MavlinkPort,
    NamedValueInt,
    Received,
    TelemetryTimeout,
    VehicleLink,
    acceleration_setpoint,
)
from mavlink_bridge.adsb import TRAFFIC_MARKER_NAME, adsb_states, home_e7, metres_per_e7, traffic_tag
from mavlink_bridge.codec import MavCodec
from mock_vehicle.proximity import (
    DEFAULT_HOME_DEG,
    encode_traffic,
    quantise_sensed_states,
    sensed_pairs,
    sensed_rows,
    traffic_reports,
)
from mock_vehicle.vehicle import MockVehicle, VehicleConfig
from mock_vehicle.world import (
    KIND_ANSWER,
    KIND_REPORT,
    Answer,
    WorldClient,
    WorldParams,
    WorldState,
    pack_answer,
    pack_report,
    serve,
    unpack,
)


def _random_states(rng: np.random.Generator, m: int) -> np.ndarray:
    """float32-rounded states as LOCAL_POSITION_NED carries them, with the edge cases
    (at rest, on the axes, exactly opposite to north) mixed in."""
    pos = rng.uniform(-2000.0, 2000.0, (m, 2))
    vel = rng.uniform(-8.0, 8.0, (m, 2)) * rng.choice([1.0, 1e-3, 0.0], (m, 1), p=[0.8, 0.1, 0.1])
    s = np.hstack([pos, vel])
    s[0, 2:] = (-1.5, 0.0)          # heading exactly 180 deg
    s[1, 2:] = (0.0, -2.0)          # 270 deg
    s[2, 2:] = (0.0, 0.0)
    return np.asarray(s, dtype=np.float32).astype(np.float64)


# ---------------------------------------------------------------- resolution, bit for bit
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_mock_encode_wire_bridge_decode_equals_sim_quantiser_bit_for_bit(seed):
    """Given random float32 states, when the mock builds ADSB_VEHICLE for them, packs them
    as MAVLink 2 and the bridge parses them and converts with the home it got from the
    vehicle's own HOME_POSITION, then the states equal quantise_sensed_states bit for bit."""
    rng = np.random.default_rng(seed)
    states = _random_states(rng, 400)
    ids = rng.permutation(400)
    reports = traffic_reports(ids, states, time_boot_ms=123_500, home_deg=DEFAULT_HOME_DEG)
    tx, rx = MavCodec(5, 1), MavCodec(5, 191)
    wire = [r.msg for m in random.Random(seed).sample(reports, len(reports)) for r in rx.decode_datagram(tx.encode(m))]
    assert all(isinstance(m, AdsbVehicle) for m in wire) and len(wire) == 400
    home = rx.decode_datagram(tx.encode(HomePosition(*DEFAULT_HOME_DEG, 488.0)))[0].msg
    got_ids, got = adsb_states(wire, home)
    order = np.argsort(ids)
    np.testing.assert_array_equal(got_ids, ids[order])
    want = quantise_sensed_states(states[order])
    assert got.dtype == want.dtype == np.float64
    assert np.array_equal(got.view(np.uint64), want.view(np.uint64))       # bit for bit
    # and the resolution is ADS-B's: ~1.1 cm north, ~0.75 cm east, ~0.5 cm/s + 0.01 deg of heading
    err = np.abs(got - states[order])
    assert err[:, 0].max() <= 0.0056 and err[:, 1].max() <= 0.0038 and err[:, 2:].max() <= 0.006


def test_encoding_does_not_depend_on_how_many_are_encoded_together():
    """The mock encodes its m sensed vehicles, the simulator all of them: same integers."""
    states = _random_states(np.random.default_rng(7), 300)
    whole = encode_traffic(states)
    parts = np.vstack([encode_traffic(states[i:i + 7]) for i in range(0, 300, 7)])
    np.testing.assert_array_equal(whole, parts)
    np.testing.assert_array_equal(quantise_sensed_states(states)[5:9], quantise_sensed_states(states[5:9]))


def _encode_traffic_scalar(states, home_deg=DEFAULT_HOME_DEG):
    """The per-vehicle scalar formulas encode_traffic must reproduce bit for bit."""
    h_lat, h_lon = home_e7(home_deg)
    m_n, m_e = metres_per_e7(h_lat)
    out = np.empty((states.shape[0], 4), dtype=np.int64)
    for i, (x, y, vx, vy) in enumerate(np.asarray(states, dtype=float).tolist()):
        speed = math.hypot(vx, vy)
        out[i] = (h_lat + round(x / m_n), h_lon + round(y / m_e), min(round(speed * 100.0), 65535),
                  round(math.degrees(math.atan2(vy, vx)) * 100.0) % 36000 if speed > 0 else 0)
    return out


def test_encoding_equals_the_scalar_formulas():
    """numpy for the exact IEEE parts, Python's math.hypot/atan2 per vehicle: the same integers as the
    scalar formulas (numpy's own hypot/arctan2 would differ in the last bit for some inputs), including
    rest (heading 0), the speed cap, negative headings, half-way roundings and the empty set."""
    rng = np.random.default_rng(11)
    states = np.concatenate([_random_states(rng, 5000),
                             rng.normal(0.0, 1.0, (2000, 4)) * [300.0, 300.0, 0.3, 0.3],
                             [[0.0, 0.0, 0.0, 0.0], [1.0, 2.0, 0.0, -0.0], [0.0, 0.0, 700.0, 1.0],
                              [0.0, 0.0, -1.0, -1e-9], [0.0, 0.0, 0.005, 0.0], [0.0, 0.0, 0.015, 0.0]]])
    m_n, m_e = metres_per_e7(home_e7(DEFAULT_HOME_DEG)[0])
    states = np.concatenate([states, [[2.5 * m_n, -0.5 * m_e, 0.0, 1.0]]])      # exact halves: round half to even
    np.testing.assert_array_equal(encode_traffic(states), _encode_traffic_scalar(states))
    assert encode_traffic(np.zeros((0, 4))).shape == (0, 4)
    with pytest.raises(ValueError, match="finite"):
        encode_traffic(np.array([[0.0, 0.0, float("nan"), 1.0]]))


def test_adsb_fields_follow_common_xml():
    (r,) = traffic_reports(np.array([4]), np.array([[1.0, -2.0, 0.0, 3.0]]), 1500, altitude_amsl_m=498.0)
    assert r.icao_address == 5 and r.callsign == traffic_tag(1500) == "000005DC"
    assert r.heading_cdeg == 9000 and r.hor_velocity_cm_s == 300 and r.altitude_mm == 498_000
    assert r.tslc_s == 0 and r.emitter_type == 14 and r.altitude_type == 1
    assert r.flags & 1 and r.flags & 4 and r.flags & 8 and r.flags & 64       # coords, heading, velocity valid; simulated


def test_sensed_pairs_are_the_simulators_query_sorted_by_owner_and_id():
    rng = np.random.default_rng(3)
    obs = np.asarray(np.hstack([rng.uniform(0, 30, (40, 2)), rng.normal(0, 1, (40, 2))]), dtype=np.float32).astype(float)
    owner, other = sensed_rows(sensed_pairs(obs, 10.0))
    ref = {(int(i), int(j)) for i, j in cKDTree(obs[:, 0:2]).query_pairs(10.0)}
    assert set(zip(owner.tolist(), other.tolist())) == ref | {(j, i) for i, j in ref}
    assert list(zip(owner.tolist(), other.tolist())) == sorted(zip(owner.tolist(), other.tolist()))
    d = np.linalg.norm(obs[owner, 0:2] - obs[other, 0:2], axis=1)
    assert np.all(d <= 10.0)


def _sensed_rows_by_argsort(pairs):
    """sensed_rows as it was (one argsort of the combined key): the reference of its radix passes."""
    pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    owner = np.concatenate([pairs[:, 0], pairs[:, 1]])
    other = np.concatenate([pairs[:, 1], pairs[:, 0]])
    if owner.size == 0:
        return owner, other
    order = np.argsort(owner * (int(other.max()) + 1) + other)
    return owner[order], other[order]


@pytest.mark.parametrize("n", [2, 3, 50, 4000, 65536, 70000])
def test_sensed_rows_equal_the_argsort_of_owner_and_other(n):
    """The radix passes (ids below 2^16) and the fallback (larger ids) give the rows of one argsort of
    (owner, other), bit for bit: on no pair, one pair, and random pair sets in random order."""
    rng = np.random.default_rng(n)
    cases = [np.zeros((0, 2), dtype=np.int64), np.array([[0, n - 1]]), np.array([[n - 2, n - 1]])]
    for m in (1, 7, 5000):
        i = rng.integers(0, n, m)
        j = rng.integers(0, n, m)
        keep = i != j
        k = np.unique(np.minimum(i, j)[keep] * n + np.maximum(i, j)[keep])
        cases.append(rng.permutation(np.stack([k // n, k % n], axis=1)))
    for pairs in cases:
        owner, other = sensed_rows(pairs)
        ref_owner, ref_other = _sensed_rows_by_argsort(pairs)
        assert owner.dtype == other.dtype == np.int64
        np.testing.assert_array_equal(owner, ref_owner)
        np.testing.assert_array_equal(other, ref_other)
    owner, other = sensed_rows(np.zeros(0, dtype=np.int64))          # the empty input of any shape
    assert owner.shape == other.shape == (0,)


# ---------------------------------------------------------------- the world
def _state(x, y=0.0):
    return np.array([x, y, 0.5, -0.25])


def test_world_barrier_answers_when_all_have_reported():
    """Given a lockstep world of 3 with R = 10 m, when vehicles 0 and 1 report t = 0 nothing
    is answered; when 2 reports, all three get their in-range sets (sorted by id)."""
    w = WorldState(WorldParams(n=3, sensor_range_m=10.0, lockstep=True, deadline_s=5.0))
    assert w.report(0, 0, _state(0.0), now=0.0) == []
    assert w.report(1, 0, _state(6.0), now=0.1) == []
    answers = {a.vehicle_id: a for a in w.report(2, 0, _state(12.0), now=0.2)}
    assert sorted(answers) == [0, 1, 2]
    assert answers[0].ids.tolist() == [1] and answers[1].ids.tolist() == [0, 2] and answers[2].ids.tolist() == [1]
    np.testing.assert_array_equal(answers[1].states, np.array([_state(0.0), _state(12.0)]))
    # a duplicate report of an answered time gets the same answer again (idempotent)
    (again,) = w.report(1, 0, _state(6.0), now=0.3)
    assert again.ids.tolist() == [0, 2] and again.time_boot_ms == 0
    # the next step waits for everyone again
    assert w.report(0, 500, _state(1.0), now=1.0) == []
    assert w.pending_times() == [500]


def test_world_exact_range_is_inclusive():
    w = WorldState(WorldParams(n=2, sensor_range_m=10.0))
    w.report(0, 0, _state(0.0), 0.0)
    answers = {a.vehicle_id: a.ids.tolist() for a in w.report(1, 0, _state(10.0), 0.0)}
    assert answers == {0: [1], 1: [0]}


def test_world_deadline_answers_without_a_silent_vehicle_and_stops_waiting_for_it(caplog):
    """Given vehicle 2 stops reporting, when the deadline of t passes, then 0 and 1 get
    their sets (2 at its last known state), the world logs it and no longer waits for 2;
    when 2 reports again it is waited for again."""
    w = WorldState(WorldParams(n=3, sensor_range_m=10.0, lockstep=True, deadline_s=2.0))
    for v, x in enumerate((0.0, 6.0, 12.0)):
        w.report(v, 0, _state(x), now=0.0)
    assert w.report(0, 500, _state(0.5), now=1.0) == [] and w.report(1, 500, _state(6.5), now=1.0) == []
    assert w.poll(now=2.9) == []                                    # not yet
    with caplog.at_level("WARNING", logger="mock_vehicle.world"):
        answers = {a.vehicle_id: a for a in w.poll(now=3.1)}
    assert sorted(answers) == [0, 1] and w.absent == {2}
    assert "no report from vehicle(s) [2]" in caplog.text
    assert answers[1].ids.tolist() == [0, 2]
    np.testing.assert_array_equal(answers[1].states[1], _state(12.0))  # last known
    # t = 1000: 0 and 1 suffice now
    w.report(0, 1000, _state(1.0), now=4.0)
    assert {a.vehicle_id for a in w.report(1, 1000, _state(7.0), now=4.0)} == {0, 1}
    # 2 comes back with a late report of t = 1000: answered at once, and waited for again
    (late,) = w.report(2, 1000, _state(12.0), now=4.5)
    assert late.ids.tolist() == [1] and w.absent == set()
    assert w.report(0, 1500, _state(1.0), now=5.0) == [] and w.report(1, 1500, _state(7.0), now=5.0) == []
    assert len(w.report(2, 1500, _state(12.0), now=5.0)) == 3


def test_world_realtime_answers_at_once_from_fresh_states():
    w = WorldState(WorldParams(n=3, sensor_range_m=10.0, lockstep=False, stale_s=1.0))
    assert w.report(0, 100, _state(0.0), now=0.0)[0].ids.tolist() == []
    w.report(1, 120, _state(3.0), now=0.1)
    (a,) = w.report(0, 200, _state(0.0), now=0.5)
    assert a.ids.tolist() == [1] and a.time_boot_ms == 200
    (a,) = w.report(0, 300, _state(0.0), now=1.5)                  # 1's state is stale now
    assert a.ids.tolist() == []


def test_world_realtime_sees_the_others_where_they_are_now():
    # a sensor measures now: vehicle 1's last report (0.4 s before vehicle 0's) is carried forward at its velocity
    w = WorldState(WorldParams(n=2, sensor_range_m=10.0, lockstep=False, stale_s=1.0))
    w.report(1, 120, _state(3.0), now=0.1)
    (a,) = w.report(0, 200, _state(0.0), now=0.5)
    np.testing.assert_allclose(a.states[0], [3.0 + 0.5 * 0.4, -0.25 * 0.4, 0.5, -0.25])


def test_world_datagrams_round_trip_and_garbage_is_refused():
    kind, vid, t, ids, st = unpack(pack_report(7, 2500, np.float32([1.5, -2.25, 0.1, 0.2])))
    assert (kind, vid, t, ids.tolist()) == (KIND_REPORT, 7, 2500, [7])
    np.testing.assert_array_equal(st[0], np.float32([1.5, -2.25, 0.1, 0.2]).astype(float))
    a = Answer(3, 500, np.array([1, 4]), np.float32([[1, 2, 3, 4], [5, 6, 7, 8]]).astype(float))
    kind, vid, t, ids, st = unpack(pack_answer(a))
    assert (kind, vid, t, ids.tolist()) == (KIND_ANSWER, 3, 500, [1, 4]) and np.array_equal(st, a.states)
    for bad in (b"", b"MFGW", b"XXXX" + pack_report(1, 0, np.zeros(4))[4:], pack_report(1, 0, np.zeros(4))[:-1],
                pack_report(1, 0, np.array([np.nan, 0, 0, 0]))):
        with pytest.raises(ValueError):
            unpack(bad)


def test_world_server_and_client_on_loopback():
    """The UDP world (``serve``) with two WorldClients: answers arrive after both reported."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    port = sock.getsockname()[1]
    stop = threading.Event()
    th = threading.Thread(target=serve, args=(WorldParams(2, 10.0, lockstep=True), ("127.0.0.1", port), stop, sock), daemon=True)
    th.start()
    c0, c1 = WorldClient(f"udp:127.0.0.1:{port}"), WorldClient(f"udp:127.0.0.1:{port}")
    try:
        c0.sock.send(b"garbage")                                   # ignored, logged
        c0.report(0, 0, np.float32([0, 0, 0, 0]))
        time.sleep(0.2)
        assert c0.receive() == []
        c1.report(1, 0, np.float32([3, 4, 0, 0]))
        a0 = wait_until(c0.receive, 5.0, "world answer to vehicle 0")[0]
        a1 = wait_until(c1.receive, 5.0, "world answer to vehicle 1")[0]
        assert a0.ids.tolist() == [1] and a1.ids.tolist() == [0] and a0.time_boot_ms == 0
        np.testing.assert_array_equal(a0.states[0], [3, 4, 0, 0])
    finally:
        stop.set()
        th.join(5.0)
        sock.close()
        c0.close()
        c1.close()
    assert not th.is_alive()


# ---------------------------------------------------------------- the mock's side
class _Clock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def _offboard_lockstep_vehicle():
    clock, sent, reports = _Clock(), [], []
    v = MockVehicle(VehicleConfig(instance=2, lockstep=True, dt_s=0.5, seed=1, initial_pos_m=(3.0, 4.0)),
                    lambda m, port: sent.append(m), clock=clock)
    v.attach_world(lambda t, s: reports.append((t, np.asarray(s).copy())))
    v.handle(Received(CommandLong(3, 1, 400, (1.0,) + (0.0,) * 6), 3, 191))
    for _ in range(30):
        v.handle(Received(acceleration_setpoint(3, 1, (0.0, 0.0, 0.0), 0xFFFFFFFF), 3, 191))
        clock.t += 0.05
        v.tick()
    v.handle(Received(CommandLong(3, 1, 176, (1.0, 6.0) + (0.0,) * 5), 3, 191))
    assert v.mode == PX4_OFFBOARD
    return v, clock, sent, reports


def test_mock_lockstep_sends_the_steps_traffic_then_marker_then_position():
    """Given a lockstep mock with a world, when a step happens its LOCAL_POSITION_NED waits
    for the world's answer; then the ADSB_VEHICLE set, the TRAFFIC_N marker and the
    position stamped t_k+1 go out in this order. Retries meanwhile get no answer."""
    v, clock, sent, reports = _offboard_lockstep_vehicle()
    assert reports[0][0] == 0 and reports[0][1].dtype == np.float32      # t = 0 reported at attach
    v.on_world_answer(0, np.array([0]), np.array([[3.5, 4.0, 0.0, 0.0]]))
    sent.clear()
    v.handle(Received(acceleration_setpoint(3, 1, (1.0, 0.0, 0.0), 0), 3, 191))
    assert v.time_boot_ms() == 500 and reports[-1][0] == 500
    assert not [m for m in sent if isinstance(m, LocalPositionNed)]
    v.handle(Received(acceleration_setpoint(3, 1, (1.0, 0.0, 0.0), 0), 3, 191))   # a retry: no answer yet
    clock.t += 0.3
    v.tick()
    assert not [m for m in sent if isinstance(m, LocalPositionNed)]
    clock.t += 0.3
    v.tick()
    assert reports[-1][0] == 500 and len([r for r in reports if r[0] == 500]) == 2  # re-reported after 0.5 s
    v.on_world_answer(0, np.array([0]), np.array([[9.0, 9.0, 0.0, 0.0]]))          # stale answer: ignored
    assert not [m for m in sent if isinstance(m, (AdsbVehicle, NamedValueInt))]
    sent.clear()
    v.on_world_answer(500, np.array([0, 5]), np.array([[3.5, 4.0, 0.1, 0.0], [2.0, 4.0, 0.0, 0.0]]))
    kinds = [type(m).__name__ for m in sent]
    assert kinds[:4] == ["AdsbVehicle", "AdsbVehicle", "NamedValueInt", "LocalPositionNed"]
    assert [m.icao_address for m in sent[:2]] == [1, 6] and sent[0].callsign == traffic_tag(500)
    assert sent[2].name == TRAFFIC_MARKER_NAME and sent[2].value == 2 and sent[2].time_boot_ms == 500
    assert sent[3].time_boot_ms == 500


def test_mock_realtime_reports_at_the_traffic_rate():
    clock, sent, reports = _Clock(), [], []
    v = MockVehicle(VehicleConfig(traffic_rate_hz=5.0), lambda m, port: sent.append(m), clock=clock)
    v.attach_world(lambda t, s: reports.append(t))
    for _ in range(100):
        clock.t += 0.01
        v.tick()
    assert 5 <= len(reports) <= 6


# ---------------------------------------------------------------- the link's side
def test_link_collects_tagged_sets_whatever_the_order_and_times_out_on_an_incomplete_one():
    """Given traffic sent to a VehicleLink (marker first, reports shuffled, a foreign
    untagged report, an older set), sensed_traffic(t) returns exactly the set tagged t;
    an incomplete set raises TelemetryTimeout."""
    port = free_udp_port()
    link = VehicleLink.open(f"udpin:127.0.0.1:{port}", target_system=3, heartbeat_rate_hz=0)
    veh = MavlinkPort.open(f"udpout:127.0.0.1:{port}", 3, 1)
    try:
        assert not link.has_traffic_sensor()
        states = _random_states(np.random.default_rng(5), 6)
        old = traffic_reports(np.arange(3), states[:3], 0)
        new = traffic_reports(np.array([0, 1, 4, 5, 7]), states[1:], 500)
        veh.send(NamedValueInt(500, TRAFFIC_MARKER_NAME, 5))
        for m in random.Random(1).sample(new, 5) + [AdsbVehicle(999, 1, 1, callsign="DLH123")] + old:
            veh.send(m)
        veh.send(NamedValueInt(0, TRAFFIC_MARKER_NAME, 3))
        veh.send(NamedValueInt(1000, TRAFFIC_MARKER_NAME, 2))          # its reports never come
        veh.send(HomePosition(*DEFAULT_HOME_DEG, 488.0))
        got = link.sensed_traffic(500, timeout_s=5.0)
        assert [r.icao_address for r in got] == [1, 2, 5, 6, 8]
        assert [r.icao_address for r in link.sensed_traffic(0, timeout_s=5.0)] == [1, 2, 3]
        assert link.has_traffic_sensor() and link.wait_traffic_sensor(0.0)
        home = link.wait_for(HomePosition, lambda h: True, 5.0)
        ids, st = adsb_states(got, home)
        assert ids.tolist() == [0, 1, 4, 5, 7]
        assert np.array_equal(st, quantise_sensed_states(states[1:]))
        with pytest.raises(TelemetryTimeout, match="traffic set"):
            link.sensed_traffic(1000, timeout_s=0.3)
        t, latest = link.latest_traffic(max_age_s=5.0)
        assert t == 500 and len(latest) == 5                     # the newest complete set
        assert link.latest_traffic(max_age_s=0.0) is None
    finally:
        veh.close()
        link.close()


# ---------------------------------------------------------------- the runtime's use of it
class _StubLink:
    """What Autopilot._sensed needs of a VehicleLink."""

    def __init__(self, sets: dict[int, list], sensor: bool = True) -> None:
        self.sets, self.sensor, self.asked = sets, sensor, []

    def wait_traffic_sensor(self, timeout_s):
        return self.sensor

    def wait_for(self, msg_type, predicate, timeout_s):
        return HomePosition(*DEFAULT_HOME_DEG, 488.0) if msg_type is HomePosition else None

    def sensed_traffic(self, t_ms, timeout_s):
        self.asked.append(t_ms)
        if t_ms not in self.sets:
            raise TelemetryTimeout(f"traffic set at {t_ms} ms", 1, timeout_s)
        return self.sets[t_ms]

    def latest_traffic(self, max_age_s):
        return max(self.sets.items()) if self.sets else None

    def latest(self, msg_type):
        return self.home if msg_type is HomePosition else None

    home = None


def _autopilot(link, lockstep=True, preset="default"):
    from mfg_autopilot.runtime.autopilot import Autopilot, AutopilotConfig, ControllerLog

    cfg = AutopilotConfig(instance=0, connect="udpin:127.0.0.1:1", mode="mfg", preset=preset, n=3, lockstep=lockstep,
                          sites_m=((0.0, 0.0), (1.0, 0.0), (2.0, 0.0)), step_timeout_s=0.1)
    return Autopilot(cfg, link, None, ControllerLog(None), threading.Event())


def test_real_time_traffic_is_carried_to_the_step_and_placed_from_home_where_home_is():
    # Given a traffic set stamped 1.5 s (vehicle clock) and a step at 1.6 s, in real time
    states = np.array([[4.0, 1.0, 2.0, -1.0], [6.0, -2.0, 0.0, 3.0]])
    link = _StubLink({1500: traffic_reports(np.array([1, 2]), states, 1500)})
    got = _autopilot(link, lockstep=False)._observe(3, np.zeros(4), 1.6).sensed.states
    # Then each neighbour is where it is at the step: its sensed position carried 0.1 s at its sensed velocity
    want = quantise_sensed_states(states)
    want[:, 0:2] += 0.1 * want[:, 2:4]
    np.testing.assert_allclose(got, want, atol=1e-9)
    # And a HOME_POSITION away from the LOCAL_NED origin (PX4 sets home where it arms: a vehicle that drifted before)
    # places the traffic from there: ADSB_VEHICLE's latitude/longitude are north/east of home, home is at (x, y)
    link.home = HomePosition(*DEFAULT_HOME_DEG, 488.0, 0.4, -0.3, 0.0)
    got = _autopilot(link, lockstep=False)._observe(3, np.zeros(4), 1.5).sensed.states
    np.testing.assert_allclose(got[:, 0:2], quantise_sensed_states(states)[:, 0:2] + [0.4, -0.3], atol=1e-9)


def test_runtime_fills_observation_sensed_from_the_steps_traffic_set():
    from mfg_autopilot.runtime.autopilot import AutopilotError

    states = _random_states(np.random.default_rng(9), 3)[1:]
    link = _StubLink({1500: traffic_reports(np.array([2, 1]), states, 1500)})
    ap = _autopilot(link)
    obs = ap._observe(3, np.zeros(4), 1.5)
    assert link.asked == [1500]
    assert obs.sensed.ids.tolist() == [1, 2] and obs.sensed.owner.tolist() == [0, 0]
    assert np.array_equal(obs.sensed.states, quantise_sensed_states(states[::-1]))
    with pytest.raises(AutopilotError, match="no complete traffic set for t = 2000 ms"):
        ap._observe(4, np.zeros(4), 2.0)
    # real time: the newest set
    assert _autopilot(link, lockstep=False)._observe(3, np.zeros(4), 7.3).sensed.ids.tolist() == [1, 2]
    # a vehicle without a sensor: no sensed set, never waited for again
    ap = _autopilot(_StubLink({}, sensor=False))
    assert ap._observe(0, np.zeros(4), 0.0).sensed is None and ap._observe(1, np.zeros(4), 0.5).sensed is None
    # a controller without a sensor range (paper preset) never asks
    link = _StubLink({})
    assert _autopilot(link, preset="paper")._observe(0, np.zeros(4), 0.0).sensed is None and link.asked == []


def test_the_mission_clock_is_agreed_from_the_t0_exchange():
    # every vehicle computes the same real-time mission start from the same exchanged states: the latest publication
    # plus the take-off margin, whatever its own clock says now; zeros (lockstep, an older sender) say nothing
    from mfg_autopilot.runtime.timing import START_MARGIN_S, agreed_start_unix_s

    published = [1000.0, 1000.07, 0.0, 1000.128]
    starts = {agreed_start_unix_s(published, now)[0] for now in (1000.2, 1000.9, 1001.5)}
    assert starts == {1000.128 + START_MARGIN_S}
    assert agreed_start_unix_s(published, 1000.2)[1] is None
    # nobody gave a time: its own clock, said so
    start, note = agreed_start_unix_s([0.0, 0.0], 55.0)
    assert start == 55.0 and "own mission clock" in note
    # a clock far ahead is not waited for
    start, note = agreed_start_unix_s([1000.0, 5000.0], 1001.0)
    assert start == 1001.0 and "clock is off" in note
    # a start already past (a vehicle slow to reach OFFBOARD) stays the agreed one: that vehicle catches up
    assert agreed_start_unix_s([1000.0], 1010.0)[0] == 1000.0 + START_MARGIN_S
