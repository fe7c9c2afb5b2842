"""`mfg-swarm bench`'s process sections: the process swarm's speed and the telemetry-to-setpoint latency.

Everything that measures real processes lives here: sampling the children's CPU and memory
(psutil), pinning one controller to its own CPU (``_CpuIsolation``), the flight window of a
lockstep swarm, the host's own noise (``mfg_swarm.hiccup``) and the latency statistics of a
real-time flight. :mod:`mfg_swarm.bench` runs these sections beside the in-process ones and
prints the table.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

def _stats_ms(samples_s) -> dict:
    a = np.asarray(samples_s, dtype=float) * 1e3
    return {"n": int(a.size), "p50_ms": float(np.percentile(a, 50)), "p10_ms": float(np.percentile(a, 10)),
            "p90_ms": float(np.percentile(a, 90)), "p99_ms": float(np.percentile(a, 99)), "max_ms": float(a.max())}


LATENCY_TARGET_MS = 5.0


def _latency_stats(samples_s) -> dict:
    """``_stats_ms`` plus what decides the p99 target: a distribution-free 95 % confidence
    interval of p99 (the order statistics that bracket it: binomial counts of samples below
    the true p99) and the number of samples over the target."""
    from scipy.stats import binom

    st = _stats_ms(samples_s)
    a = np.sort(np.asarray(samples_s, dtype=float) * 1e3)
    n = a.size
    lo, hi = int(binom.ppf(0.025, n, 0.99)), int(binom.ppf(0.975, n, 0.99)) + 1    # 1-based ranks
    st["p99_ci95_ms"] = [float(a[max(lo, 1) - 1]), float(a[min(hi, n) - 1])]
    st["over_target"] = int(np.count_nonzero(a > LATENCY_TARGET_MS))
    st["target_ms"] = LATENCY_TARGET_MS
    return st


def _load() -> list[float]:
    return list(os.getloadavg())


# -- process swarm -------------------------------------------------------------------------
class _ChildSampler:
    """Polls psutil over this process's children: peak RSS and last CPU times per pid, by role."""

    def __init__(self, period_s: float = 0.25) -> None:
        import psutil

        self.psutil, self.period_s = psutil, period_s
        self.me = psutil.Process()
        self.cpu: dict[int, float] = {}
        self.rss: dict[int, int] = {}
        self.role: dict[int, str] = {}
        self.series: dict[int, list[tuple[float, float]]] = {}   # pid -> [(Unix time, CPU s so far)]
        self.stop = threading.Event()
        self.th = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        while not self.stop.is_set():
            for c in self.me.children(recursive=True):
                try:
                    with c.oneshot():
                        ct = c.cpu_times()
                        self.cpu[c.pid] = ct.user + ct.system
                        self.series.setdefault(c.pid, []).append((time.time(), self.cpu[c.pid]))
                        self.rss[c.pid] = max(self.rss.get(c.pid, 0), c.memory_info().rss)
                        if c.pid not in self.role:
                            cmd = " ".join(c.cmdline())
                            self.role[c.pid] = ("controller" if "mfg_autopilot.runtime.cli" in cmd else "mock" if "mock_vehicle.cli" in cmd
                                                else "router" if "zenoh_router" in cmd else "world" if "mock_vehicle.world" in cmd
                                                else "other")
                except (self.psutil.NoSuchProcess, self.psutil.AccessDenied, self.psutil.ZombieProcess):
                    pass
            self.stop.wait(self.period_s)

    def __enter__(self):
        self.th.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop.set()
        self.th.join()

    def cpu_between(self, pid: int, t0: float, t1: float) -> float:
        """CPU seconds ``pid`` spent between Unix times t0 and t1, interpolated between samples."""
        ser = self.series.get(pid, [])
        if not ser:
            return 0.0
        ts, cs = np.array([t for t, _ in ser]), np.array([c for _, c in ser])
        return float(np.interp(t1, ts, cs) - np.interp(t0, ts, cs))

    def by_role(self) -> dict:
        out: dict = {}
        for pid, role in self.role.items():
            r = out.setdefault(role, {"count": 0, "cpu_s": 0.0, "peak_rss_mb_sum": 0.0})
            r["count"] += 1
            r["cpu_s"] += self.cpu.get(pid, 0.0)
            r["peak_rss_mb_sum"] += self.rss.get(pid, 0) / 2**20
        return out


class _CpuIsolation:
    """A flight computer's dedicated core on a shared machine: controller ``instance`` (every
    thread) on ``own_cpu``, this process and every other process of the swarm on the other
    CPUs. Children are pinned as they appear (polled; a thread started later is pinned at the
    next poll); the flight's first steps come seconds after the processes start."""

    def __init__(self, own_cpu: int, instance: int = 0, period_s: float = 0.2) -> None:
        import psutil

        self.psutil, self.own, self.instance, self.period_s = psutil, own_cpu, instance, period_s
        self.rest = set(os.sched_getaffinity(0)) - {own_cpu}
        if not self.rest:
            raise ValueError(f"isolating CPU {own_cpu} leaves no CPU for the rest of the swarm")
        self.pinned: set[tuple[int, int]] = set()      # (pid, tid) already pinned
        self.stop = threading.Event()
        self.th = threading.Thread(target=self._run, daemon=True)

    def _is_isolated(self, cmd: list[str]) -> bool:
        return ("mfg_autopilot.runtime.cli" in " ".join(cmd) and "--instance" in cmd
                and cmd[cmd.index("--instance") + 1:cmd.index("--instance") + 2] == [str(self.instance)])

    def _run(self) -> None:
        while not self.stop.is_set():
            for c in self.psutil.Process().children(recursive=True):
                try:
                    mine = self._is_isolated(c.cmdline())
                    for t in os.listdir(f"/proc/{c.pid}/task"):
                        if (c.pid, int(t)) not in self.pinned:
                            os.sched_setaffinity(int(t), {self.own} if mine else self.rest)
                            self.pinned.add((c.pid, int(t)))
                except (self.psutil.Error, OSError):
                    pass
            self.stop.wait(self.period_s)

    def __enter__(self):
        self._before = os.sched_getaffinity(0)
        os.sched_setaffinity(0, self.rest)
        self.th.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop.set()
        self.th.join()
        os.sched_setaffinity(0, self._before)


def _swarm_point(n: int, steps: int, lockstep: bool, out_dir: Path, mode: str = "mfg", rt_priority: int | None = None,
                 isolate_cpu: int | None = None) -> dict:
    from mfg_autopilot.presets import preset_by_name
    from mfg_swarm.launcher import RunConfig, run_swarm
    from mfg_swarm.scenarios import make_scenario

    dt = preset_by_name("default").dt_s
    cfg = RunConfig(scenario=make_scenario("paper", n), mode=mode, preset_name="default", out=out_dir, seed=0, steps=steps,
                    range_m=10.0 if mode == "hjb" else None, lockstep=lockstep, progress=False,
                    controller_rt_priority=rt_priority)
    first_step = {"t": None, "cpu": {}}
    stop = threading.Event()
    samp = _ChildSampler()

    def watch() -> None:               # when the first control step record appears (start-up over)
        log = out_dir / "controllers" / "controller0.jsonl"
        offset = 0
        while not stop.is_set() and first_step["t"] is None:
            try:
                with open(log, "rb") as fh:                 # only what was appended since the last look
                    fh.seek(max(0, offset - 16))
                    data = fh.read()
                    offset = fh.tell()
                if b'"type": "step"' in data or b'"type":"step"' in data:
                    first_step["t"] = time.perf_counter()
                    first_step["cpu"] = dict(samp.cpu)       # CPU spent by then: start-up
            except OSError:
                pass
            stop.wait(0.05)

    w = threading.Thread(target=watch, daemon=True)
    load0 = _load()
    t0 = time.perf_counter()
    iso = _CpuIsolation(isolate_cpu) if isolate_cpu is not None else contextlib.nullcontext()
    with iso, samp:
        w.start()
        _, metrics = run_swarm(cfg)
        t1 = time.perf_counter()
    stop.set(); w.join()
    roles = samp.by_role()
    sim_s = steps * dt
    rec = {"n": n, "mode": mode, "steps": steps, "simulated_s": sim_s, "lockstep": lockstep, "load_before": load0,
           "wall_total_s": t1 - t0, "partial": bool(metrics.get("partial")), "roles": roles,
           "realtime_factor_total": sim_s / (t1 - t0)}
    if first_step["t"] is not None:
        rec["wall_start_up_s"] = first_step["t"] - t0
    pair_cpu = sum(roles.get(r, {}).get("cpu_s", 0.0) for r in ("mock", "controller"))
    pair_rss = sum(roles.get(r, {}).get("peak_rss_mb_sum", 0.0) for r in ("mock", "controller"))
    rec.update(cpu_s_per_pair=pair_cpu / n, peak_rss_mb_per_pair=pair_rss / n,
               cpu_s_per_pair_per_sim_s=pair_cpu / n / sim_s)
    rec.update(_flight_window(out_dir, samp, n))
    rec["load_after"] = _load()
    return rec


def _flight_window(out_dir: Path, samp: _ChildSampler, n: int, skip_steps: int = 2) -> dict:
    """The flight itself, from controller 0's step records (``wall_s``, ``time_s``,
    ``timing.process_cpu_s``): simulated seconds per wall second between its step ``skip_steps``
    and its last step (start-up, the first steps and the shutdown are outside), the controllers'
    CPU over their own records' window (exact) and the other roles' CPU over controller 0's window
    (psutil samples, interpolated)."""
    from mfg_swarm.flightlog import read_controller_log

    def steps_of(i: int) -> list[dict]:
        try:
            return [r for r in read_controller_log(out_dir / "controllers" / f"controller{i}.jsonl").steps
                    if "wall_s" in r and "process_cpu_s" in r.get("timing", {})]
        except OSError:
            return []

    s0 = steps_of(0)
    if len(s0) < skip_steps + 2:
        return {}
    a, b = s0[skip_steps], s0[-1]
    k = b["step"] - a["step"]
    out = {"flight_steps": k, "wall_flight_s": b["wall_s"] - a["wall_s"],
           "realtime_factor_flight": (b["time_s"] - a["time_s"]) / max(b["wall_s"] - a["wall_s"], 1e-9)}
    by_role: dict[str, float] = {}
    for pid, role in samp.role.items():
        if role != "controller":
            by_role[role] = by_role.get(role, 0.0) + samp.cpu_between(pid, a["wall_s"], b["wall_s"])
    ctl, counted = 0.0, 0
    for i in range(n):
        recs = {r["step"]: r for r in steps_of(i)}
        if a["step"] in recs and b["step"] in recs:
            ctl += recs[b["step"]]["timing"]["process_cpu_s"] - recs[a["step"]]["timing"]["process_cpu_s"]
            counted += 1
    if counted < n:        # a controller without both records: its CPU is unknown, so is the sum
        out["controllers_without_window"] = n - counted
        return out
    by_role["controller"] = ctl
    # CPU per step of each role summed over its processes (the world and the router are serial or shared)
    out["cpu_ms_per_step_flight_by_role"] = {r: c / k * 1e3 for r, c in sorted(by_role.items())}
    out["cpu_ms_per_pair_step_flight"] = (ctl + by_role.get("mock", 0.0)) / n / k * 1e3
    return out


_SWARM_SPREAD_KEYS = ("realtime_factor_flight", "cpu_ms_per_pair_step_flight", "wall_start_up_s", "realtime_factor_total")


def _swarm_summary(reps: list[dict]) -> dict:
    """The last repeat's record with each of _SWARM_SPREAD_KEYS replaced by the median over
    the repeats, plus KEY_min / KEY_max and ``repeats`` (every repeat is kept in ``runs``)."""
    rec = dict(reps[-1])
    for key in _SWARM_SPREAD_KEYS:
        vals = [r[key] for r in reps if r.get(key) is not None]
        if vals:
            rec.update({key: float(np.median(vals)), f"{key}_min": min(vals), f"{key}_max": max(vals)})
    rec["repeats"] = len(reps)
    if len(reps) > 1:
        rec["runs"] = [{k: r.get(k) for k in (*_SWARM_SPREAD_KEYS, "load_before", "partial")} for r in reps]
    return rec


def bench_swarm(out: Path, quick: bool = False, repeats: int | None = None) -> list[dict]:
    """Lockstep process swarms, N = 4, 9, 25, 49, 81 (quick: 4, 9); ``repeats`` runs (default
    3, quick 1) for N <= 25, one for the larger ones (start-up alone takes minutes there)."""
    ns = (4, 9) if quick else (4, 9, 25, 49, 81)
    steps = 20 if quick else 60          # 30 simulated s at dt = 0.5 s
    repeats = repeats or (1 if quick else 3)
    res = []
    for n in ns:
        reps = [_swarm_point(n, steps, True, out / f"swarm-n{n}-{r}") for r in range(repeats if n <= 25 else 1)]
        res.append(_swarm_summary(reps))
    return res


def _latency_of(d: Path | list[Path], pattern: str = "controller*.jsonl") -> tuple[dict, dict, bool | None]:
    """Latency statistics pooled over the controller logs matching ``pattern`` of the run folder(s) ``d``."""
    from mfg_swarm.flightlog import read_controller_log

    lat, wake, compute, rt = [], [], [], None
    phases: dict[str, list[float]] = {}
    files = [f for x in ([d] if isinstance(d, Path) else d) for f in sorted((x / "controllers").glob(pattern))]
    for f in files:
        rec = read_controller_log(f)
        for r in rec.steps:
            if r.get("latency_ms") is not None:
                lat.append(float(r["latency_ms"]))
                if r.get("latency_wake_ms") is not None:
                    wake.append(float(r["latency_wake_ms"]))
                    compute.append(float(r["latency_compute_ms"]))
                t = r.get("timing") or {}
                if "control_cpu_ms" in t:
                    # the control step's own CPU (thread time) and what it was not running (preempted, GIL),
                    # split by whether the backstop acted (its response costs the numeric step ~2x)
                    kind = "backstop_active" if r.get("backstop_active") else "backstop_idle"
                    for name, v in ((f"control_cpu_{kind}", t["control_cpu_ms"]),
                                    ("control_not_running", t["control_ms"] - t["control_cpu_ms"]),
                                    ("observe", t.get("observe_ms", math.nan)), ("send", t.get("send_ms", math.nan))):
                        phases.setdefault(name, []).append(float(v))
        for e in rec.events:
            if e.get("what") == "rt_priority":
                rt = bool(e.get("applied")) if rt is None else (rt and bool(e.get("applied")))
    st = _latency_stats(np.asarray(lat) / 1e3) if lat else {"n": 0}
    split = {k: _stats_ms(np.asarray(v) / 1e3) for k, v in (("wake", wake), ("compute", compute)) if v}
    split.update({k: _stats_ms(np.asarray(v) / 1e3) for k, v in sorted(phases.items()) if v and np.all(np.isfinite(v))})
    return st, split, rt


def _cpus() -> list[int]:
    """The CPUs this process may run on (empty where the OS does not say)."""
    return sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else []


def host_noise(duration_s: float) -> list[dict]:
    """mfg_swarm.hiccup on every CPU this process may use, all at once (one pinned child each):
    how often and how long each CPU stops running a SCHED_FIFO thread, and the probability
    that a job of 0.5-4.5 ms of CPU ends after the latency target there."""
    cpus = _cpus() or [None]
    procs = [subprocess.Popen([sys.executable, "-m", "mfg_swarm.hiccup", "--duration-s", str(duration_s),
                               "--limit-ms", str(LATENCY_TARGET_MS)] + ([] if c is None else ["--cpu", str(c)]),
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for c in cpus]
    res = []
    for c, pr in zip(cpus, procs):
        try:
            out, err = pr.communicate(timeout=3 * duration_s + 60)
        except subprocess.TimeoutExpired:
            pr.kill()
            out, err = pr.communicate()
        res.append(json.loads(out) if pr.returncode == 0 and out.strip() else {"cpu": c, "error": err.strip()[-300:]})
    return res


def host_floor(host: list[dict], job_ms: float) -> list[float | None]:
    """Per CPU of ``host_noise``: the probability that a job of ``job_ms`` (interpolated on the
    meter's 0.5-4.5 ms grid; above it, the last point: a lower bound) ends after the target."""
    out = []
    for h in host:
        ex = h.get("job_exceedance")
        if not ex:
            out.append(None)
            continue
        xs = sorted(ex, key=float)
        out.append(float(np.interp(job_ms, [float(x) for x in xs], [ex[x] for x in xs])))
    return out


def bench_latency(out: Path, quick: bool = False, rt_priority: int | None = 50) -> dict:
    """Real-time flights of N = 4 (quick: N = 1, 10 s; else 50 s = 100 steps at dt = 0.5 s: they
    arrive at ~55 s): once with normal scheduling, once with the controllers at SCHED_FIFO
    ``rt_priority`` (as a flight computer runs its controller; recorded as not applied where the
    OS refuses it), and (not quick, 2 CPUs or more) twice more at SCHED_FIFO with controller 0
    alone on the last CPU and everything else on the others (its latency only: a flight
    computer's dedicated core). The host's own noise is measured just before (``host_noise``)."""
    n, steps = (1, 20) if quick else (4, 100)
    host = host_noise(1.0 if quick else 10.0)
    res: dict = {"n_vehicles": n, "steps": steps, "host": host}

    def config(dirs: list[Path], pattern: str = "controller*.jsonl") -> tuple[dict, dict, bool | None]:
        st, split, applied = _latency_of(dirs, pattern)
        if st.get("n"):
            st["host_floor_over_target"] = host_floor(host, st["p50_ms"])
        return st, split, applied

    d = out / f"latency-n{n}"
    res["flight"] = _swarm_point(n, steps, False, d)
    res["latency"], res["latency_split"], _ = config([d])
    if rt_priority is not None:
        d_rt = out / f"latency-n{n}-rt{rt_priority}"
        rec_rt = _swarm_point(n, steps, False, d_rt, rt_priority=rt_priority)
        st_rt, split_rt, applied = config([d_rt])
        res["rt"] = {"priority": rt_priority, "applied": applied, "latency": st_rt, "latency_split": split_rt, "flight": rec_rt}
        cpus = _cpus()
        if not quick and len(cpus) >= 2:
            dirs = [out / f"latency-n{n}-rt{rt_priority}-own-cpu-{r}" for r in range(2)]
            recs = [_swarm_point(n, steps, False, x, rt_priority=rt_priority, isolate_cpu=cpus[-1]) for x in dirs]
            st_i, split_i, applied_i = config(dirs, "controller0.jsonl")
            res["own_cpu"] = {"priority": rt_priority, "applied": applied_i, "cpu": cpus[-1], "flights": len(dirs),
                              "latency": st_i, "latency_split": split_i, "flight": recs}
    return res
