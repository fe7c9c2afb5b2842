"""`mfg-swarm bench`: per-step cost, simulator scaling, process-swarm speed, latency (issue 8).

    mfg-swarm bench --out DIR [--quick] [--only step,sim,swarm,latency,pde]

Each section measures what it compares in the same run and reports a median over repeats
with its spread (p10/p90, or min/max where there are few repeats). Results: DIR/bench.json
and a table on stdout. No figure here is asserted by a test; docs/benchmarks.md holds a run.

Sections
- ``step``: wall time of one controller step for ONE vehicle (a bank of 1), p50/p99 over
  the steps of a replay, and as a fraction of the preset's control period dt.
- ``sim``: `simulate` wall time and peak RSS (ru_maxrss of a fresh subprocess per point),
  default preset, both modes; the growth exponent is the log-log slope over the two largest
  points measured. The paper preset's MFG (O(N^2) by construction) on small N only.
- ``swarm``: the process swarm in lockstep (`mfg-swarm run`): simulated seconds per wall
  second (from the first to the last control step, start-up excluded; and including
  start-up), CPU seconds and peak RSS of the children (psutil), per vehicle pair.
- ``latency``: a real-time flight; `latency_ms` of every controller step record (arrival
  of the LOCAL_POSITION_NED used -> setpoint sent).
- ``pde``: bench/pde_bench.py's learned-vs-solved time per decision, small settings.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import platform
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

__all__ = ["run_bench", "SECTIONS", "format_table"]

SECTIONS = ("step", "sim", "swarm", "latency", "pde")


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


def machine_info() -> dict:
    model = ""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return {"nproc": os.cpu_count(), "cpu_model": model, "python": platform.python_version(),
            "numpy": np.__version__, "platform": platform.platform()}


def _load() -> list[float]:
    return list(os.getloadavg())


# -- controller step, one vehicle ---------------------------------------------------------
def bench_step(quick: bool = False) -> list[dict]:
    from mfg_autopilot.interface import Neighbours, Observation
    from mfg_autopilot.presets import make_controller, preset_by_name
    from mfg_swarm.scenarios import make_scenario

    steps = 40 if quick else 300
    rng = np.random.default_rng(0)
    paper, default = preset_by_name("paper"), preset_by_name("default")
    cases = []
    for k_nb in (0, 8, 24):
        cases.append(("hjb", paper, f"HJB_d paper, {k_nb} neighbours", {"neighbours": k_nb}))
    for K in (1, 5):
        for N in (25, 81):
            pr = replace(paper, learner=replace(paper.learner, K=K))
            cases.append(("mfg", pr, f"MFG paper K={K}, N={N}", {"K": K, "N": N}))
    for N in (25, 81):
        cases.append(("mfg", default, f"MFG default, N={N}", {"N": N}))
    for k_nb in (0, 8, 24):
        cases.append(("hjb", default, f"HJB_d default, {k_nb} neighbours", {"neighbours": k_nb}))
    out = []
    for mode, preset, label, extra in cases:
        N = extra.get("N", 25)
        sc = make_scenario("paper", N)
        s0 = np.concatenate([sc.initial_pos_m, np.tile(preset.cost.v_o, (N, 1))], axis=1)
        ctrl = make_controller(mode, preset, sc.destination_m[0:1])
        if mode == "mfg" or getattr(ctrl, "uses_t0_exchange", False):
            ctrl.exchange_t0(s0, np.arange(N), np.array([0]), sc.destination_m)
        own = s0[0:1].copy()
        k_nb = extra.get("neighbours", 0)
        times = []
        for k in range(steps):
            nb = None
            if mode == "hjb":
                st = own + np.concatenate([rng.normal(0, 3.0, (k_nb, 2)), rng.normal(0, 0.5, (k_nb, 2))], axis=1)
                nb = Neighbours(st, np.zeros(k_nb, dtype=np.int64), np.arange(1, k_nb + 1))
            obs = Observation(k, k * preset.dt_s, own.copy(), nb, None)
            t = time.perf_counter()
            info = ctrl.step(obs)
            times.append(time.perf_counter() - t)
            # a crude plant so that the state moves as in flight (not timed)
            a = np.asarray(info.acc_m_s2, dtype=float).reshape(1, 2)
            own[:, 0:2] += own[:, 2:4] * preset.dt_s
            own[:, 2:4] += a * preset.dt_s
        st = _stats_ms(times[1:])          # the first step pays one-off set-up (e.g. the plan's first action)
        st.update(label=label, mode=mode, preset=preset.name, dt_s=preset.dt_s, first_step_ms=times[0] * 1e3,
                  p50_frac_dt=st["p50_ms"] / 1e3 / preset.dt_s, p99_frac_dt=st["p99_ms"] / 1e3 / preset.dt_s, **extra)
        out.append(st)
    return out


# -- simulator scaling ---------------------------------------------------------------------
_SIM_CHILD = r"""
import json, resource, sys, time
from mfg_autopilot.presets import preset_by_name
from mfg_swarm.scenarios import make_scenario
from mfg_swarm.sim import SimConfig, simulate
import numpy as np
import mfg_swarm.sim as S
marks = []
class _Marks:                      # replaces the progress bar: a timestamp after every control step
    def __init__(self, total, enabled): pass
    def update(self, k): marks.append(time.perf_counter())
S._Progress = _Marks
a = json.loads(sys.argv[1])
cfg = SimConfig(scenario=make_scenario(a["scenario"], a["n"]), mode=a["mode"], preset=preset_by_name(a["preset"]),
                seed=0, steps=a["steps"], range_m=a["range_m"])
t = time.perf_counter(); _, m = simulate(cfg, progress=False); wall = time.perf_counter() - t
d = np.diff(marks)
print(json.dumps({"setup_and_first_step_s": marks[0] - t, "step_s_median": float(np.median(d)) if d.size else None,
                  "step_s_p90": float(np.percentile(d, 90)) if d.size else None, "after_loop_s": t + wall - marks[-1],
                  "wall_s": wall, "cpu_s": time.process_time(), "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
                  "collision_pairs": m["collision_pairs"], "arrived_fraction": m["arrived_fraction"]}))
"""


SIM_HJB_RANGE_M = 100.0
"""HJB_d's radio range in the simulator benchmark: HJB_100, issue 8's "both modes" (at the slots every UAV
hears nearly everyone: the simulator's worst case)."""


def _sim_point(n: int, mode: str, preset: str, steps: int, timeout_s: float, scenario: str = "paper") -> dict:
    args = {"n": n, "mode": mode, "preset": preset, "steps": steps, "scenario": scenario,
            "range_m": SIM_HJB_RANGE_M if mode == "hjb" else None}
    rec = {"n": n, "mode": mode, "preset": preset, "scenario": scenario, "steps": steps, "load_before": _load()}
    t = time.perf_counter()
    try:
        p = subprocess.run([sys.executable, "-c", _SIM_CHILD, json.dumps(args)], capture_output=True, text=True,
                           timeout=timeout_s)
    except subprocess.TimeoutExpired:
        rec.update(status="timeout", timeout_s=timeout_s, wall_s=None)
        return rec
    if p.returncode != 0:
        rec.update(status="error", error=p.stderr[-2000:])
        return rec
    rec.update(json.loads(p.stdout.strip().splitlines()[-1]), status="ok", process_wall_s=time.perf_counter() - t)
    return rec


def _slope(points: list[dict], key: str = "wall_s") -> float | None:
    ok = [p for p in points if p.get("status") == "ok" and p.get(key)]
    if len(ok) < 2:
        return None
    a, b = ok[-2], ok[-1]
    return math.log(b[key] / a[key]) / math.log(b["n"] / a["n"])


_SHORT_STEPS = 10


def bench_sim(quick: bool = False, timeout_s: float = 900.0, ns: tuple[int, ...] | None = None,
              repeats: int | None = None) -> dict:
    """Default preset, 200 simulated seconds = 400 steps at dt = 0.5 s (quick: 20 steps)."""
    from mfg_autopilot.presets import preset_by_name

    steps = 20 if quick else int(round(200.0 / preset_by_name("default").dt_s))
    ns = ns or ((25, 81) if quick else (25, 81, 1000, 10000))
    repeats = repeats or (1 if quick else 3)
    out: dict = {"steps": steps, "simulated_s": steps * preset_by_name("default").dt_s, "hjb_range_m": SIM_HJB_RANGE_M,
                 "points": [], "exponent": {}, "exponent_cpu": {}}
    for mode in ("mfg", "hjb"):
        pts = []
        for n in ns:
            reps = [_sim_point(n, mode, "default", steps, timeout_s) for _ in range(repeats if n <= 81 else 1)]
            ok = [r for r in reps if r["status"] == "ok"]
            rec = dict(reps[-1])
            if ok:
                w = [r["wall_s"] for r in ok]
                rec.update(wall_s=float(np.median(w)), wall_min_s=min(w), wall_max_s=max(w), repeats=len(ok),
                           peak_rss_mb=float(max(r["peak_rss_mb"] for r in ok)))
            if rec["status"] == "timeout":
                # what one step costs at this N: a short run (set-up included), extrapolated to the full run
                short = _sim_point(n, mode, "default", _SHORT_STEPS, timeout_s)
                if short["status"] == "ok":
                    rec["short_run"] = short
                    rec["extrapolated_wall_s"] = (short["setup_and_first_step_s"] + (steps - 1) * short["step_s_median"]
                                                  + short["after_loop_s"])
            pts.append(rec)
            out["points"].append(rec)
            if rec["status"] != "ok":
                break                      # larger N would not finish either
        out["exponent"][mode] = _slope(pts)
        out["exponent_cpu"][mode] = _slope(pts, "cpu_s")     # CPU time: less sensitive to a shared machine's load
    # the paper preset's MFG: N particles per vehicle, O(N^2) per step by construction (docs/mean_field.md)
    psteps = 10 if quick else 50
    paper_pts = [_sim_point(n, "mfg", "paper", psteps, timeout_s) for n in ((25,) if quick else (25, 81, 256))]
    out["paper_mfg"] = {"steps": psteps, "points": paper_pts, "exponent": _slope(paper_pts)}
    return out


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


def bench_pde_ratio(quick: bool = False) -> dict:
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "bench"))
    try:
        import pde_bench
    finally:
        sys.path.pop(0)
    r = pde_bench.bench_pde(n=9, steps=5 if quick else 20, levels=((4.0, 1.0),), mfg_levels=1, inits=("lqr",), flights=False)
    return {"n": 9, "steps": r["steps"], "timing": r["timing"]}


# -- report ---------------------------------------------------------------------------------
def _latency_line(st: dict) -> str:
    line = f"{st['n']} steps, p50 {st['p50_ms']:.3f} ms, p99 {st['p99_ms']:.3f} ms"
    if "p99_ci95_ms" in st:
        lo, hi = st["p99_ci95_ms"]
        line += f" (95 % CI {lo:.2f}-{hi:.2f}), {st['over_target']} over {st['target_ms']:g} ms"
    line += f", max {st['max_ms']:.3f} ms"
    fl = [f"{x * 100:.2f} %" for x in st.get("host_floor_over_target") or [] if x is not None]
    if fl:
        line += f"; host floor for a p50-long job: {' / '.join(fl)} over {st.get('target_ms', LATENCY_TARGET_MS):g} ms (per CPU)"
    return line


def _split_lines(split: dict, indent: str) -> list[str]:
    return [f"{indent}of which {part}: p50 {st['p50_ms']:.3f} ms, p99 {st['p99_ms']:.3f} ms" for part, st in split.items()]


def format_table(res: dict) -> str:
    L = []
    m = res["machine"]
    L.append(f"machine: {m['nproc']} cores, {m['cpu_model']}; load before {res['load_before']}, after {res.get('load_after')}")
    if "step" in res:
        L.append("\nController step, one vehicle (ms; fraction of dt)")
        L.append(f"{'case':36s} {'p50':>8s} {'p99':>8s} {'p10':>8s} {'p90':>8s} {'p50/dt':>9s} {'p99/dt':>9s}")
        for r in res["step"]:
            L.append(f"{r['label']:36s} {r['p50_ms']:8.3f} {r['p99_ms']:8.3f} {r['p10_ms']:8.3f} {r['p90_ms']:8.3f} "
                     f"{r['p50_frac_dt']:9.2e} {r['p99_frac_dt']:9.2e}")
    if "sim" in res:
        s = res["sim"]
        L.append(f"\nSimulator, default preset, paper scenario, {s['steps']} steps = {s['simulated_s']:.0f} simulated s")
        L.append(f"{'mode':5s} {'N':>6s} {'wall s':>9s} {'min':>8s} {'max':>8s} {'peak MB':>8s} status")
        for r in s["points"]:
            wall = f"{r['wall_s']:9.2f}" if r.get("wall_s") is not None else f"{'>' + str(r.get('timeout_s')):>9s}"
            extra = ""
            if "short_run" in r:
                sr = r["short_run"]
                extra = (f" ({sr['steps']}-step run: set-up + step 1 {sr['setup_and_first_step_s']:.1f} s, then "
                         f"{sr['step_s_median']:.2f} s/step, peak {sr['peak_rss_mb']:.0f} MB -> ~{r['extrapolated_wall_s']:.0f} s for {s['steps']})")
            L.append(f"{r['mode']:5s} {r['n']:6d} {wall} {r.get('wall_min_s', float('nan')):8.2f} {r.get('wall_max_s', float('nan')):8.2f} "
                     f"{r.get('peak_rss_mb', float('nan')):8.0f} {r['status']}{extra}")
        L.append("growth exponent (log-log slope, two largest N): " + ", ".join(
            f"{k} {v:.2f}" if v is not None else f"{k} n/a" for k, v in s["exponent"].items()))
        pm = s["paper_mfg"]
        L.append(f"paper preset MFG ({pm['steps']} steps): " + ", ".join(
            f"N={r['n']}: {r['wall_s']:.2f} s" if r.get("wall_s") is not None else f"N={r['n']}: {r['status']}" for r in pm["points"])
                 + (f"; exponent {pm['exponent']:.2f}" if pm["exponent"] is not None else ""))
    if "swarm" in res:
        L.append("\nProcess swarm, lockstep, default preset MFG (sim s / wall s; per vehicle pair = mock + controller)")
        L.append(f"{'N':>4s} {'steps':>6s} {'x real (flight)':>16s} {'start-up s':>11s} {'x real (total)':>15s} {'CPU s/pair':>11s} "
                 f"{'CPU/pair/sim s':>15s} {'flight CPU ms/pair/step':>24s} {'peak MB/pair':>13s}")
        for r in res["swarm"]:
            spread = (f"  (x real flight {r['realtime_factor_flight_min']:.2f}-{r['realtime_factor_flight_max']:.2f}, "
                      f"CPU {r['cpu_ms_per_pair_step_flight_min']:.1f}-{r['cpu_ms_per_pair_step_flight_max']:.1f}, "
                      f"{r['repeats']} runs)" if r.get("repeats", 1) > 1 and "realtime_factor_flight_min" in r
                      and "cpu_ms_per_pair_step_flight_min" in r else "")
            L.append(f"{r['n']:4d} {r['steps']:6d} {r.get('realtime_factor_flight', float('nan')):16.2f} "
                     f"{r.get('wall_start_up_s', float('nan')):11.1f} {r['realtime_factor_total']:15.2f} "
                     f"{r['cpu_s_per_pair']:11.2f} {r['cpu_s_per_pair_per_sim_s']:15.3f} {r.get('cpu_ms_per_pair_step_flight', float('nan')):24.1f} "
                     f"{r['peak_rss_mb_per_pair']:13.0f}" + (" PARTIAL" if r["partial"] else "") + spread)
    if "latency" in res:
        la = res["latency"]["latency"]
        L.append(f"\nTelemetry-to-setpoint latency, real time, N = {res['latency']['n_vehicles']}: "
                 + (_latency_line(la) if la["n"] else "no steps"))
        for h in res["latency"].get("host", []):
            if "error" in h:
                L.append(f"  host noise, CPU {h['cpu']}: not measured ({h['error']})")
                continue
            L.append(f"  host noise, CPU {h['cpu']} ({'SCHED_FIFO' if h['fifo'] else 'normal'}, {h['duration_s']:g} s busy): "
                     f"stops > 2 ms {h['per_s_over_2ms']:.1f}/s, > 5 ms {h['per_s_over_5ms']:.1f}/s, max {h['max_ms']:.1f} ms, "
                     f"lost {h['lost_fraction'] * 100:.1f} %" + (f", steal {h['steal_fraction'] * 100:.1f} %" if "steal_fraction" in h else "")
                     + "; P(job ends > target) for 1/2/3/4 ms jobs: "
                     + " / ".join(f"{h['job_exceedance'][k] * 100:.2f} %" for k in ("1", "2", "3", "4")))
        L += _split_lines(res["latency"].get("latency_split", {}), "  ")
        rt = res["latency"].get("rt")
        if rt:
            lr = rt["latency"]
            L.append(f"  controllers at SCHED_FIFO {rt['priority']} ({'applied' if rt['applied'] else 'NOT applied: normal scheduling'}): "
                     + (_latency_line(lr) if lr["n"] else "no steps"))
            L += _split_lines(rt.get("latency_split", {}), "    ")
        oc = res["latency"].get("own_cpu")
        if oc:
            lo = oc["latency"]
            L.append(f"  controller 0 alone on CPU {oc['cpu']} (the rest of the swarm on the other CPUs), SCHED_FIFO {oc['priority']}"
                     f"{'' if oc['applied'] else ' NOT applied'}, {oc['flights']} flights: " + (_latency_line(lo) if lo["n"] else "no steps"))
            L += _split_lines(oc.get("latency_split", {}), "    ")
    if "pde" in res:
        L.append("\nLearned vs solved (bench/pde_bench.py, N = 9, coarsest grid): time per decision")
        for r in res["pde"]["timing"]:
            L.append(f"  {r['mode']:8s} learned {r['learned_s_per_decision'] * 1e3:.3f} ms, solved {r['solved_s_per_decision'] * 1e3:.3f} ms, "
                     f"solved/learned {r['ratio_step']:.2f}x (with re-solve per decision {r['ratio_resolve_per_decision']:.0f}x)")
    return "\n".join(L)


def run_bench(out: Path, quick: bool = False, only: tuple[str, ...] = SECTIONS, sim_timeout_s: float = 900.0,
              log=lambda s: print(s, file=sys.stderr)) -> dict:
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    bad = set(only) - set(SECTIONS)
    if bad:
        raise ValueError(f"unknown bench sections {sorted(bad)}; known: {', '.join(SECTIONS)}")
    res: dict = {"quick": quick, "machine": machine_info(), "load_before": _load(), "started_unix_s": time.time()}
    work = Path(tempfile.mkdtemp(prefix="swarm-", dir=out))
    steps = [("step", lambda: bench_step(quick)), ("sim", lambda: bench_sim(quick, sim_timeout_s)),
             ("swarm", lambda: bench_swarm(work, quick)), ("latency", lambda: bench_latency(work, quick)),
             ("pde", lambda: bench_pde_ratio(quick))]
    for name, fn in steps:
        if name not in only:
            continue
        log(f"bench: {name} ...")
        t = time.perf_counter()
        res[name] = fn()
        res.setdefault("section_wall_s", {})[name] = time.perf_counter() - t
        res["load_after"] = _load()
        (out / "bench.json").write_text(json.dumps(res, indent=1))      # partial results survive a later failure
    res["load_after"] = _load()
    (out / "bench.json").write_text(json.dumps(res, indent=1))
    return res
