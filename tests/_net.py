"""Shared helpers for end-to-end tests: free loopback UDP ports, spawning real processes
with their stderr in a file, killing them (whole process group) in ``finally``, and
waiting with a timeout. Nothing here imports project packages."""

from __future__ import annotations

import contextlib
import os
import random
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Callable, Iterator, Sequence

__all__ = ["free_udp_port", "free_udp_ports", "free_tcp_ports", "free_ports", "Proc", "spawn", "wait_until", "mock_vehicle_cmd", "running_mock_vehicle", "MockVehicleProc", "PYTHON", "VENV_BIN"]

PYTHON = sys.executable
VENV_BIN = Path(sys.executable).parent
REPO = Path(__file__).resolve().parent.parent
LOG_ROOT: Path | None = None
"""Where ``spawn`` puts the log folder of a test that gives none: tests/conftest.py sets it to a folder of pytest's
own temporary tree (which pytest prunes, keeping the last runs); None (a helper run outside pytest): the system's."""


# Ports for the test's processes are chosen below Linux's ephemeral range (32768-60999), as mfg_swarm.launcher does:
# a port the OS picked with bind(0) and then released can be handed out again as the source port of another socket (a
# mock vehicle's udpout, a Zenoh connection) before the process under test binds it (seen once in CI: "[Errno 98]
# Address already in use" for a controller's udpin). Ports outside that range are never handed out implicitly.
_PORT_LO, _PORT_HI = 20000, 32000
_port_rng = random.Random(os.getpid() ^ time.time_ns())


def free_udp_port() -> int:
    """A UDP port on 127.0.0.1, free a moment ago and outside the OS's ephemeral range."""
    return free_ports(1, socket.SOCK_DGRAM)[0]


def free_udp_ports(n: int) -> list[int]:
    """``n`` distinct UDP ports on 127.0.0.1 (``free_ports``)."""
    return free_ports(n, socket.SOCK_DGRAM)


def free_tcp_ports(n: int) -> list[int]:
    """``n`` distinct TCP ports on 127.0.0.1 (``free_ports``)."""
    return free_ports(n, socket.SOCK_STREAM)


def free_ports(n: int, kind: int) -> list[int]:
    """``n`` distinct ports of socket type ``kind`` on 127.0.0.1, free at once (held open together while picking),
    below the ephemeral range."""
    for _ in range(500):
        socks = []
        try:
            for p in _port_rng.sample(range(_PORT_LO, _PORT_HI), n):
                s = socket.socket(socket.AF_INET, kind)
                socks.append(s)
                s.bind(("127.0.0.1", p))
            return [s.getsockname()[1] for s in socks]
        except OSError:
            continue
        finally:
            for s in socks:
                s.close()
    raise RuntimeError(f"no {n} free loopback ports in {_PORT_LO}..{_PORT_HI}")


def wait_until(predicate: Callable[[], object], timeout_s: float, what: str, poll_s: float = 0.05):
    """Poll ``predicate`` until it returns something truthy; raise TimeoutError naming ``what``."""
    deadline = time.monotonic() + timeout_s
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() > deadline:
            raise TimeoutError(f"timed out after {timeout_s} s waiting for {what}")
        time.sleep(poll_s)


class Proc:
    """A spawned process in its own session; stdout+stderr go to ``log_path``."""

    def __init__(self, argv: Sequence[str], log_path: Path, env: dict | None = None, cwd: Path | None = None) -> None:
        self.argv = list(argv)
        self.log_path = log_path
        self._log_file = open(log_path, "wb")
        self.popen = subprocess.Popen(
            self.argv,
            stdout=self._log_file,
            stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL,
            env=env,
            cwd=str(cwd or REPO),
            start_new_session=True,
        )

    @property
    def pid(self) -> int:
        return self.popen.pid

    def alive(self) -> bool:
        return self.popen.poll() is None

    def log_text(self) -> str:
        if not self._log_file.closed:
            self._log_file.flush()
        return self.log_path.read_text(errors="replace")

    def wait_log(self, needle: str, timeout_s: float) -> str:
        """Wait until ``needle`` appears in the process's output."""
        return wait_until(lambda: needle in self.log_text() and self.log_text(), timeout_s, f"{needle!r} in {self.log_path}")

    def send_signal(self, signum: int) -> None:
        if self.alive():
            self.popen.send_signal(signum)

    def stop(self, signum: int = signal.SIGTERM, timeout_s: float = 5.0) -> int:
        """Send ``signum``, wait up to ``timeout_s``, then SIGKILL the process group."""
        try:
            if self.alive():
                self.popen.send_signal(signum)
                try:
                    return self.popen.wait(timeout=timeout_s)
                except subprocess.TimeoutExpired:
                    pass
            return self.popen.wait(timeout=0.1)
        except subprocess.TimeoutExpired:
            return self.kill()
        finally:
            self._kill_group()
            self._log_file.close()

    def kill(self) -> int:
        self._kill_group()
        try:
            return self.popen.wait(timeout=5.0)
        except subprocess.TimeoutExpired:  # pragma: no cover - should not happen after SIGKILL
            return -9

    def _kill_group(self) -> None:
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.killpg(self.popen.pid, signal.SIGKILL)


@contextlib.contextmanager
def spawn(argv: Sequence[str], log_dir: Path | None = None, name: str = "proc", env: dict | None = None,
          stop_signal: int = signal.SIGTERM, stop_timeout_s: float = 5.0) -> Iterator[Proc]:
    """Run ``argv`` for the duration of the ``with`` block; always stopped (then killed) on exit."""
    log_dir = Path(log_dir or tempfile.mkdtemp(prefix="e2e-", dir=LOG_ROOT))
    log_dir.mkdir(parents=True, exist_ok=True)
    proc = Proc(argv, log_dir / f"{name}-{time.monotonic_ns()}.log", env=env)
    try:
        yield proc
    finally:
        proc.stop(stop_signal, stop_timeout_s)


def mock_vehicle_cmd(onboard_port: int, *extra: str, instance: int = 0, gcs: str = "none") -> list[str]:
    """Command line of a mock vehicle sending its onboard link to 127.0.0.1:``onboard_port``."""
    return [
        PYTHON, "-m", "mock_vehicle.cli",
        "--instance", str(instance),
        "--onboard-url", f"udpout:127.0.0.1:{onboard_port}",
        "--gcs-url", gcs,
        *extra,
    ]  # fmt: skip


class MockVehicleProc:
    """A running ``mock-vehicle``: its process, the UDP ports it sends its onboard and GCS
    links to (``udpin:127.0.0.1:<port>`` there to talk to it), and its log."""

    def __init__(self, proc: Proc, onboard_port: int, gcs_port: int | None) -> None:
        self.proc = proc
        self.onboard_port = onboard_port
        self.gcs_port = gcs_port

    @property
    def onboard_url(self) -> str:
        return f"udpin:127.0.0.1:{self.onboard_port}"

    @property
    def gcs_url(self) -> str:
        return f"udpin:127.0.0.1:{self.gcs_port}"

    def log_text(self) -> str:
        return self.proc.log_text()


@contextlib.contextmanager
def running_mock_vehicle(*extra: str, instance: int = 0, gcs: bool = False, log_dir: Path | None = None,
                         stop_signal: int = signal.SIGTERM) -> Iterator[MockVehicleProc]:
    """Start a mock vehicle on free loopback ports for the ``with`` block; always stopped."""
    ports = free_udp_ports(2)
    gcs_port = ports[1] if gcs else None
    argv = mock_vehicle_cmd(ports[0], *extra, instance=instance, gcs="none" if gcs_port is None else f"udpout:127.0.0.1:{gcs_port}")
    with spawn(argv, log_dir=log_dir, name=f"mock{instance}", stop_signal=stop_signal) as proc:
        yield MockVehicleProc(proc, ports[0], gcs_port)
