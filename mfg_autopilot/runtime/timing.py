"""Where a control step's time goes, and how the process is scheduled: GC pauses, per-phase wall and
CPU timings for the step record (docs/controller_log.md), SCHED_FIFO for the whole process."""

from __future__ import annotations

import gc
import logging
import os
import time

from mavlink_bridge import VehicleLink
from mfg_autopilot.runtime.config import check_rt_priority

__all__ = ["GcClock", "PhaseClock", "START_MARGIN_S", "START_MAX_WAIT_S", "agreed_start_unix_s", "set_realtime_priority"]

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


# the real-time mission clock's start (agreed_start_unix_s): after the last vehicle published its t = 0 state, every
# vehicle still takes off into OFFBOARD (~1.3 s: a second of setpoint stream, arming, the mode's acknowledgement)
START_MARGIN_S = 2.5
START_MAX_WAIT_S = 30.0     # a start further ahead than this is a wrong clock, not a slow swarm


def agreed_start_unix_s(published_unix_s, now_unix_s: float, margin_s: float = START_MARGIN_S,
                        max_wait_s: float = START_MAX_WAIT_S) -> tuple[float, str | None]:
    """The real-time mission start every vehicle computes alike from the t = 0 exchange: the latest Unix time at
    which a vehicle published its t = 0 state (``StateMsg.time_s`` at step 0; 0 or less: a sender that says nothing,
    lockstep or an older one) plus ``margin_s``. Step k of every controller then falls at start + k dt on the same
    clock, so each vehicle's plan particle is where the others expect it: with a start of its own, a controller that
    starts 0.1 s before its neighbours sees them 0.1 s behind their particles (0.3-0.4 m in cruise) and its formation
    feedback brakes it (docs/proximity.md, "One mission clock for the swarm"). Across machines the wall clocks must agree
    (NTP/PTP), as for the traffic's timestamps.

    Returns (start, note): ``now_unix_s`` and a note saying why when no sender gave a time, or when the agreed start
    lies more than ``max_wait_s`` ahead of now (a clock that is off: the vehicle starts now on its own clock)."""
    stamps = [float(t) for t in published_unix_s if t > 0.0]        # StateMsg refuses a non-finite time
    if not stamps:
        return float(now_unix_s), "no vehicle published its t = 0 time: this controller starts its own mission clock"
    start = max(stamps) + float(margin_s)
    if start - now_unix_s > max_wait_s:
        return float(now_unix_s), (f"the agreed start lies {start - now_unix_s:.1f} s ahead (a vehicle's clock is off?): "
                                   f"this controller starts its own mission clock")
    return start, None
