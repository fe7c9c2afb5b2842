"""Zenoh faults with real processes: router restart (client mode) and lossy links (tc netem).

    .venv/bin/python bench/zenoh_faults.py [--loss 0,10,20,30] [--steps 60] [--repeats 3]
                                           [--restarts 3] [--json OUT]

Needs root and iproute2 (`ip netns`, `tc` with netem) for the loss sweep; the router restart
runs on loopback. Every vehicle is tests/_zenoh_helpers.py run as a script (a real process with
a SwarmExchange); tests/test_zenoh_faults.py runs short versions of the same scenarios.

Router restart: a router process and N vehicles in client mode gossip (lockstep, one step per
``period_s``); the router is SIGKILLed after step 3 and restarted on the same port after
``down_s``. Reported: per vehicle, the time from the restarted router printing "ready" to the
first step at which the vehicle hears all its neighbours again (reconnect_s), and the steps
run with no neighbour while the router was down.

Loss sweep (netem): host A (netns) runs a router and vehicles 0-1 as clients, host B (netns, joined by
a veth /30) runs vehicles 2-3 as peers connecting to the router; ``tc qdisc ... netem loss X%``
on both veth ends. Every vehicle is in range of every other (3 neighbours). Reported: mean
neighbours heard per step (of 3), the share of steps where all 3 were heard, the share of
steps that waited the deadline, and the mean/max gossip wait.

Loss sweep without netem (kernels without sch_netem, e.g. this project's CI VM): the same
4 vehicles, 0-1 over TCP to a router on loopback, 2-3 over zenoh ``udp/`` links through
:class:`LossyUdpRelay`, which drops X % of datagrams each way (used automatically when the
netem probe fails).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import shutil
import signal
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Iterator

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))
from _zenoh_helpers import Proc, ep, free_tcp_port, router_argv, stop_all, vehicle_argv  # noqa: E402


class TimedProc(Proc):
    """A Proc that records the arrival time (monotonic) of each JSON event line."""

    def __init__(self, *a, **kw):
        self.events: list[tuple[float, dict]] = []
        super().__init__(*a, **kw)

    def _read(self, f, is_stdout: bool) -> None:
        for line in f:
            line = line.rstrip("\n")
            if is_stdout:
                try:
                    ev = json.loads(line)
                    if isinstance(ev, dict):
                        self.events.append((time.monotonic(), ev))
                except ValueError:
                    pass
                self.lines.put(line)
            else:
                self.stderr_lines.append(line)

    def wait_event(self, event: str, timeout_s: float, pred=lambda ev: True, start: int = 0):
        """Wait for an event (recorded at index >= start) matching ``pred``; (t, ev, index)."""
        deadline = time.monotonic() + timeout_s
        while True:
            for i in range(start, len(self.events)):
                t, ev = self.events[i]
                if ev.get("event") == "error":
                    raise RuntimeError(f"{self.name} failed: {ev}")
                if ev.get("event") == event and pred(ev):
                    return t, ev, i
            if time.monotonic() > deadline:
                raise TimeoutError(f"{self.name}: no {event!r} event within {timeout_s} s; "
                                   f"rc={self.p.poll()} stderr tail:\n" + "\n".join(self.stderr_lines[-10:]))
            time.sleep(0.01)

    def step_events(self) -> list[tuple[float, dict]]:
        return [(t, ev) for t, ev in self.events if ev.get("event") == "step"]


def _sh(*argv: str) -> None:
    subprocess.run(argv, check=True, capture_output=True, timeout=10)


def netns_unavailable() -> str | None:
    """Why network namespaces with netem cannot be used here, or None."""
    for tool in ("ip", "tc"):
        if shutil.which(tool) is None:
            return f"iproute2 `{tool}` not installed"
    if os.geteuid() != 0:
        return "needs root to create network namespaces"
    probe = f"zfprobe{os.getpid()}"
    try:
        _sh("ip", "netns", "add", probe)
        _sh("ip", "-n", probe, "link", "set", "lo", "up")
        _sh("ip", "netns", "exec", probe, "tc", "qdisc", "add", "dev", "lo", "root", "netem", "loss", "1%")
    except (subprocess.CalledProcessError, OSError) as e:
        return f"netns/netem probe failed: {getattr(e, 'stderr', e)!r}"
    finally:
        subprocess.run(["ip", "netns", "del", probe], capture_output=True, timeout=10)
    return None


@contextlib.contextmanager
def two_hosts(tag: int) -> Iterator[dict]:
    """Two network namespaces joined by a veth pair on 10.202.K.0/30; deleted on exit."""
    pid = os.getpid() % 100000
    k = (os.getpid() + tag) % 250 + 1
    h = {"ns_a": f"zfa{pid}t{tag}", "ns_b": f"zfb{pid}t{tag}",
         "veth_a": f"zfa{pid}{tag}"[:15], "veth_b": f"zfb{pid}{tag}"[:15],
         "ip_a": f"10.202.{k}.1", "ip_b": f"10.202.{k}.2"}
    try:
        _sh("ip", "netns", "add", h["ns_a"])
        _sh("ip", "netns", "add", h["ns_b"])
        _sh("ip", "link", "add", h["veth_a"], "type", "veth", "peer", "name", h["veth_b"])
        _sh("ip", "link", "set", h["veth_a"], "netns", h["ns_a"])
        _sh("ip", "link", "set", h["veth_b"], "netns", h["ns_b"])
        for ns, dev, addr in ((h["ns_a"], h["veth_a"], h["ip_a"]), (h["ns_b"], h["veth_b"], h["ip_b"])):
            _sh("ip", "-n", ns, "addr", "add", f"{addr}/30", "dev", dev)
            _sh("ip", "-n", ns, "link", "set", dev, "up")
            _sh("ip", "-n", ns, "link", "set", "lo", "up")
        yield h
    finally:
        for ns in (h["ns_a"], h["ns_b"]):  # deleting a namespace deletes its end of the veth
            subprocess.run(["ip", "netns", "del", ns], capture_output=True, timeout=10)
        subprocess.run(["ip", "link", "del", h["veth_a"]], capture_output=True, timeout=10)


def set_loss(h: dict, loss_pct: float) -> None:
    """netem loss on both ends of the veth pair (each direction loses loss_pct %)."""
    for ns, dev in ((h["ns_a"], h["veth_a"]), (h["ns_b"], h["veth_b"])):
        _sh("ip", "netns", "exec", ns, "tc", "qdisc", "replace", "dev", dev, "root",
            "netem", "loss", f"{loss_pct}%")


class LossyUdpRelay:
    """A UDP relay on 127.0.0.1 that drops each datagram with probability ``loss`` in both
    directions (seeded). The stand-in for ``tc netem loss`` where the kernel has no netem:
    zenoh sessions over ``udp/`` endpoints (unreliable links: a dropped datagram is a lost
    message, no retransmission) connect to ``port`` and reach ``upstream_port``."""

    def __init__(self, upstream_port: int, loss: float, seed: int = 0):
        import random
        import selectors
        import socket
        import threading

        self._socket, self._selectors = socket, selectors
        self.upstream = ("127.0.0.1", upstream_port)
        self.loss = float(loss)
        self.rng = random.Random(seed)
        self.front = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.front.bind(("127.0.0.1", 0))
        self.port = self.front.getsockname()[1]
        self.sel = selectors.DefaultSelector()
        self.sel.register(self.front, selectors.EVENT_READ, None)
        self.back: dict[tuple, object] = {}  # client address -> socket towards upstream
        self.forwarded = 0
        self.dropped = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            for key, _ in self.sel.select(timeout=0.1):
                sock, client = key.fileobj, key.data
                try:
                    data, addr = sock.recvfrom(65536)
                except OSError:
                    continue
                if client is None:  # client -> upstream
                    up = self.back.get(addr)
                    if up is None:
                        up = self._socket.socket(self._socket.AF_INET, self._socket.SOCK_DGRAM)
                        up.bind(("127.0.0.1", 0))
                        self.back[addr] = up
                        self.sel.register(up, self._selectors.EVENT_READ, addr)
                    dst, out = self.upstream, up
                else:  # upstream -> client
                    dst, out = client, self.front
                if self.rng.random() < self.loss:
                    self.dropped += 1
                    continue
                try:
                    out.sendto(data, dst)
                    self.forwarded += 1
                except OSError:
                    pass

    def close(self) -> None:
        self._stop.set()
        self._thread.join(5)
        for sock in [self.front, *self.back.values()]:
            sock.close()
        self.sel.close()


# --------------------------------------------------------------------------------------
# Scenarios
# --------------------------------------------------------------------------------------
def router_restart(swarm: str, n: int = 3, period_s: float = 0.2, deadline_s: float = 1.0,
                   down_s: float = 1.0, kill_after_step: int = 3, reconnect_timeout_s: float = 30.0,
                   timeout_s: float = 60.0) -> dict:
    """Kill the router mid-flight, restart it after ``down_s``; see the module docstring.
    The vehicles fly until every one hears all the others again after the restart (or
    ``reconnect_timeout_s`` passes), plus 1 s; then they are stopped."""
    port = free_tcp_port()
    procs: list[Proc] = []
    try:
        router = Proc(router_argv([ep(port)]), "router")
        procs.append(router)
        if router.next_line(20) != "ready":
            raise RuntimeError("router did not start")
        vehicles = []
        for i in range(n):
            vehicles.append(TimedProc(vehicle_argv(
                swarm, i, n, x=float(i), steps=100000, range_m=100.0, step_timeout_s=deadline_s,
                step_period_s=period_s, mode="client", connect=[ep(port)]), f"veh{i}"))
        procs += vehicles
        for v in vehicles:
            v.wait_event("step", timeout_s, lambda ev: ev["step"] >= kill_after_step)
        router.p.kill()
        router.p.wait(5)
        t_kill = time.monotonic()
        time.sleep(down_s)
        router2 = Proc(router_argv([ep(port)]), "router2")
        procs.append(router2)
        if router2.next_line(20) != "ready":
            raise RuntimeError("restarted router did not start: " + "\n".join(router2.stderr_lines))
        t_ready = time.monotonic()
        for i, v in enumerate(vehicles):
            others = [j for j in range(n) if j != i]
            try:
                v.wait_event("step", max(0.1, t_ready + reconnect_timeout_s - time.monotonic()),
                             lambda ev: ev["neighbours"] == others
                             and ev["step"] > kill_after_step + 1)
            except TimeoutError:
                pass
        time.sleep(1.0)
        out = {"n": n, "period_s": period_s, "deadline_s": deadline_s, "down_s": down_s,
               "router_down_s": t_ready - t_kill, "vehicles": []}
        for i, v in enumerate(vehicles):
            evs = v.step_events()
            others = [j for j in range(n) if j != i]
            t_lost = next((t for t, ev in evs if t > t_kill and not set(others) & set(ev["present"])),
                          None)
            gap = [ev for t, ev in evs if t_kill < t < t_ready]
            back = next(((t, ev) for t, ev in evs if t > t_ready and ev["neighbours"] == others), None)
            out["vehicles"].append({
                "id": i,
                "membership_lost_after_kill_s": None if t_lost is None else t_lost - t_kill,
                "reconnect_s": None if back is None else back[0] - t_ready,
                "first_full_step_after_restart": None if back is None else back[1]["step"],
                "steps_while_router_down": len(gap),
                "steps_without_neighbours": sum(1 for _, ev in evs if not ev["neighbours"]),
                "deadline_waits": sum(1 for _, ev in evs if ev["wait_s"] >= 0.9 * deadline_s),
                "max_wait_s": max(ev["wait_s"] for _, ev in evs),
                "present_while_down": sorted({tuple(ev["present"]) for ev in gap}),
                "last_step_neighbours": evs[-1][1]["neighbours"],
                "steps": evs[-1][1]["step"],
            })
        return out
    finally:
        stop_all(procs)


def lossy_link(swarm: str, loss_pct: float, tag: int = 0, steps: int = 30, period_s: float = 0.1,
               deadline_s: float = 0.3, timeout_s: float = 90.0) -> dict:
    """Two hosts through a router with netem loss on the veth; see the module docstring."""
    n, port = 4, 7447
    procs: list[Proc] = []
    with two_hosts(tag) as h:
        try:
            set_loss(h, loss_pct)
            router = Proc(router_argv([ep(port, h["ip_a"])], netns=h["ns_a"]), "router@A")
            procs.append(router)
            if router.next_line(20) != "ready":
                raise RuntimeError("router did not start")
            vehicles = []
            for i in range(n):
                on_a = i < 2
                vehicles.append(TimedProc(vehicle_argv(
                    swarm, i, n, x=float(i), steps=steps, range_m=100.0,
                    step_timeout_s=deadline_s, step_period_s=period_s, init_timeout_s=40.0,
                    mode="client" if on_a else "peer", connect=[ep(port, h["ip_a"])],
                    listen=[] if on_a else [ep(7448 + i, h["ip_b"])],
                    netns=h["ns_a"] if on_a else h["ns_b"]), f"veh{i}@{'A' if on_a else 'B'}"))
            procs += vehicles
            t0 = time.monotonic()
            inits = [v.wait_event("init", timeout_s)[1] for v in vehicles]
            t_init = time.monotonic() - t0
            for v in vehicles:
                v.wait_event("done", timeout_s)
            out = {"link": "netem", "loss_pct": loss_pct, "steps": steps, "period_s": period_s,
                   "deadline_s": deadline_s, "init_s": t_init}
            out.update(_loss_stats(vehicles, inits, deadline_s))
            return out
        finally:
            stop_all(procs)


def _free_udp_port() -> int:
    import socket
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sk:
        sk.bind(("127.0.0.1", 0))
        return sk.getsockname()[1]


def _loss_stats(vehicles: list[TimedProc], inits: list[dict], deadline_s: float) -> dict:
    n = len(vehicles)
    heard, waited, waits, per_vehicle, present = [], 0, [], [], []
    for v in vehicles:
        evs = [ev for _, ev in v.step_events()]
        per_vehicle.append(round(statistics.mean(len(ev["neighbours"]) for ev in evs), 3))
        for ev in evs:
            heard.append(len(ev["neighbours"]))
            present.append(len(ev["present"]) - 1)
            waits.append(ev["wait_s"])
            waited += ev["wait_s"] >= 0.9 * deadline_s
    return {"init_received": [ev["received"] for ev in inits],
            "mean_heard": statistics.mean(heard), "max_heard": n - 1,
            "mean_present_others": statistics.mean(present),
            "mean_heard_by_vehicle": per_vehicle,
            "full_share": sum(x == n - 1 for x in heard) / len(heard),
            "deadline_share": waited / len(heard),
            "mean_wait_s": statistics.mean(waits), "max_wait_s": max(waits)}


def lossy_udp(swarm: str, loss_pct: float, steps: int = 30, period_s: float = 0.1,
              deadline_s: float = 0.3, seed: int = 0, timeout_s: float = 90.0,
              lossy_from: str = "gossip") -> dict:
    """Loss without netem: a router listening on TCP and UDP (loopback); vehicles 0-1 connect
    over TCP (the router's own site), vehicles 2-3 over ``udp/`` through a
    :class:`LossyUdpRelay` dropping ``loss_pct`` % of datagrams each way (the lossy radio
    link). All 4 in range of each other.

    ``lossy_from="start"``: the link is lossy from the first datagram (session set-up,
    declarations, t = 0 exchange); ``"gossip"``: lossless until all 4 t = 0 exchanges are done,
    then lossy (zenoh does not retransmit over udp/ links: a lost liveliness-token declaration
    leaves that vehicle absent for good, see docs/zenoh.md "## Faults")."""
    if lossy_from not in ("start", "gossip"):
        raise ValueError(f"lossy_from must be start or gossip, got {lossy_from!r}")
    n = 4
    tcp_port, udp_port = free_tcp_port(), _free_udp_port()
    procs: list[Proc] = []
    relay = LossyUdpRelay(udp_port, loss_pct / 100.0 if lossy_from == "start" else 0.0, seed=seed)
    try:
        router = Proc(router_argv([ep(tcp_port), f"udp/127.0.0.1:{udp_port}"]), "router")
        procs.append(router)
        if router.next_line(20) != "ready":
            raise RuntimeError("router did not start")
        vehicles = []
        for i in range(n):
            connect = ep(tcp_port) if i < 2 else f"udp/127.0.0.1:{relay.port}"
            vehicles.append(TimedProc(vehicle_argv(
                swarm, i, n, x=float(i), steps=steps, range_m=100.0, step_timeout_s=deadline_s,
                step_period_s=period_s, init_timeout_s=40.0, mode="client", connect=[connect]),
                f"veh{i}"))
        procs += vehicles
        t0 = time.monotonic()
        inits = [v.wait_event("init", timeout_s)[1] for v in vehicles]
        t_init = time.monotonic() - t0
        relay.loss = loss_pct / 100.0
        for v in vehicles:
            v.wait_event("done", timeout_s)
        out = {"link": f"udp relay, lossy from {lossy_from}", "loss_pct": loss_pct, "steps": steps, "period_s": period_s,
               "deadline_s": deadline_s, "init_s": t_init,
               "relay_forwarded": relay.forwarded, "relay_dropped": relay.dropped}
        out.update(_loss_stats(vehicles, inits, deadline_s))
        return out
    finally:
        stop_all(procs)
        relay.close()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--loss", default="0,10,20,30", help="loss percentages (comma list)")
    ap.add_argument("--steps", type=int, default=60)
    ap.add_argument("--period", type=float, default=0.1, help="gossip step period (s)")
    ap.add_argument("--deadline", type=float, default=0.3, help="lockstep gossip deadline (s)")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--restarts", type=int, default=3, help="router restart runs")
    ap.add_argument("--lossy-from", choices=["start", "gossip"], default="gossip",
                    help="udp relay only: loss from session set-up on, or after the t = 0 exchange")
    ap.add_argument("--json", default=None, help="write all results here")
    ns = ap.parse_args(argv)
    results: dict = {"router_restart": [], "loss": []}
    tag = os.getpid()
    for r in range(ns.restarts):
        res = router_restart(f"zr{tag}x{r}")
        results["router_restart"].append(res)
        rec = [v["reconnect_s"] for v in res["vehicles"]]
        print(f"router restart {r}: router down {res['router_down_s']:.2f} s; reconnect "
              f"(restart -> all neighbours heard) per vehicle: "
              + ", ".join("never" if x is None else f"{x:.2f} s" for x in rec)
              + f"; steps without neighbours: {[v['steps_without_neighbours'] for v in res['vehicles']]}",
              flush=True)
    reason = netns_unavailable() if ns.loss else None
    if reason:
        print(f"netem unavailable ({reason}); loss sweep over zenoh udp/ links through a "
              f"lossy UDP relay instead")
    for loss in [float(x) for x in ns.loss.split(",") if x.strip()]:
        for r in range(ns.repeats):
            try:
                if reason:
                    res = lossy_udp(f"zl{tag}x{r}", loss, steps=ns.steps, period_s=ns.period,
                                    deadline_s=ns.deadline, seed=r, lossy_from=ns.lossy_from,
                                    timeout_s=60.0)
                else:
                    res = lossy_link(f"zl{tag}x{r}", loss, tag=r, steps=ns.steps,
                                     period_s=ns.period, deadline_s=ns.deadline)
            except (RuntimeError, TimeoutError) as e:
                results["loss"].append({"loss_pct": loss, "run": r, "failed": str(e)})
                print(f"loss {loss:4.0f} % run {r}: FAILED: {str(e).splitlines()[0]}", flush=True)
                continue
            results["loss"].append(res)
            print(f"loss {loss:4.0f} % run {r} ({res['link']}): heard {res['mean_heard']:.2f}/3 "
                  f"per step (by vehicle {res['mean_heard_by_vehicle']}; others present "
                  f"{res['mean_present_others']:.2f}), all 3 in "
                  f"{100 * res['full_share']:.0f} % of steps, deadline waits in "
                  f"{100 * res['deadline_share']:.0f} % of steps, wait mean "
                  f"{1000 * res['mean_wait_s']:.0f} ms max {1000 * res['max_wait_s']:.0f} ms, "
                  f"t=0 exchange {res['init_s']:.1f} s", flush=True)
    if ns.json:
        Path(ns.json).write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
