"""Zenoh faults with real processes (each vehicle is tests/_zenoh_helpers.py run as a script):
a router killed and restarted mid-flight (client mode), a peer that vanishes (the one the
others connected to), a late joiner (a restarted vehicle after the t = 0 exchange, and one
after the others have finished), and a lossy link (tc netem on a namespace's veth).

Short versions of bench/zenoh_faults.py, which measures the same scenarios for longer
(docs/zenoh.md, "## Faults")."""

from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path

import psutil
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
from _zenoh_helpers import Proc, ep, free_tcp_port, stop_all, vehicle_argv
import zenoh_faults as zf

pytestmark = pytest.mark.e2e


from _zenoh_helpers import no_process_left_behind  # noqa: E402,F401  (autouse fixture)


@pytest.fixture
def swarm_name(request):
    return "f" + str(os.getpid()) + str(abs(hash(request.node.name)) % 10**6)


def test_router_killed_and_restarted_clients_reconnect_and_gossip_resumes(swarm_name):
    """3 client vehicles gossip every 0.2 s through a router process; the router is SIGKILLed
    after step 3 and restarted on the same port 1 s later. The vehicles never stop stepping
    (no wait beyond the 1 s deadline), lose each other while it is down, reconnect on their
    own and hear all neighbours again."""
    res = zf.router_restart(swarm_name, n=3, period_s=0.2, deadline_s=1.0, down_s=1.0,
                            reconnect_timeout_s=15.0, timeout_s=60.0)
    print("\nrouter restart:", json.dumps(res))
    for v in res["vehicles"]:
        others = [j for j in range(3) if j != v["id"]]
        assert v["membership_lost_after_kill_s"] is not None, v  # it noticed the router loss
        assert v["steps_while_router_down"] >= 1, v  # kept stepping
        assert all(v["id"] in p for p in v["present_while_down"]), v  # self stays present
        assert v["reconnect_s"] is not None, f"vehicle {v['id']} never heard all again: {v}"
        assert v["reconnect_s"] < 10.0, v
        assert v["last_step_neighbours"] == others, v
        assert v["max_wait_s"] < 1.0 + 0.8, v


def test_the_peer_the_others_connected_to_vanishes_and_the_others_go_on(swarm_name):
    """Peers 1-3 connect only to peer 0's endpoint; peer 0 is SIGKILLed after step 2. Gossip
    scouting has meshed the others directly: they keep hearing each other, without waiting a
    deadline for vehicle 0."""
    n, steps = 4, 10
    port = free_tcp_port()
    procs: list[Proc] = []
    try:
        for i in range(n):
            procs.append(zf.TimedProc(vehicle_argv(
                swarm_name, i, n, x=float(i), steps=steps, range_m=100.0, step_timeout_s=3.0,
                step_period_s=0.25, listen=[ep(port)] if i == 0 else [],
                connect=[ep(port)] if i else []), f"veh{i}"))
        for pr in procs:
            pr.wait_event("step", 60, lambda ev: ev["step"] >= 2)
        procs[0].p.kill()
        procs[0].p.wait(timeout=5)
        t_kill = time.monotonic()
        for i in range(1, n):
            procs[i].wait_event("done", 60)
            after = [ev for t, ev in procs[i].step_events() if t > t_kill + 0.5]
            assert after, procs[i].step_events()
            assert all(ev["neighbours"] == [j for j in range(1, n) if j != i] for ev in after), after
            assert after[-1]["lost"] == [0]
            assert all(ev["wait_s"] < 2.0 for _, ev in procs[i].step_events())
    finally:
        stop_all(procs)


def test_restarted_vehicle_gets_the_t0_states_from_the_swarm(swarm_name):
    """3 vehicles do the t = 0 exchange and gossip; vehicle 2 is killed after step 3 and a new
    vehicle-2 process joins later (a late joiner): its initial_exchange completes at once from
    the others' init queryables, with their original t = 0 states; the others see it back."""
    n = 3
    port = free_tcp_port()
    procs: list[Proc] = []
    try:
        for i in range(n):
            procs.append(zf.TimedProc(vehicle_argv(
                swarm_name, i, n, x=10.0 * i, steps=40, range_m=100.0, step_timeout_s=1.0,
                step_period_s=0.2, listen=[ep(port)] if i == 0 else [],
                connect=[ep(port)] if i else []), f"veh{i}"))
        for pr in procs:
            pr.wait_event("step", 60, lambda ev: ev["step"] >= 3)
        procs[2].p.kill()
        procs[2].p.wait(timeout=5)
        late = zf.TimedProc(vehicle_argv(swarm_name, 2, n, x=99.0, steps=0, init_timeout_s=10.0,
                                         connect=[ep(port)]), "veh2-late")
        procs.append(late)
        _, init, _ = late.wait_event("init", 30)
        print(f"\nlate joiner: t = 0 exchange took {init['elapsed_s']:.3f} s")
        assert {k: v[0] for k, v in init["states"].items()} == {"0": 0.0, "1": 10.0, "2": 99.0}
        assert init["received"] == 2
        assert init["elapsed_s"] < 5.0
        for i in range(2):  # the others see vehicle 2 leave and come back
            _, ev, _ = procs[i].wait_event("step", 30, lambda ev: ev["present"] == [0, 1, 2]
                                           and ev["lost"] == [])
            assert ev["present"] == [0, 1, 2]
    finally:
        stop_all(procs)


def test_late_joiner_after_the_others_finished_times_out_naming_them(swarm_name):
    """Vehicles 0 and 1 fly and exit (sessions closed); a vehicle 1 restarted afterwards cannot
    get vehicle 0's t = 0 state from anyone: its exchange times out naming vehicle 0."""
    port = free_tcp_port()
    procs: list[Proc] = []
    try:
        first = [zf.TimedProc(vehicle_argv(swarm_name, i, 2, x=float(i), steps=2,
                                           listen=[ep(port)] if i == 0 else [],
                                           connect=[] if i == 0 else [ep(port)]), f"veh{i}")
                 for i in range(2)]
        procs += first
        for pr in first:
            pr.wait_event("done", 60)
        stop_all(first)
        assert all(pr.p.returncode == 0 for pr in first)
        late = Proc(vehicle_argv(swarm_name, 1, 2, init_timeout_s=2.0, listen=[ep(port)]),
                    "veh1-late")
        procs.append(late)
        deadline = time.monotonic() + 30
        while True:
            ev = json.loads(late.next_line(max(0.1, deadline - time.monotonic())))
            if ev["event"] != "open":
                break
        assert ev["event"] == "error" and ev["kind"] == "timeout", ev
        assert ev["missing"] == [0] and "not present: [0]" in ev["message"]
    finally:
        stop_all(procs)


def test_lossy_link_gossip_goes_on_with_what_arrives():
    """4 vehicles, 2 of them across a link losing 10 % of packets each way (tc netem on a
    veth between two namespaces; where the kernel has no netem, zenoh udp/ links through a
    relay dropping 10 % of datagrams once the t = 0 exchange is done): the t = 0 exchange
    completes, every gossip step returns within the deadline plus a margin, and the vehicles
    still hear neighbours, fewer than on the lossless run."""
    reason = zf.netns_unavailable()
    runs = {}
    for loss in (0.0, 10.0):
        if reason:
            runs[loss] = zf.lossy_udp(f"fu{os.getpid()}l{int(loss)}", loss, steps=25,
                                      period_s=0.1, deadline_s=0.3, seed=1, timeout_s=60.0,
                                      lossy_from="gossip")
        else:
            runs[loss] = zf.lossy_link(f"fl{os.getpid()}l{int(loss)}", loss, tag=7, steps=25,
                                       period_s=0.1, deadline_s=0.3, timeout_s=60.0)
        print(f"\nloss {loss} %:", json.dumps(runs[loss]))
    for res in runs.values():
        assert res["init_received"] == [3, 3, 3, 3]
        assert res["max_wait_s"] < 0.3 + 0.5
    assert runs[0.0]["mean_heard"] == 3.0
    assert 0.0 < runs[10.0]["mean_heard"] < 3.0
    out = zf.subprocess.run(["ip", "netns", "list"], capture_output=True, text=True).stdout
    assert f"zfa{os.getpid() % 100000}t7" not in out
