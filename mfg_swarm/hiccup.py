"""The host's share of a latency: how long a CPU of this machine stops running a thread.

A busy loop pinned to one CPU (at SCHED_FIFO where the OS allows it, so no process of ours
can preempt it; in half-second chunks, under the kernel's real-time throttling) reads the
clock; every gap between two readings longer than
``threshold_s`` is time the thread did not run: hypervisor steal, interrupts, kernel work
(what ``cyclictest`` and jHiccup measure). ``job_exceedance`` then answers the question a
latency target asks of the host alone: a job that needs ``job_s`` of CPU, started at a
random moment on that CPU, finishes after ``limit_s`` wall with what probability? If that
is above 1 % for the controller's telemetry-to-setpoint CPU time, no code change brings
that path's p99 under ``limit_s`` on this machine.

    python -m mfg_swarm.hiccup --cpu 1 --duration-s 10      # prints JSON
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

import numpy as np

__all__ = ["record_gaps", "job_exceedance", "gap_summary", "measure"]

JOB_GRID_S = tuple(x * 1e-3 for x in (0.5, 1.0, 1.5, 2.0, 2.5, 3.0, 3.5, 4.0, 4.5))


def record_gaps(duration_s: float, threshold_s: float = 2e-4, clock=time.perf_counter, chunk_s: float | None = 0.5,
                rest_s: float = 0.1, sleep=time.sleep) -> np.ndarray:
    """Busy-read ``clock`` for ``duration_s`` in all; (k, 2) [start_s, length_s] of every gap
    longer than ``threshold_s``, start on the busy time line (chunks laid end to end).

    The reading runs in chunks of ``chunk_s`` with ``rest_s`` of sleep between them (None: one
    stretch): a SCHED_FIFO thread busy for more than sched_rt_runtime_us of every
    sched_rt_period_us (Linux default 0.95 of 1 s) is throttled for the rest of the period,
    a 50 ms gap of the measurement's own making."""
    gaps = []
    done = 0.0
    while done < duration_s:
        span = duration_s - done if chunk_s is None else min(chunk_s, duration_s - done)
        t0 = t = clock()
        end = t0 + span
        while t < end:
            u = clock()
            if u - t > threshold_s:
                gaps.append((done + t - t0, u - t))
            t = u
        done += t - t0
        if done < duration_s:
            sleep(rest_s)
    return np.asarray(gaps, dtype=float).reshape(-1, 2)


def job_exceedance(gaps: np.ndarray, duration_s: float, job_s: float, limit_s: float, step_s: float = 1e-4) -> float:
    """The fraction of start times t in [0, duration_s - limit_s) (every ``step_s``) at which
    a job needing ``job_s`` of run time, running whenever the CPU is not in a gap, ends after
    t + ``limit_s``. Run time R(tau) = tau - (gap time before tau) is piecewise linear; the
    job ends at the first tau with R(tau) = R(t) + job_s."""
    if job_s > limit_s:
        return 1.0
    g = np.asarray(gaps, dtype=float).reshape(-1, 2)
    g = g[np.argsort(g[:, 0], kind="stable")]
    s, ln = g[:, 0], g[:, 1]
    before = np.concatenate([[0.0], np.cumsum(ln)[:-1]])          # gap time before each gap starts
    # breakpoints (tau, R): each gap's start and end share R = start - gap time before it
    tau = np.concatenate([[0.0], np.column_stack([s, s + ln]).ravel(), [duration_s + limit_s]])
    r_gap = s - before
    total = float(ln.sum())
    R = np.concatenate([[0.0], np.repeat(r_gap, 2), [duration_s + limit_s - total]])
    starts = np.arange(0.0, max(duration_s - limit_s, 0.0), step_s)
    if starts.size == 0:
        raise ValueError(f"duration_s {duration_s} must exceed limit_s {limit_s}")
    r0 = np.interp(starts, tau, R)
    # the earliest tau reaching r0 + job_s: the inverse of the non-decreasing R (flat in gaps;
    # searchsorted 'left' picks the segment where R first reaches the value)
    target = r0 + job_s
    i = np.clip(np.searchsorted(R, target, side="left"), 1, R.size - 1)
    r_a, r_b, t_a, t_b = R[i - 1], R[i], tau[i - 1], tau[i]
    frac = np.where(r_b > r_a, (target - r_a) / np.where(r_b > r_a, r_b - r_a, 1.0), 0.0)
    end = t_a + frac * (t_b - t_a)
    return float(np.mean(end - starts > limit_s))


def gap_summary(gaps: np.ndarray, duration_s: float) -> dict:
    ln_ms = np.asarray(gaps, dtype=float).reshape(-1, 2)[:, 1] * 1e3
    return {"duration_s": duration_s, "gaps": int(ln_ms.size),
            "per_s_over_1ms": float(np.sum(ln_ms > 1.0) / duration_s), "per_s_over_2ms": float(np.sum(ln_ms > 2.0) / duration_s),
            "per_s_over_5ms": float(np.sum(ln_ms > 5.0) / duration_s), "max_ms": float(ln_ms.max()) if ln_ms.size else 0.0,
            "lost_fraction": float(ln_ms.sum() / 1e3 / duration_s)}


def _proc_stat_cpu(cpu: int) -> tuple[int, int] | None:
    """(steal, irq + softirq) clock ticks of one CPU from /proc/stat, None where unreadable."""
    try:
        with open("/proc/stat") as fh:
            for line in fh:
                if line.startswith(f"cpu{cpu} "):
                    f = line.split()
                    return int(f[8]), int(f[6]) + int(f[7])
    except (OSError, IndexError, ValueError):
        return None
    return None


def measure(cpu: int | None, duration_s: float, limit_s: float = 5e-3, rt_priority: int | None = 50) -> dict:
    """Pin this process to ``cpu`` (None: leave it), try SCHED_FIFO ``rt_priority``, record the
    gaps and report ``gap_summary``, the /proc/stat steal time of the CPU over the same span,
    and ``job_exceedance`` for the jobs of ``JOB_GRID_S`` against ``limit_s``."""
    res: dict = {"cpu": cpu, "limit_ms": limit_s * 1e3, "fifo": False}
    if cpu is not None and hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {cpu})
    if rt_priority is not None and hasattr(os, "sched_setscheduler"):
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(rt_priority))
            res["fifo"] = True
        except (PermissionError, OSError):
            pass
    st0 = _proc_stat_cpu(cpu) if cpu is not None else None
    gaps = record_gaps(duration_s)
    st1 = _proc_stat_cpu(cpu) if cpu is not None else None
    res.update(gap_summary(gaps, duration_s))
    if st0 is not None and st1 is not None:
        hz = os.sysconf("SC_CLK_TCK")
        res["steal_fraction"] = (st1[0] - st0[0]) / hz / duration_s
        res["irq_fraction"] = (st1[1] - st0[1]) / hz / duration_s
    res["job_exceedance"] = {f"{j * 1e3:g}": job_exceedance(gaps, duration_s, j, limit_s) for j in JOB_GRID_S}
    return res


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m mfg_swarm.hiccup", description=__doc__.split("\n\n")[0])
    p.add_argument("--cpu", type=int, default=None, help="CPU to pin to (default: not pinned)")
    p.add_argument("--duration-s", type=float, default=10.0)
    p.add_argument("--limit-ms", type=float, default=5.0, help="the latency limit job_exceedance is computed against")
    a = p.parse_args(argv)
    if not a.duration_s > a.limit_ms / 1e3:
        p.error("--duration-s must exceed --limit-ms")
    if a.cpu is not None and hasattr(os, "sched_getaffinity") and a.cpu not in os.sched_getaffinity(0):
        p.error(f"--cpu {a.cpu} is not available to this process (allowed: {sorted(os.sched_getaffinity(0))})")
    json.dump(measure(a.cpu, a.duration_s, a.limit_ms / 1e3), sys.stdout)
    print()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
