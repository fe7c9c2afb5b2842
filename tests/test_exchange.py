"""Zenoh swarm exchange, in one process: payload, settings, membership, t = 0 exchange,
gossip semantics, malformed input. Several sessions in one process talk over loopback TCP
with multicast scouting off; every session is closed explicitly (SPEC section 5)."""

from __future__ import annotations

import argparse
import logging
import math
import struct
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _zenoh_helpers import ep, free_tcp_port

from mfg_autopilot.runtime.exchange import (
    PAYLOAD_SIZE,
    ExchangeStopped,
    ExchangeTimeout,
    PayloadError,
    StateMsg,
    SwarmExchange,
    ZenohSettings,
)


def wait_until(pred, timeout_s: float, what: str):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        v = pred()
        if v:
            return v
        time.sleep(0.01)
    raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")


@pytest.fixture
def swarm_name(request):
    return "t" + str(abs(hash(request.node.name)) % 10**8)


def make_swarm(swarm: str, n: int, n_expected: int | None = None):
    """n exchanges in a star: vehicle 0 listens, the others connect to it."""
    p0 = free_tcp_port()
    exs = [SwarmExchange(ZenohSettings(listen=(ep(p0),)), swarm, 0, n_expected or n)]
    for i in range(1, n):
        exs.append(SwarmExchange(ZenohSettings(connect=(ep(p0),)), swarm, i, n_expected or n))
    return exs


class Opened:
    """Open several exchanges; close all of them on exit, whatever happens."""

    def __init__(self, exs):
        self.exs = exs

    def __enter__(self):
        try:
            for e in self.exs:
                e.open()
        except BaseException:
            self.__exit__()
            raise
        return self.exs

    def __exit__(self, *exc):
        for e in self.exs:
            e.close()


def in_parallel(fns):
    with ThreadPoolExecutor(len(fns)) as pool:
        return [f.result(timeout=30) for f in [pool.submit(fn) for fn in fns]]


# ---- payload ---------------------------------------------------------------------------
def test_payload_round_trip_and_layout():
    m = StateMsg(7, 123456789012, 12.5, (150.0, -100.25, 1.0, -1.0))
    b = m.encode()
    assert len(b) == PAYLOAD_SIZE == 56
    assert StateMsg.decode(b) == m
    # the documented layout (docs/zenoh.md), read with plain struct
    assert struct.unpack("<2sBBIqd4d", b) == (b"MF", 1, 0, 7, 123456789012, 12.5,
                                              150.0, -100.25, 1.0, -1.0)


@pytest.mark.parametrize("mutate, kind", [
    (lambda b: b[:-1], "length"),
    (lambda b: b + b"\0", "length"),
    (lambda b: b"", "length"),
    (lambda b: b"XX" + b[2:], "magic"),
    (lambda b: b[:2] + bytes([2]) + b[3:], "version"),
    (lambda b: b[:3] + bytes([1]) + b[4:], "flags"),
    (lambda b: b[:24] + struct.pack("<d", math.nan) + b[32:], "non_finite"),
    (lambda b: b[:16] + struct.pack("<d", math.inf) + b[24:], "non_finite"),
    (lambda b: b[:8] + struct.pack("<q", -1) + b[16:], "range"),
])
def test_malformed_payload_raises(mutate, kind):
    good = StateMsg(1, 2, 3.0, (1.0, 2.0, 3.0, 4.0)).encode()
    with pytest.raises(PayloadError, match=kind) as ei:
        StateMsg.decode(mutate(good))
    assert ei.value.kind == kind


def test_encode_rejects_non_finite():
    with pytest.raises(PayloadError, match="non_finite"):
        StateMsg(1, 0, 0.0, (math.nan, 0.0, 0.0, 0.0)).encode()


# ---- settings --------------------------------------------------------------------------
def test_settings_from_cli_and_config(tmp_path):
    ap = argparse.ArgumentParser()
    ZenohSettings.add_cli_args(ap)
    cfg = tmp_path / "z.json5"
    cfg.write_text('{ mode: "client", transport: { link: { tx: { lease: 3000 } } } }')
    ns = ap.parse_args(["--zenoh-mode", "client", "--zenoh-connect", "tcp/127.0.0.1:7447",
                        "--zenoh-connect", "tcp/127.0.0.1:7448", "--zenoh-config", str(cfg)])
    s = ZenohSettings.from_args(ns)
    assert s == ZenohSettings("client", ("tcp/127.0.0.1:7447", "tcp/127.0.0.1:7448"), (),
                              str(cfg), False)
    conf = s.to_config()
    assert conf.get_json("mode") == '"client"'
    assert conf.get_json("transport/link/tx/lease") == "3000"  # from the file
    assert "7448" in conf.get_json("connect/endpoints")
    assert conf.get_json("scouting/multicast/enabled") == "false"
    default = ZenohSettings().to_config()
    assert default.get_json("mode") == '"peer"'
    assert "127.0.0.1:0" in default.get_json("listen/endpoints")  # loopback by default
    with pytest.raises(ValueError, match="mode"):
        ZenohSettings(mode="bogus")


# ---- t = 0 exchange ---------------------------------------------------------------------
def test_initial_exchange_late_joiner_gets_earlier_states(swarm_name):
    """Vehicles 0 and 1 publish their t = 0 state before vehicle 2 exists; 2 still gets them
    (init queryable), and the counts are N - 1 at step 0."""
    a, b, c = make_swarm(swarm_name, 3)
    with Opened([a, b]):
        results = {}
        ts = [threading.Thread(target=lambda ex=ex, i=i: results.setdefault(
            i, ex.initial_exchange([float(i), 0, 0, 0], timeout_s=10))) for i, ex in enumerate([a, b])]
        for t in ts:
            t.start()
        time.sleep(0.4)  # a and b have published and are waiting for 2
        with Opened([c]):
            results[2] = c.initial_exchange([2.0, 0, 0, 0], timeout_s=10)
            for t in ts:
                t.join(timeout=10)
            assert c.states_heard_total >= 2
    for i in range(3):
        assert sorted(results[i]) == [0, 1, 2]
        assert [results[i][j].state[0] for j in range(3)] == [0.0, 1.0, 2.0]
    for ex in (a, b, c):
        assert ex.states_received_by_step == {0: 2} and ex.states_received_total == 2


def test_initial_exchange_timeout_names_missing(swarm_name):
    a, b = make_swarm(swarm_name, 2, n_expected=4)
    with Opened([a, b]):
        t0 = time.monotonic()
        with pytest.raises(ExchangeTimeout, match=r"missing vehicles \[2, 3\]") as ei:
            in_parallel([lambda: a.initial_exchange([0, 0, 0, 0], timeout_s=1.0),
                         lambda: b.initial_exchange([1, 0, 0, 0], timeout_s=1.0)])
        assert ei.value.missing == (2, 3)
        assert time.monotonic() - t0 < 3.0


def test_initial_exchange_and_wait_present_give_up_when_stopped(swarm_name):
    """A signal during the t = 0 exchange (the stop event) ends the wait within a fraction of
    a second instead of at the exchange timeout."""
    (a,) = make_swarm(swarm_name, 1, n_expected=3)
    stop = threading.Event()
    with Opened([a]):
        threading.Timer(0.3, stop.set).start()
        t0 = time.monotonic()
        with pytest.raises(ExchangeStopped, match=r"still missing \[1, 2\]"):
            a.initial_exchange([0, 0, 0, 0], timeout_s=60.0, stop=stop)
        with pytest.raises(ExchangeStopped):
            a.wait_present(range(3), timeout_s=60.0, stop=stop)
        assert time.monotonic() - t0 < 5.0


def test_finish_lockstep_waits_for_every_present_vehicle_and_counts_nothing(swarm_name):
    a, b = make_swarm(swarm_name, 2)
    with Opened([a, b]):
        wait_until(lambda: a.present() == {0, 1} and b.present() == {0, 1}, 10, "both present")
        t0 = time.monotonic()
        assert a.finish_lockstep(7, 3.5, [0, 0, 0, 0], timeout_s=0.5) == {1}       # b has not finished
        assert time.monotonic() - t0 >= 0.45
        got = in_parallel([lambda: a.finish_lockstep(8, 4.0, [0, 0, 0, 0], timeout_s=10),
                           lambda: b.finish_lockstep(8, 4.0, [1, 0, 0, 0], timeout_s=10)])
        assert got == [frozenset(), frozenset()]
        assert a.states_received_total == b.states_received_total == 0


def test_present_and_lost(swarm_name):
    a, b, c = make_swarm(swarm_name, 3)
    lost = []
    a.on_vehicle_lost(lost.append)
    with Opened([a, b]):
        with Opened([c]):
            wait_until(lambda: a.present() == {0, 1, 2}, 5, "all present")
        wait_until(lambda: a.present() == {0, 1}, 5, "vehicle 2 gone")
        assert a.lost() == {2} and lost == [2]


# ---- gossip ----------------------------------------------------------------------------
def test_gossip_in_range_and_counts(swarm_name):
    pos = [0.0, 1.0, 2.0, 10.0]  # range 1.5: 0-1, 1-2 neighbours; 3 alone
    exs = make_swarm(swarm_name, 4)
    with Opened(exs):
        wait_until(lambda: all(e.present() == {0, 1, 2, 3} for e in exs), 5, "all present")
        for step in (1, 2):
            got = in_parallel([lambda e=e, x=x: e.gossip(step, step * 1.0, [x, 0, 0, 0], 1.5, 5.0)
                               for e, x in zip(exs, pos)])
            assert [[m.vehicle_id for m in g] for g in got] == [[1], [0, 2], [1], []]
            assert all(m.step == step for g in got for m in g)
    assert [e.states_received_by_step for e in exs] == [{1: 1, 2: 1}, {1: 2, 2: 2},
                                                        {1: 1, 2: 1}, {1: 0, 2: 0}]
    assert [e.states_received_total for e in exs] == [2, 4, 2, 0]


def test_gossip_silent_vehicle_dropped_after_deadline_once(swarm_name, caplog):
    """Vehicle 2 stays present but stops publishing: the first step waits the deadline, the
    next steps do not wait for it; when it publishes again it is back."""
    a, b, c = make_swarm(swarm_name, 3)
    with Opened([a, b, c]), caplog.at_level(logging.WARNING, logger="mfg_autopilot.runtime.exchange"):
        wait_until(lambda: a.present() == {0, 1, 2}, 5, "all present")
        t0 = time.monotonic()
        got = in_parallel([lambda: a.gossip(1, 1.0, [0, 0, 0, 0], 100, 0.6),
                           lambda: b.gossip(1, 1.0, [1, 0, 0, 0], 100, 0.6)])
        assert time.monotonic() - t0 >= 0.55
        assert [m.vehicle_id for m in got[0]] == [1]
        t1 = time.monotonic()
        for step in (2, 3):
            in_parallel([lambda: a.gossip(step, 1.0, [0, 0, 0, 0], 100, 0.6),
                         lambda: b.gossip(step, 1.0, [1, 0, 0, 0], 100, 0.6)])
        assert time.monotonic() - t1 < 0.5  # no second deadline
        assert sum("no state for step 1 from vehicles [2]" in r.message for r in caplog.records) == 2
        assert not any("step 2" in r.message or "step 3" in r.message for r in caplog.records)
        c.publish_state(4, 4.0, [2, 0, 0, 0])  # back
        got = in_parallel([lambda: a.gossip(4, 4.0, [0, 0, 0, 0], 100, 2.0),
                           lambda: b.gossip(4, 4.0, [1, 0, 0, 0], 100, 2.0)])
        assert [m.vehicle_id for m in got[0]] == [1, 2]


def test_gossip_real_time_takes_latest_without_waiting(swarm_name):
    a, b = make_swarm(swarm_name, 2)
    with Opened([a, b]):
        wait_until(lambda: a.present() == {0, 1}, 5, "both present")
        t0 = time.monotonic()
        assert a.gossip(1, 0.1, [0, 0, 0, 0], 5.0, 5.0, lockstep=False) == []
        assert time.monotonic() - t0 < 0.5
        b.publish_state(3, 0.3, [1, 0, 0, 0])
        b.publish_state(4, 0.4, [2, 0, 0, 0])
        wait_until(lambda: a.states_heard_total >= 2, 5, "states heard")
        got = a.gossip(2, 0.2, [0, 0, 0, 0], 5.0, 5.0, lockstep=False)
        assert [(m.vehicle_id, m.step) for m in got] == [(1, 4)]
        got = a.gossip(3, 0.3, [0, 0, 0, 0], 5.0, 5.0, lockstep=False)
        assert [(m.vehicle_id, m.step) for m in got] == [(1, 4)]  # still the latest ...
        assert a.states_received_total == 1  # ... but counted once
        assert a.gossip(4, 0.4, [100, 0, 0, 0], 5.0, 5.0, lockstep=False) == []  # out of range


# ---- malformed input on the wire -------------------------------------------------------
def test_garbage_on_state_keys_is_dropped_and_logged(swarm_name, caplog):
    import zenoh  # the test plays a misbehaving third party

    a, b = make_swarm(swarm_name, 2)
    port = int(a.settings.listen[0].rsplit(":", 1)[1])
    conf = ZenohSettings(connect=(ep(port),)).to_config()
    with Opened([a, b]), caplog.at_level(logging.WARNING, logger="mfg_autopilot.runtime.exchange"):
        with zenoh.open(conf) as z:
            wait_until(lambda: a.present() == {0, 1}, 5, "both present")
            time.sleep(0.2)  # let the third party learn a's subscriber
            key = f"mfg/{swarm_name}/state/1"
            good = StateMsg(1, 1, 1.0, (1.0, 0, 0, 0)).encode()
            for _ in range(5):
                z.put(key, b"garbage")
            z.put(key, good[:3] + b"\x07" + good[4:])  # flags set
            z.put(key, good[:24] + struct.pack("<d", math.nan) + good[32:])
            z.put(f"mfg/{swarm_name}/state/9", good)  # key does not match the payload's id
            z.put(f"mfg/{swarm_name}/state/x", good)
            wait_until(lambda: sum(a.malformed_counts.values()) >= 9, 5, "garbage counted")
        assert a.malformed_counts == {"length": 5, "flags": 1, "non_finite": 1, "key": 2}
        warnings = [r.message for r in caplog.records if r.message.startswith("vehicle 0: dropped malformed state (")]
        assert len(warnings) == 4  # once per kind, then only counted
        # still works
        got = in_parallel([lambda: a.gossip(1, 1.0, [0, 0, 0, 0], 5, 5.0),
                           lambda: b.gossip(1, 1.0, [1, 0, 0, 0], 5, 5.0)])
        assert [m.vehicle_id for m in got[0]] == [1] and [m.vehicle_id for m in got[1]] == [0]


def test_closes_on_exception(swarm_name):
    ex = SwarmExchange(ZenohSettings(listen=(ep(free_tcp_port()),)), swarm_name, 0, 1)
    with pytest.raises(RuntimeError, match="boom"):
        with ex:
            raise RuntimeError("boom")
    assert ex._session is None
    with pytest.raises(Exception, match="not open"):
        ex.publish_state(1, 0.0, [0, 0, 0, 0])
