"""Helpers for the Zenoh exchange tests: free ports, a vehicle process, process bookkeeping.

Run as a script, this file is one vehicle of a test swarm (a real process using
SwarmExchange)::

    python tests/_zenoh_helpers.py --swarm S --id 0 --n 5 --x 0 --y 0 --steps 3 \
        --range 1.5 --zenoh-listen tcp/127.0.0.1:PORT --zenoh-connect tcp/127.0.0.1:PORT0

It prints JSON lines on stdout (``init``, one ``step`` per gossip step, ``done`` or
``error``), then keeps its session open until stdin is closed (so that late joiners can
still query its t = 0 state), at most ``--linger-s`` seconds.
"""

from __future__ import annotations

import json
import os
import queue
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
HELPER = Path(__file__).resolve()


def free_tcp_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago, below the OS's ephemeral range (tests/_net.py
    free_ports: an ephemeral port can be handed out as another connection's source port before the listener binds)."""
    from _net import free_tcp_ports

    return free_tcp_ports(1)[0]


def ep(port: int, host: str = "127.0.0.1") -> str:
    return f"tcp/{host}:{port}"


class Proc:
    """A child process whose stdout lines are collected by a reader thread."""

    def __init__(self, argv: list[str], name: str, stdin_pipe: bool = True):
        env = dict(os.environ)
        env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
        env["PYTHONUNBUFFERED"] = "1"
        self.name = name
        self.argv = argv
        self.p = subprocess.Popen(argv, cwd=REPO, env=env, text=True,
                                  stdin=subprocess.PIPE if stdin_pipe else subprocess.DEVNULL,
                                  stdout=subprocess.PIPE, stderr=subprocess.PIPE)
        self.lines: queue.Queue[str] = queue.Queue()
        self.all_lines: list[str] = []
        self.stderr_lines: list[str] = []
        threading.Thread(target=self._read, args=(self.p.stdout, True), daemon=True).start()
        threading.Thread(target=self._read, args=(self.p.stderr, False), daemon=True).start()

    def _read(self, f, is_stdout: bool) -> None:
        for line in f:
            if is_stdout:
                self.lines.put(line.rstrip("\n"))
            else:
                self.stderr_lines.append(line.rstrip("\n"))

    def next_line(self, timeout_s: float) -> str:
        try:
            line = self.lines.get(timeout=timeout_s)
        except queue.Empty:
            raise TimeoutError(f"{self.name}: no output line within {timeout_s} s; rc={self.p.poll()}; "
                               f"stdout lines read so far (tail):\n" + "\n".join(self.all_lines[-15:])
                               + "\nstderr tail:\n" + "\n".join(self.stderr_lines[-15:]))
        self.all_lines.append(line)
        return line

    def next_event(self, timeout_s: float, event: str | None = None) -> dict:
        """Next JSON line (skipping non-JSON ones), optionally the next of a given event."""
        deadline = time.monotonic() + timeout_s
        while True:
            line = self.next_line(max(0.01, deadline - time.monotonic()))
            try:
                ev = json.loads(line)
            except ValueError:
                continue
            if ev.get("event") == "error":
                raise AssertionError(f"{self.name} failed: {ev}")
            if event is None or ev.get("event") == event:
                return ev

    def release(self) -> None:
        """Close stdin: a vehicle process then closes its session and exits."""
        try:
            if self.p.stdin:
                self.p.stdin.close()
        except OSError:
            pass

    def kill(self) -> None:
        if self.p.poll() is None:
            self.p.kill()
        try:
            self.p.wait(timeout=5)
        except subprocess.TimeoutExpired:
            pass


def vehicle_argv(swarm: str, vid: int, n: int, *, x: float = 0.0, y: float = 0.0,
                 steps: int = 0, range_m: float = 1e9, step_timeout_s: float = 2.0,
                 init_timeout_s: float = 20.0, step_period_s: float = 0.0,
                 listen: list[str] = (), connect: list[str] = (), mode: str = "peer",
                 netns: str | None = None) -> list[str]:
    argv = [sys.executable, str(HELPER), "--swarm", swarm, "--id", str(vid), "--n", str(n),
            "--x", str(x), "--y", str(y), "--steps", str(steps), "--range", str(range_m),
            "--step-timeout", str(step_timeout_s), "--init-timeout", str(init_timeout_s),
            "--step-period", str(step_period_s), "--zenoh-mode", mode]
    for e in listen:
        argv += ["--zenoh-listen", e]
    for e in connect:
        argv += ["--zenoh-connect", e]
    if netns:
        argv = ["ip", "netns", "exec", netns] + argv
    return argv


def router_argv(listen: list[str], netns: str | None = None) -> list[str]:
    argv = [sys.executable, "-m", "mfg_autopilot.runtime.router"]
    for e in listen:
        argv += ["--zenoh-listen", e]
    if netns:
        argv = ["ip", "netns", "exec", netns] + argv
    return argv


def stop_all(procs: list[Proc], grace_s: float = 3.0) -> None:
    """Release every process, give it ``grace_s`` to exit, then kill what is left."""
    for pr in procs:
        pr.release()
        if pr.p.poll() is None and "zenoh_router" in " ".join(pr.argv):
            pr.p.send_signal(signal.SIGTERM)
    deadline = time.monotonic() + grace_s
    for pr in procs:
        try:
            pr.p.wait(timeout=max(0.01, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            pass
    for pr in procs:
        pr.kill()


# --------------------------------------------------------------------------------------
# The vehicle process
# --------------------------------------------------------------------------------------
def _vehicle_main(argv: list[str] | None = None) -> int:
    import argparse
    import logging

    from mfg_autopilot.runtime.exchange import ExchangeTimeout, SwarmExchange, ZenohSettings

    ap = argparse.ArgumentParser()
    ap.add_argument("--swarm", required=True)
    ap.add_argument("--id", type=int, required=True)
    ap.add_argument("--n", type=int, required=True)
    ap.add_argument("--x", type=float, default=0.0)
    ap.add_argument("--y", type=float, default=0.0)
    ap.add_argument("--steps", type=int, default=0)
    ap.add_argument("--range", type=float, default=1e9)
    ap.add_argument("--step-timeout", type=float, default=2.0)
    ap.add_argument("--init-timeout", type=float, default=20.0)
    ap.add_argument("--step-period", type=float, default=0.0)
    ap.add_argument("--linger-s", type=float, default=60.0)
    ZenohSettings.add_cli_args(ap)
    ns = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, stream=sys.stderr,
                        format=f"[veh {ns.id}] %(levelname)s %(message)s")
    settings = ZenohSettings.from_args(ns)

    def out(**kw) -> None:
        print(json.dumps(kw), flush=True)

    state = [ns.x, ns.y, 0.0, 0.0]
    with SwarmExchange(settings, ns.swarm, ns.id, ns.n) as ex:
        out(event="open")
        t0 = time.monotonic()
        try:
            init = ex.initial_exchange(state, timeout_s=ns.init_timeout)
        except ExchangeTimeout as e:
            out(event="error", kind="timeout", missing=list(e.missing), message=str(e))
            return 3
        out(event="init", elapsed_s=time.monotonic() - t0,
            states={str(k): list(v.state) for k, v in init.items()},
            received=ex.states_received_by_step.get(0, 0))
        for step in range(1, ns.steps + 1):
            if ns.step_period > 0:
                time.sleep(ns.step_period)
            t1 = time.monotonic()
            got = ex.gossip(step, float(step), state, ns.range, ns.step_timeout)
            out(event="step", step=step, neighbours=[m.vehicle_id for m in got],
                present=sorted(ex.present()), lost=sorted(ex.lost()),
                wait_s=time.monotonic() - t1)
        out(event="done", received_by_step={str(k): v for k, v in ex.states_received_by_step.items()},
            received_total=ex.states_received_total)
        # keep answering t = 0 queries until released (stdin closed) or linger_s passes
        done = threading.Event()
        threading.Thread(target=lambda: (sys.stdin.read(), done.set()), daemon=True).start()
        done.wait(ns.linger_s)
    return 0


if __name__ == "__main__":
    raise SystemExit(_vehicle_main())


import psutil  # noqa: E402
import pytest  # noqa: E402


@pytest.fixture(autouse=True)
def no_process_left_behind():
    """Autouse in the Zenoh test modules that import it: fail a test that leaves a child process."""
    yield
    me = psutil.Process()
    deadline = time.monotonic() + 5
    while me.children(recursive=True) and time.monotonic() < deadline:
        time.sleep(0.05)
    left = me.children(recursive=True)
    for c in left:
        c.kill()
    assert not left, f"processes left behind: {[c.cmdline() for c in left]}"
