"""Zenoh swarm exchange with real processes: N peers on loopback, a killed vehicle, client
mode through a router process, two network namespaces joined through a router, and the
independent watcher example. Each vehicle is ``tests/_zenoh_helpers.py`` run as a script."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import psutil
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _zenoh_helpers import REPO, Proc, ep, free_tcp_port, router_argv, stop_all, vehicle_argv

from mfg_autopilot.runtime.exchange import SwarmExchange, ZenohSettings

pytestmark = pytest.mark.e2e

# Positions on a line; with range 1.5 m: 0-1, 1-2, 2-3 are neighbours, 4 is alone.
XS = [0.0, 1.0, 2.0, 3.0, 10.0]
NEIGHBOURS = {0: [1], 1: [0, 2], 2: [1, 3], 3: [2], 4: []}


from _zenoh_helpers import no_process_left_behind  # noqa: E402,F401  (autouse fixture)


@pytest.fixture
def swarm_name(request):
    return "e" + str(os.getpid()) + str(abs(hash(request.node.name)) % 10**6)


def run_swarm(procs: list[Proc], n: int, steps: int, timeout_s: float = 30.0):
    """Collect init, per-step and done events of every vehicle process."""
    inits = {i: p.next_event(timeout_s, "init") for i, p in enumerate(procs)}
    step_events = {i: [p.next_event(timeout_s, "step") for _ in range(steps)]
                   for i, p in enumerate(procs)}
    dones = {i: p.next_event(timeout_s, "done") for i, p in enumerate(procs)}
    return inits, step_events, dones


def check_swarm(inits, steps, dones, n, xs, neighbours):
    for i in range(n):
        assert sorted(int(k) for k in inits[i]["states"]) == list(range(n))
        assert [inits[i]["states"][str(j)][0] for j in range(n)] == xs[:n]
        assert inits[i]["received"] == n - 1
        for ev in steps[i]:
            assert ev["neighbours"] == neighbours[i], (i, ev)
            assert ev["present"] == list(range(n))
        want = {"0": n - 1} | {str(s["step"]): len(neighbours[i]) for s in steps[i]}
        assert dones[i]["received_by_step"] == want


def test_initial_exchange_and_gossip_five_peer_processes(swarm_name):
    """N = 5 peers, each listening on its own port, all connecting to vehicle 0 (started
    last, so the others' first attempts fail and retry); t = 0 exchange, then 3 lockstep
    gossip steps with range 1.5 m deliver exactly the in-range neighbours."""
    n = 5
    ports = [free_tcp_port() for _ in range(n)]
    procs: list[Proc] = []
    try:
        for i in reversed(range(n)):
            procs.insert(0, Proc(vehicle_argv(
                swarm_name, i, n, x=XS[i], steps=3, range_m=1.5, step_timeout_s=5.0,
                listen=[ep(ports[i])], connect=[ep(ports[0])] if i else []), f"veh{i}"))
            time.sleep(0.05)
        inits, steps, dones = run_swarm(procs, n, 3)
        check_swarm(inits, steps, dones, n, XS, NEIGHBOURS)
    finally:
        stop_all(procs)


def test_initial_exchange_timeout_names_missing_vehicles(swarm_name):
    """N = 4 expected, only vehicles 0 and 2 run: vehicle 2's exchange fails after its
    timeout and names vehicles 1 and 3."""
    port = free_tcp_port()
    procs: list[Proc] = []
    try:
        procs.append(Proc(vehicle_argv(swarm_name, 0, 4, listen=[ep(port)], init_timeout_s=3.5),
                          "veh0"))
        procs[0].next_event(15, "open")  # listening before vehicle 2 connects
        procs.append(Proc(vehicle_argv(swarm_name, 2, 4, connect=[ep(port)], init_timeout_s=1.5),
                          "veh2"))
        procs[1].next_event(15, "open")
        t0 = time.monotonic()
        ev = json.loads(procs[1].next_line(10))
        assert time.monotonic() - t0 < 5.0
        assert ev["event"] == "error" and ev["kind"] == "timeout"
        assert ev["missing"] == [1, 3] and "missing vehicles [1, 3]" in ev["message"]
    finally:
        stop_all(procs)


def test_killed_vehicle_is_gone_and_others_go_on(swarm_name):
    """4 vehicles gossip every 0.25 s; vehicle 3 is SIGKILLed after step 2. The others see it
    leave present() and keep stepping without waiting a deadline for it."""
    n, steps = 4, 8
    port = free_tcp_port()
    procs: list[Proc] = []
    try:
        for i in range(n):
            procs.append(Proc(vehicle_argv(
                swarm_name, i, n, x=float(i), steps=steps, range_m=100.0, step_timeout_s=3.0,
                step_period_s=0.25, listen=[ep(port)] if i == 0 else [],
                connect=[ep(port)] if i else []), f"veh{i}"))
        for pr in procs:
            pr.next_event(30, "init")
        for pr in procs:
            assert pr.next_event(10, "step")["step"] == 1
        ev = procs[3].next_event(10, "step")
        assert ev["step"] == 2
        procs[3].p.kill()
        procs[3].p.wait(timeout=5)
        t_kill = time.monotonic()
        for i in range(3):
            evs = [procs[i].next_event(15, "step") for _ in range(steps - 1)]
            late = [e for e in evs if 3 not in e["present"]]
            assert late, f"vehicle {i} never saw vehicle 3 leave: {evs}"
            assert late[-1]["lost"] == [3]
            assert all(e["wait_s"] < 2.0 for e in evs), evs  # never waited a 3 s deadline
            assert evs[-1]["neighbours"] == [j for j in range(3) if j != i]
            assert procs[i].next_event(10, "done")
        assert time.monotonic() - t_kill < 10
    finally:
        stop_all(procs)


def test_frozen_vehicle_drops_out_after_one_deadline(swarm_name):
    """Vehicle 2 is frozen (SIGSTOP) after step 2: its token stays alive (lease 10 s), so the
    others wait one deadline (1 s) for it, then step on without waiting for it again."""
    n, steps, deadline_s = 3, 7, 1.0
    port = free_tcp_port()
    procs: list[Proc] = []
    try:
        for i in range(n):
            procs.append(Proc(vehicle_argv(
                swarm_name, i, n, x=float(i), steps=steps, range_m=100.0,
                step_timeout_s=deadline_s, step_period_s=0.15,
                listen=[ep(port)] if i == 0 else [], connect=[ep(port)] if i else []), f"veh{i}"))
        for pr in procs:
            pr.next_event(30, "init")
        for _ in range(2):
            procs[2].next_event(10, "step")
        procs[2].p.send_signal(signal.SIGSTOP)
        for i in range(2):
            evs = [procs[i].next_event(15, "step") for _ in range(steps)]
            after = [e for e in evs if 2 not in e["neighbours"]]
            assert after, evs
            assert all(2 in e["present"] for e in evs)  # frozen, not gone
            waited = [e for e in after if e["wait_s"] > 0.8 * deadline_s]
            assert len(waited) == 1, evs  # exactly one deadline
            assert all(e["wait_s"] < 0.5 for e in after if e is not waited[0])
            assert after[-1]["neighbours"] == [1 - i]
    finally:
        if len(procs) == n:
            procs[2].kill()  # SIGKILL also ends a stopped process
        stop_all(procs)


def test_client_mode_through_router_process_same_as_peer(swarm_name):
    """A router process (python -m mfg_autopilot.runtime.router) and 5 vehicles in client
    mode: same t = 0 exchange and same neighbours as the peer test."""
    n = 5
    port = free_tcp_port()
    procs: list[Proc] = []
    try:
        router = Proc(router_argv([ep(port)]), "router")
        procs.append(router)
        assert router.next_line(20) == "ready"
        for i in range(n):
            procs.append(Proc(vehicle_argv(swarm_name, i, n, x=XS[i], steps=3, range_m=1.5,
                                           step_timeout_s=5.0, mode="client",
                                           connect=[ep(port)]), f"veh{i}"))
        inits, steps, dones = run_swarm(procs[1:], n, 3)
        check_swarm(inits, steps, dones, n, XS, NEIGHBOURS)
    finally:
        stop_all(procs)


def _sh(*argv: str) -> None:
    subprocess.run(argv, check=True, capture_output=True, timeout=10)


def _netns_unavailable() -> str | None:
    if shutil.which("ip") is None:
        return "iproute2 `ip` not installed"
    if os.geteuid() != 0:
        return "needs root to create network namespaces"
    probe = f"zxprobe{os.getpid()}"
    try:
        _sh("ip", "netns", "add", probe)
    except (subprocess.CalledProcessError, OSError) as e:
        return f"`ip netns add` failed: {getattr(e, 'stderr', e)!r}"
    finally:
        subprocess.run(["ip", "netns", "del", probe], capture_output=True, timeout=10)
    return None


def test_two_network_namespaces_joined_through_router(swarm_name):
    """Host A (netns, 10.201.K.1/30) runs a router and vehicles 0-1 as clients; host B (netns,
    10.201.K.2/30, joined by a veth pair) runs vehicles 2-3 as peers connecting to the router
    over the veth link. Multicast scouting off: traffic stays inside the two namespaces."""
    reason = _netns_unavailable()
    if reason:
        pytest.skip(f"network namespaces unavailable: {reason}")
    k = os.getpid() % 250 + 1
    ns_a, ns_b = f"zxa{os.getpid()}", f"zxb{os.getpid()}"
    veth_a, veth_b = f"zva{os.getpid() % 100000}", f"zvb{os.getpid() % 100000}"
    ip_a, ip_b = f"10.201.{k}.1", f"10.201.{k}.2"
    n, port = 4, 7447
    xs = [0.0, 1.0, 2.0, 3.0]
    neighbours = {0: [1], 1: [0, 2], 2: [1, 3], 3: [2]}
    procs: list[Proc] = []
    try:
        _sh("ip", "netns", "add", ns_a)
        _sh("ip", "netns", "add", ns_b)
        _sh("ip", "link", "add", veth_a, "type", "veth", "peer", "name", veth_b)
        _sh("ip", "link", "set", veth_a, "netns", ns_a)
        _sh("ip", "link", "set", veth_b, "netns", ns_b)
        for ns, dev, addr in ((ns_a, veth_a, ip_a), (ns_b, veth_b, ip_b)):
            _sh("ip", "-n", ns, "addr", "add", f"{addr}/30", "dev", dev)
            _sh("ip", "-n", ns, "link", "set", dev, "up")
            _sh("ip", "-n", ns, "link", "set", "lo", "up")
        router = Proc(router_argv([ep(port, ip_a)], netns=ns_a), "router@A")
        procs.append(router)
        assert router.next_line(20) == "ready"
        vehicles = []
        for i in range(n):
            on_a = i < 2
            vehicles.append(Proc(vehicle_argv(
                swarm_name, i, n, x=xs[i], steps=2, range_m=1.5, step_timeout_s=5.0,
                mode="client" if on_a else "peer", connect=[ep(port, ip_a)],
                listen=[] if on_a else [ep(7448 + i, ip_b)],
                netns=ns_a if on_a else ns_b), f"veh{i}@{'A' if on_a else 'B'}"))
        procs += vehicles
        inits, steps, dones = run_swarm(vehicles, n, 2)
        check_swarm(inits, steps, dones, n, xs, neighbours)
    finally:
        stop_all(procs)
        for ns in (ns_a, ns_b):  # deleting a namespace deletes its end of the veth pair
            subprocess.run(["ip", "netns", "del", ns], capture_output=True, timeout=10)
        subprocess.run(["ip", "link", "del", veth_a], capture_output=True, timeout=10)
    out = subprocess.run(["ip", "netns", "list"], capture_output=True, text=True).stdout
    assert ns_a not in out and ns_b not in out


def test_watcher_example_prints_decoded_states(swarm_name):
    """examples/watch_swarm.py, a separate process with its own session, prints the t = 0
    states (via the init queryables) and the live states of a running 2-vehicle swarm."""
    port = free_tcp_port()
    a = SwarmExchange(ZenohSettings(listen=(ep(port),)), swarm_name, 0, 2)
    b = SwarmExchange(ZenohSettings(connect=(ep(port),)), swarm_name, 1, 2)
    procs: list[Proc] = []
    try:
        with a, b:
            import threading
            t = threading.Thread(target=lambda: a.initial_exchange([150.0, 100.0, 1.0, -1.0], 10))
            t.start()
            b.initial_exchange([151.5, 100.0, 1.0, -1.0], 10)
            t.join(10)
            w = Proc([sys.executable, str(REPO / "examples" / "watch_swarm.py"), "--swarm",
                      swarm_name, "--connect", ep(port), "--count", "6", "--duration", "20",
                      "--vehicles", "2"],
                     "watcher", stdin_pipe=False)
            procs.append(w)
            lines = []
            while sum(ln.startswith("init ") for ln in lines) < 2:  # t = 0 states first
                lines.append(w.next_line(40))   # a cold Python + zenoh start on a loaded 2-core machine
            step = 1
            deadline = time.monotonic() + 20
            while w.p.poll() is None and time.monotonic() < deadline:
                a.publish_state(step, step * 0.1, [150.0 - step, 100.0, 1.0, -1.0])
                b.publish_state(step, step * 0.1, [151.5 - step, 100.0, 1.0, -1.0])
                step += 1
                time.sleep(0.05)
            w.p.wait(timeout=10)
            time.sleep(0.1)  # reader thread drains the pipe
            while not w.lines.empty():
                lines.append(w.lines.get())
        text = "\n".join(lines)
        assert "init vehicle=0 step=0 t=0.000s x=150.00m y=100.00m vx=1.00m/s vy=-1.00m/s" in text
        assert "init vehicle=1 step=0 t=0.000s x=151.50m" in text
        assert "state vehicle=0 step=" in text and "state vehicle=1 step=" in text
        assert "alive vehicle=0 joined" in text and "alive vehicle=1 joined" in text
    finally:
        stop_all(procs)
