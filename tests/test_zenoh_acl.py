"""Zenoh access control: a router process with user/password authentication and an
access-control list (examples/zenoh_acl/), legitimate vehicles in client mode, and forgers.

- Without the swarm's credentials (none, or a wrong password) the router refuses the session:
  ``SwarmExchange.open`` raises ``ExchangeError``.
- With valid "observer" credentials the session opens and may listen, but its puts on
  ``mfg/demo/state/**``, its liveliness token and its init queryable are dropped by the router:
  the forged states are never counted, never returned by ``initial_exchange`` or ``gossip``,
  and the forger never appears in ``present()``.
- Control: the same put made with the vehicle credentials does arrive (the path is open, the
  ACL is what stops the forger).
"""

from __future__ import annotations

import json
import re
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import psutil
import pytest
import zenoh

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _zenoh_helpers import REPO, Proc, ep, free_tcp_port, router_argv, stop_all

from mfg_autopilot.runtime.exchange import (
    ExchangeError,
    StateMsg,
    SwarmExchange,
    ZenohSettings,
    alive_key,
    init_key,
    state_key,
)

pytestmark = pytest.mark.e2e

EXAMPLES = REPO / "examples" / "zenoh_acl"
SWARM = "demo"  # the swarm the example ACL is written for; each test has its own router/port
FORGED_X_M = 666.0


from _zenoh_helpers import no_process_left_behind  # noqa: E402,F401  (autouse fixture)


def wait_until(pred, timeout_s: float, what: str):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        v = pred()
        if v:
            return v
        time.sleep(0.02)
    raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")


@pytest.fixture
def acl(tmp_path):
    """The example configs copied to tmp_path, pointing at a free port and at the copied
    credentials file; yields (port, {name: path})."""
    port = free_tcp_port()
    paths = {}
    creds = tmp_path / "credentials.txt"
    creds.write_text((EXAMPLES / "credentials.txt").read_text())
    creds.chmod(0o600)
    for name in ("router", "vehicle", "observer"):
        text = (EXAMPLES / f"{name}.json5").read_text()
        text = text.replace('"examples/zenoh_acl/credentials.txt"', json.dumps(str(creds)))
        text = re.sub(r'"tcp/(127\.0\.0\.1|0\.0\.0\.0):7447"', f'"tcp/127.0.0.1:{port}"', text)
        p = tmp_path / f"{name}.json5"
        p.write_text(text)
        paths[name] = p
    # a vehicle config with the right user and a wrong password, and one without credentials
    vehicle = paths["vehicle"].read_text()
    paths["wrong_password"] = tmp_path / "wrong_password.json5"
    paths["wrong_password"].write_text(vehicle.replace("change-me-vehicle", "guessed"))
    paths["no_credentials"] = tmp_path / "no_credentials.json5"
    paths["no_credentials"].write_text(re.sub(r"transport: \{.*?\n  \},\n", "", vehicle, flags=re.S))
    assert "usrpwd" not in paths["no_credentials"].read_text()
    return port, paths


@pytest.fixture
def acl_router(acl):
    port, paths = acl
    router = Proc(router_argv([ep(port)]) + ["--zenoh-config", str(paths["router"])], "router")
    try:
        assert router.next_line(20) == "ready", router.stderr_lines
        yield port, paths
    finally:
        stop_all([router])


def settings(port: int, config: Path) -> ZenohSettings:
    return ZenohSettings(mode="client", connect=(ep(port),), config_file=str(config))


def raw_config(port: int, config: Path) -> zenoh.Config:
    return settings(port, config).to_config()


def test_example_configs_parse():
    for name in ("router", "vehicle", "observer"):
        zenoh.Config.from_file(str(EXAMPLES / f"{name}.json5"))


@pytest.mark.parametrize("config", ["no_credentials", "wrong_password"])
def test_session_without_the_swarm_credentials_is_refused(acl_router, config):
    port, paths = acl_router
    ex = SwarmExchange(settings(port, paths[config]), SWARM, 0, 1)
    t0 = time.monotonic()
    with pytest.raises(ExchangeError, match="cannot open zenoh session"):
        ex.open()
    assert time.monotonic() - t0 < 5.0
    ex.close()
    # the same session with the right credentials opens (the router is up and reachable)
    with SwarmExchange(settings(port, paths["vehicle"]), SWARM, 0, 1) as ok:
        assert ok.present() == {0}


class Forger:
    """An authenticated but unauthorised session (observer credentials) that floods forged,
    well-formed states for vehicles 0..n (every step 0..steps, at x = 666 m), holds the
    liveliness token of vehicle 7 and answers init queries with forged t = 0 states."""

    def __init__(self, port: int, config: Path, n: int, steps: int):
        self.session = zenoh.open(raw_config(port, config))
        self.n, self.steps = n, steps
        self.stop = threading.Event()
        self.puts = 0
        self.replies = 0
        self.entities = [
            self.session.liveliness().declare_token(alive_key(SWARM, 7)),
            self.session.declare_queryable(init_key(SWARM, "**"), self._on_query),
        ]
        self.thread = threading.Thread(target=self._flood, daemon=True)
        self.thread.start()

    def forged(self, vid: int, step: int) -> bytes:
        return StateMsg(vid, step, float(step), (FORGED_X_M, 0.0, 0.0, 0.0)).encode()

    def _on_query(self, query) -> None:
        for vid in range(self.n):
            query.reply(init_key(SWARM, vid), self.forged(vid, 0))
            self.replies += 1

    def _flood(self) -> None:
        while not self.stop.is_set():
            for step in range(self.steps + 1):
                for vid in range(self.n):
                    self.session.put(state_key(SWARM, vid), self.forged(vid, step))
                    self.puts += 1
            self.stop.wait(0.01)

    def close(self) -> None:
        self.stop.set()
        self.thread.join(5)
        self.entities.clear()
        self.session.close()


def test_forged_states_from_unauthorised_user_never_reach_the_exchange(acl_router):
    """Three vehicles (client mode, vehicle credentials) do the t = 0 exchange and 3 lockstep
    gossip steps while an observer-credentialed forger floods states for ids 0-2 at
    x = 666 m, holds a token for vehicle 7 and answers init queries. Nothing forged arrives."""
    port, paths = acl_router
    n, steps = 3, 3
    xs = [0.0, 1.0, 2.0]
    exs = [SwarmExchange(settings(port, paths["vehicle"]), SWARM, i, n) for i in range(n)]
    forger = None
    watched: list[StateMsg] = []
    try:
        for ex in exs:
            ex.open()
        forger = Forger(port, paths["observer"], n, steps)
        # an observer may still watch the swarm: it hears the legitimate states
        watch = forger.session.declare_subscriber(
            state_key(SWARM, "*"), lambda s: watched.append(StateMsg.decode(s.payload.to_bytes())))
        wait_until(lambda: forger.puts > 1000, 10, "the forger to flood")

        def fly(i: int):
            ex = exs[i]
            init = ex.initial_exchange([xs[i], 0.0, 0.0, 0.0], timeout_s=15)
            got = [ex.gossip(s, float(s), [xs[i], 0.0, 0.0, 0.0], 100.0, timeout_s=5)
                   for s in range(1, steps + 1)]
            return init, got

        with ThreadPoolExecutor(n) as pool:
            results = [f.result(timeout=60) for f in [pool.submit(fly, i) for i in range(n)]]
        time.sleep(0.3)  # the forger keeps flooding while the vehicles look
        for i, (init, got) in enumerate(results):
            ex = exs[i]
            assert {k: m.state[0] for k, m in init.items()} == dict(enumerate(xs))
            for per_step in got:
                assert [(m.vehicle_id, m.state[0]) for m in per_step] == \
                    [(j, xs[j]) for j in range(n) if j != i]
            assert ex.present() == set(range(n))  # no token 7
            assert ex.states_received_by_step == {s: n - 1 for s in range(steps + 1)}
            # heard: the other vehicles' step-0 puts (or init replies) and gossip puts only
            assert ex.states_heard_total <= (n - 1) * (steps + 1) + (n - 1) * 10
            assert ex.malformed_counts == {}
            assert all(m.state[0] != FORGED_X_M for m in ex._latest.values())
        assert forger.puts > 1000
        # (its own forged puts are delivered to its own subscriber locally, never beyond it)
        assert {m.vehicle_id for m in watched if m.state[0] != FORGED_X_M} == set(range(n))

        # control: the same kind of put with the vehicle credentials does reach the exchange
        heard0 = exs[0].states_heard_total
        with zenoh.open(raw_config(port, paths["vehicle"])) as insider:
            wait_until(lambda: (insider.put(state_key(SWARM, 2), forger.forged(2, 99)),
                                exs[0].states_heard_total > heard0)[1], 5,
                       "a vehicle-credentialed put to arrive")
        assert exs[0]._latest[2].state[0] == FORGED_X_M
    finally:
        if forger is not None:
            forger.close()
        for ex in exs:
            ex.close()


def _load_make_acl():
    import importlib.util
    spec = importlib.util.spec_from_file_location("make_acl", EXAMPLES / "make_acl.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_per_vehicle_acl_a_vehicle_cannot_speak_for_another(tmp_path):
    """examples/zenoh_acl/make_acl.py (one user per vehicle): three vehicles complete the t = 0
    exchange and 2 gossip steps while a session logged in with vehicle 1's credentials floods
    forged states for vehicles 0 and 2 and holds their tokens: none of it arrives. Control: the
    same session's put on vehicle 1's own key does arrive."""
    n, swarm = 3, "pv"
    port = free_tcp_port()
    paths = _load_make_acl().main(swarm, n, ep(port), ep(port), tmp_path / "acl")
    for name in ("credentials", "router", "vehicle0", "observer"):
        assert paths[name].stat().st_mode & 0o077 == 0, name
    router = Proc(router_argv([ep(port)]) + ["--zenoh-config", str(paths["router"])], "router")
    exs = [SwarmExchange(settings(port, paths[f"vehicle{i}"]), swarm, i, n) for i in range(n)]
    xs = [0.0, 1.0, 2.0]
    forger = None
    stop = threading.Event()
    puts = [0]
    t = None
    try:
        assert router.next_line(20) == "ready", router.stderr_lines
        for ex in exs:
            ex.open()
        forger = zenoh.open(raw_config(port, paths["vehicle1"]))
        tokens = [forger.liveliness().declare_token(alive_key(swarm, v)) for v in (0, 2)]

        def flood():
            while not stop.is_set():
                for step in range(3):
                    for vid in (0, 2):
                        forger.put(state_key(swarm, vid), StateMsg(
                            vid, step, float(step), (FORGED_X_M, 0.0, 0.0, 0.0)).encode())
                        puts[0] += 1
                stop.wait(0.01)

        t = threading.Thread(target=flood, daemon=True)
        t.start()
        wait_until(lambda: puts[0] > 300, 10, "the forger to flood")

        def fly(i: int):
            ex = exs[i]
            init = ex.initial_exchange([xs[i], 0.0, 0.0, 0.0], timeout_s=15)
            got = [ex.gossip(s, float(s), [xs[i], 0.0, 0.0, 0.0], 100.0, timeout_s=5)
                   for s in (1, 2)]
            return init, got

        with ThreadPoolExecutor(n) as pool:
            results = [f.result(timeout=60) for f in [pool.submit(fly, i) for i in range(n)]]
        for i, (init, got) in enumerate(results):
            assert {k: m.state[0] for k, m in init.items()} == dict(enumerate(xs))
            for per_step in got:
                assert [(m.vehicle_id, m.state[0]) for m in per_step] == \
                    [(j, xs[j]) for j in range(n) if j != i]
            assert exs[i].states_received_by_step == {0: 2, 1: 2, 2: 2}
        # control: vehicle 1's credentials may put on vehicle 1's key
        heard0 = exs[0].states_heard_total
        wait_until(lambda: (forger.put(state_key(swarm, 1), StateMsg(
            1, 99, 99.0, (FORGED_X_M, 0.0, 0.0, 0.0)).encode()),
            exs[0].states_heard_total > heard0)[1], 5, "vehicle 1's own put to arrive")
        del tokens
    finally:
        stop.set()
        if t is not None:
            t.join(10)          # the flood ends before its session closes (a put on a closed session raises)
        if forger is not None:
            forger.close()
        for ex in exs:
            ex.close()
        stop_all([router])
