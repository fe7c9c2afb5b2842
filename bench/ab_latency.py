"""Telemetry-to-setpoint latency of two code trees, measured back to back (A/B, interleaved).

    .venv/bin/python bench/ab_latency.py --base /tmp/old --new . --reps 2 --out /tmp/ab

On a shared machine the host's speed can change by 2x within minutes (docs/benchmarks.md,
"Fifth round"), so two separate bench runs compare machines as much as code. This flies the
same real-time N = 4 flight (default preset, MFG, ``--steps`` steps at dt = 0.5 s) with each
tree in turn, with normal scheduling and with the controllers at SCHED_FIFO 50, ``--reps``
times, and pools every controller's step records per (tree, scheduling). A tree is any
checkout of this project (e.g. ``git worktree add --detach /tmp/old <commit>``); it runs with
this interpreter and ``PYTHONPATH`` set to the tree, so both use the same installed packages.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

_FLY = """
import sys
from pathlib import Path
from mfg_swarm.launcher import RunConfig, run_swarm
from mfg_swarm.scenarios import make_scenario
rt = None if sys.argv[2] == "none" else int(sys.argv[2])
run_swarm(RunConfig(scenario=make_scenario("paper", 4), mode="mfg", preset_name="default", out=Path(sys.argv[1]), seed=0,
                    steps=int(sys.argv[3]), range_m=None, lockstep=False, progress=False, controller_rt_priority=rt))
"""


def fly(tree: Path, out: Path, rt: str, steps: int) -> None:
    env = dict(os.environ, PYTHONPATH=str(tree))
    p = subprocess.run([sys.executable, "-c", _FLY, str(out), rt, str(steps)], env=env, cwd=tree, timeout=900,
                       capture_output=True, text=True)
    if p.returncode != 0:
        raise SystemExit(f"flight {out} failed:\n{p.stderr[-2000:]}")


def summary(dirs: list[Path]) -> dict:
    from mfg_swarm.bench_processes import _latency_of

    st, split, _ = _latency_of(dirs)
    return {"latency": st, "compute_p50_ms": split.get("compute", {}).get("p50_ms"),
            "control_cpu_p50_ms": split.get("control_cpu_backstop_idle", {}).get("p50_ms")}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--base", type=Path, required=True, help="the tree to compare against")
    p.add_argument("--new", type=Path, default=Path("."), help="the tree under test (default: this one)")
    p.add_argument("--reps", type=int, default=2)
    p.add_argument("--steps", type=int, default=80, help="steps per flight (they arrive at ~110)")
    p.add_argument("--out", type=Path, required=True)
    a = p.parse_args(argv)
    trees = {"base": a.base.resolve(), "new": a.new.resolve()}
    for name, t in trees.items():
        if not (t / "mfg_swarm" / "launcher.py").is_file():
            p.error(f"--{name} {t} is not a checkout of this project")
    runs: dict[tuple[str, str], list[Path]] = {}
    for r in range(a.reps):
        for rt in ("none", "50"):
            for name, tree in trees.items():          # alternately: each pair of flights sees the same host
                d = a.out / f"{name}-rt{rt}-{r}"
                fly(tree, d, rt, a.steps)
                runs.setdefault((name, rt), []).append(d)
                print(f"flown {d}", file=sys.stderr)
    print(f"{'scheduling':12s} {'tree':5s} {'steps':>5s} {'p50':>6s} {'p90':>6s} {'p99':>6s} {'> 5 ms':>7s} {'compute p50':>12s} {'ctl CPU p50':>12s}")
    for (name, rt), dirs in sorted(runs.items(), key=lambda kv: (kv[0][1], kv[0][0])):
        s = summary(dirs)
        la = s["latency"]
        print(f"{'normal' if rt == 'none' else 'FIFO ' + rt:12s} {name:5s} {la['n']:5d} {la['p50_ms']:6.2f} {la['p90_ms']:6.2f} "
              f"{la['p99_ms']:6.2f} {la['over_target']:7d} {s['compute_p50_ms'] or np.nan:12.2f} {s['control_cpu_p50_ms'] or np.nan:12.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
