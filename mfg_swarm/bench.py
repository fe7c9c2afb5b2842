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

The process sections (``swarm``, ``latency``) live in :mod:`mfg_swarm.bench_processes`.
"""

from __future__ import annotations

import json
import math
import os
import platform
import subprocess
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from mfg_swarm.bench_processes import LATENCY_TARGET_MS, _load, _stats_ms, bench_latency, bench_swarm

__all__ = ["run_bench", "SECTIONS", "format_table"]

SECTIONS = ("step", "sim", "swarm", "latency", "pde")


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
