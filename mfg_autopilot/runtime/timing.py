"""Where a control step's time goes, and how the process is scheduled: GC pauses, per-phase wall and
CPU timings for the step record (docs/controller_log.md), SCHED_FIFO for the whole process."""

from __future__ import annotations

import gc
import logging
import os
import time

from mavlink_bridge import VehicleLink
from mfg_autopilot.runtime.config import check_rt_priority

__all__ = ["GcClock", "PhaseClock", "set_realtime_priority"]

log = logging.getLogger("mfg_autopilot")


class GcClock:
    """Wall time the cyclic garbage collector paused this process (``gc.callbacks``; any
    thread's collections): ``total_s`` and ``collections`` since install."""

    def __init__(self) -> None:
        self.total_s = 0.0
        self.collections = 0
        self._t: float | None = None

    def __call__(self, phase: str, info: dict) -> None:
        if phase == "start":
            self._t = time.perf_counter()
        elif self._t is not None:
            self.total_s += time.perf_counter() - self._t
            self.collections += 1
            self._t = None

    def install(self) -> "GcClock":
        gc.callbacks.append(self)
        return self

    def remove(self) -> None:
        if self in gc.callbacks:
            gc.callbacks.remove(self)


class PhaseClock:
    """Per-step phase timings for the step record's ``timing`` (docs/controller_log.md): wall
    (perf_counter) and this thread's CPU (thread_time) at each mark, the MAVLink receive
    thread's CPU and the GC pause time since the previous step record."""

    def __init__(self, link: VehicleLink, gc_clock: GcClock | None) -> None:
        self.link, self.gc_clock = link, gc_clock
        self._rx_cpu_s = getattr(link, "rx_cpu_s", 0.0)
        self._gc_s = gc_clock.total_s if gc_clock is not None else 0.0
        self._gc_n = gc_clock.collections if gc_clock is not None else 0
        self.wall: list[float] = []
        self.cpu: list[float] = []

    def start(self) -> None:
        self.wall = [time.perf_counter()]
        self.cpu = [time.thread_time()]

    def mark(self) -> None:
        self.wall.append(time.perf_counter())
        self.cpu.append(time.thread_time())

    def phases(self, names: tuple[str, ...], first: int = 0) -> dict:
        """{name_ms, name_cpu_ms} of the phases between consecutive marks from mark ``first`` on."""
        out = {}
        for i, name in enumerate(names, start=first):
            out[f"{name}_ms"] = round((self.wall[i + 1] - self.wall[i]) * 1e3, 4)
            out[f"{name}_cpu_ms"] = round((self.cpu[i + 1] - self.cpu[i]) * 1e3, 4)
        return out

    def record(self, names: tuple[str, ...]) -> dict:
        """``phases(names)`` plus rx_cpu_ms, gc_ms, gc_collections since the previous record."""
        out = self.phases(names)
        out["process_cpu_s"] = round(time.process_time(), 6)
        rx = getattr(self.link, "rx_cpu_s", 0.0)
        out["rx_cpu_ms"] = round((rx - self._rx_cpu_s) * 1e3, 4)
        self._rx_cpu_s = rx
        if self.gc_clock is not None:
            g, n = self.gc_clock.total_s, self.gc_clock.collections
            out["gc_ms"] = round((g - self._gc_s) * 1e3, 4)
            out["gc_collections"] = n - self._gc_n
            self._gc_s, self._gc_n = g, n
        return out


def set_realtime_priority(priority: int, clog=None) -> bool:
    """Put every thread of this process (the control loop, the MAVLink receive and setpoint
    threads, Zenoh's) under SCHED_FIFO at `priority` (1-99), as a flight computer runs its
    controller (PX4 runs its modules at SCHED_FIFO priorities): the control step is then not
    preempted by normal-priority processes (the mocks, loggers) between telemetry and setpoint.
    Needs CAP_SYS_NICE or an RLIMIT_RTPRIO >= priority; refused -> a log line and normal
    scheduling (returns False). Every thread sleeps on a socket or a timer between steps, so
    the kernel's real-time throttling is never reached."""
    check_rt_priority(priority)
    if not hasattr(os, "sched_setscheduler"):
        log.warning("--rt-priority %d: this platform has no sched_setscheduler; normal scheduling", priority)
        return False
    param = os.sched_param(int(priority))
    tids = [int(t) for t in os.listdir("/proc/self/task")] if os.path.isdir("/proc/self/task") else [0]
    done, refused = 0, None
    for tid in tids:
        try:
            os.sched_setscheduler(tid, os.SCHED_FIFO, param)
            done += 1
        except ProcessLookupError:                 # a thread that ended meanwhile
            continue
        except PermissionError as exc:
            refused = exc
            break
    if refused is not None:
        log.warning("--rt-priority %d refused (%s: needs CAP_SYS_NICE or an rtprio limit); normal scheduling", priority, refused)
        if clog is not None:
            clog.event("rt_priority", priority=int(priority), applied=False, error=str(refused))
        return False
    if clog is not None:
        clog.event("rt_priority", priority=int(priority), applied=True, threads=done)
    return True
