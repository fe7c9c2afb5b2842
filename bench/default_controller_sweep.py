"""Measurements behind docs/default_controller.md (issue 7): the must-show table, the
ablation table (each piece of the default controller on / off) and the fault runs.

    .venv/bin/python bench/default_controller_sweep.py must      --seeds 0,1,2 --workers 1
    .venv/bin/python bench/default_controller_sweep.py ablation  --seeds 0,1,2 --workers 1
    .venv/bin/python bench/default_controller_sweep.py faults    --seeds 0,1,2 --workers 1
    .venv/bin/python bench/default_controller_sweep.py faults    --seeds 3,4 --workers 1 --variants "MFG default;MFG default, no backstop"
    .venv/bin/python bench/default_controller_sweep.py ablation  --seeds 0,1,2 --workers 1 --variants "default (all pieces);no backstop"

Each prints a markdown table (and writes the raw rows as JSON with --json PATH). Every run
is `mfg-swarm sim` in process (mfg_swarm.sim.simulate) with the default 200 steps.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import multiprocessing as mp
import sys

import numpy as np

from mfg_autopilot.presets import preset_by_name
from mfg_swarm.scenarios import make_scenario
from mfg_swarm.sim import GustParams, SimConfig, simulate

ABLATIONS = {
    "default (all pieces)": {},
    "no slots (all to the site)": {"use_slots": False},
    "plan without interaction (no repulsion)": {"use_repulsion": False},
    "no value-model feedback (plan feedforward only)": {"tracking.feedback": False},
    "value model frozen at w_H(0) (no HJB learning)": {"tracking.learn_hjb": False},
    "HJB learning, FPK model off (uniform phi_G weights)": {"tracking.learn_fpk": False},
    "no backstop": {"backstop.enabled": False},
    "plan without interaction and no backstop": {"use_repulsion": False, "backstop.enabled": False},
}


def variant(changes: dict):
    p = preset_by_name("default")
    for key, val in changes.items():
        if "." in key:
            a, b = key.split(".")
            p = dataclasses.replace(p, **{a: dataclasses.replace(getattr(p, a), **{b: val})})
        else:
            p = dataclasses.replace(p, **{key: val})
    return p


def run_one(job: dict) -> dict:
    preset = preset_by_name("paper") if job.get("preset") == "paper" else variant(job.get("changes", {}))
    gust = GustParams() if job.get("gust") else None
    cfg = SimConfig(scenario=make_scenario(job["scenario"], job["n"]), mode=job["mode"], preset=preset, seed=job["seed"],
                    steps=job.get("steps", 200), range_m=job.get("range_m"), fail_vehicle=job.get("fail_vehicle"),
                    fail_at_s=job.get("fail_at_s", 0.0), gust=gust)
    _, m = simulate(cfg, progress=False)
    keep = ("collision_pairs", "min_pair_distance_m", "arrived_fraction", "arrival_time_s", "final_distance_mean_m",
            "comm_states_per_uav", "motion_energy_per_uav", "backstop_activations", "failed_vehicle_collision_pairs",
            "arrived_fraction_others", "wall_s", "grad_evals_per_uav")
    return {**{k: v for k, v in job.items() if k != "changes"}, **{k: m.get(k) for k in keep}}


def _pool(jobs, workers):
    if workers <= 1:
        return [run_one(j) for j in jobs]
    with mp.get_context("fork").Pool(workers) as pool:
        return pool.map(run_one, jobs, chunksize=1)


CASES = [("paper", 9), ("paper", 25), ("paper", 49), ("paper", 81), ("crossing", 50), ("dense", 81)]


def must(seeds, workers):
    jobs = [dict(scenario=s, n=n, mode=m, seed=sd, range_m=100.0 if m == "hjb" else None)
            for s, n in CASES for sd in seeds for m in ("mfg", "hjb")]
    rows = _pool(jobs, workers)
    print("| scenario | N | seed | MFG collided pairs | MFG min dist (m) | MFG in slot | MFG arrival (s) | MFG comm/UAV | "
          "HJB_100 collided pairs | HJB_100 in slot | HJB_100 comm/UAV | energy MFG / HJB_100 |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for s, n in CASES:
        for sd in seeds:
            a = next(r for r in rows if r["scenario"] == s and r["n"] == n and r["seed"] == sd and r["mode"] == "mfg")
            b = next(r for r in rows if r["scenario"] == s and r["n"] == n and r["seed"] == sd and r["mode"] == "hjb")
            print(f"| {s} | {n} | {sd} | {a['collision_pairs']} | {a['min_pair_distance_m']:.3f} | {100 * a['arrived_fraction']:.0f} % | "
                  f"{a['arrival_time_s']} | {a['comm_states_per_uav']:.0f} | {b['collision_pairs']} | {100 * b['arrived_fraction']:.0f} % | "
                  f"{b['comm_states_per_uav']:.0f} | {a['motion_energy_per_uav'] / b['motion_energy_per_uav']:.3f} |")
    return rows


ABLATION_REFERENCES = ("HJB_100 default (reference)", "paper preset MFG (reference)")


def ablation(seeds, workers, variants=None):
    cases = [("paper", 25), ("crossing", 50), ("dense", 81)]
    names = [v for v in list(ABLATIONS) + list(ABLATION_REFERENCES) if variants is None or v in variants]
    jobs = [dict(scenario=s, n=n, mode="mfg", seed=sd, variant=name, changes=ch)
            for name, ch in ABLATIONS.items() if name in names for s, n in cases for sd in seeds]
    if ABLATION_REFERENCES[0] in names:
        jobs += [dict(scenario=s, n=n, mode="hjb", seed=sd, variant=ABLATION_REFERENCES[0], range_m=100.0)
                 for s, n in cases for sd in seeds]
    if ABLATION_REFERENCES[1] in names:
        jobs += [dict(scenario=s, n=n, mode="mfg", seed=sd, variant=ABLATION_REFERENCES[1], preset="paper")
                 for s, n in cases for sd in seeds]
    rows = _pool(jobs, workers)
    print(f"Sums / means over seeds {','.join(map(str, seeds))}. Cells: collided pairs (sum) / in slot (mean %) / "
          "min pair distance (min, m) / motion energy per UAV (mean)")
    print("| variant | " + " | ".join(f"{s} N={n}" for s, n in cases) + " |")
    print("|---|" + "---|" * len(cases))
    for name in names:
        cells = []
        for s, n in cases:
            rs = [r for r in rows if r["variant"] == name and r["scenario"] == s]
            cells.append(f"{sum(r['collision_pairs'] for r in rs)} / {100 * np.mean([r['arrived_fraction'] for r in rs]):.0f} % / "
                         f"{min(r['min_pair_distance_m'] for r in rs):.2f} / {np.mean([r['motion_energy_per_uav'] for r in rs]):.0f}")
        print(f"| {name} | " + " | ".join(cells) + " |")
    return rows


FAULTS = [
    ("paper", 25, dict(fail_vehicle=0, fail_at_s=5.0)),
    ("paper", 25, dict(fail_vehicle=12, fail_at_s=20.0)),
    ("crossing", 50, dict(fail_vehicle=22, fail_at_s=10.0)),
    ("crossing", 50, dict(fail_vehicle=37, fail_at_s=12.0)),
    ("crossing", 50, dict(fail_vehicle=27, fail_at_s=15.0)),
    ("crossing", 50, dict(fail_vehicle=12, fail_at_s=16.0)),
    ("dense", 81, dict(fail_vehicle=10, fail_at_s=15.0)),
    ("dense", 81, dict(fail_vehicle=40, fail_at_s=20.0)),
    ("paper", 25, dict(gust=True)),
    ("crossing", 50, dict(gust=True)),
    ("dense", 81, dict(gust=True)),
]


FAULT_VARIANTS = ("MFG default", "MFG default, no backstop", "HJB_100 default")


def faults(seeds, workers, variants=FAULT_VARIANTS):
    jobs = []
    for s, n, f in FAULTS:
        for sd in seeds:
            if "MFG default" in variants:
                jobs.append(dict(scenario=s, n=n, mode="mfg", seed=sd, variant="MFG default", **f))
            if "MFG default, no backstop" in variants:
                jobs.append(dict(scenario=s, n=n, mode="mfg", seed=sd, variant="MFG default, no backstop",
                                 changes={"backstop.enabled": False}, **f))
            if "HJB_100 default" in variants:
                jobs.append(dict(scenario=s, n=n, mode="hjb", seed=sd, range_m=100.0, variant="HJB_100 default", **f))
    rows = _pool(jobs, workers)
    print("| scenario | N | fault | variant | collided pairs (sum) | with failed vehicle | min dist (m) | others in slot (mean) | backstop activations |")
    print("|---|---|---|---|---|---|---|---|---|")
    for s, n, f in FAULTS:
        for v in variants:
            rs = [r for r in rows if r["scenario"] == s and r["n"] == n and r["variant"] == v
                  and all(r.get(k) == val for k, val in f.items())]
            fault = "gust" if f.get("gust") else f"vehicle {f['fail_vehicle']} holds at {f['fail_at_s']} s"
            fv = sum(r["failed_vehicle_collision_pairs"] or 0 for r in rs) if "fail_vehicle" in f else "-"
            arr = np.mean([r["arrived_fraction_others"] if r["arrived_fraction_others"] is not None else r["arrived_fraction"] for r in rs])
            print(f"| {s} | {n} | {fault} | {v} | {sum(r['collision_pairs'] for r in rs)} | {fv} | "
                  f"{min(r['min_pair_distance_m'] for r in rs):.3f} | {100 * arr:.0f} % | {sum(r['backstop_activations'] for r in rs)} |")
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("what", choices=("must", "ablation", "faults"))
    ap.add_argument("--seeds", default="0,1,2")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--json", default=None)
    ap.add_argument("--variants", default=None,
                    help="';'-separated subset of the rows: faults: " + "; ".join(FAULT_VARIANTS) +
                    "; ablation: " + "; ".join(list(ABLATIONS) + list(ABLATION_REFERENCES)))
    a = ap.parse_args(argv)
    seeds = tuple(int(s) for s in a.seeds.split(","))
    variants = None if a.variants is None else tuple(v.strip() for v in a.variants.split(";"))
    known = {"faults": FAULT_VARIANTS, "ablation": tuple(ABLATIONS) + ABLATION_REFERENCES, "must": ()}[a.what]
    if variants is not None and not set(variants) <= set(known):
        ap.error(f"--variants: unknown for {a.what}: {sorted(set(variants) - set(known))}")
    if a.what == "faults":
        rows = faults(seeds, a.workers, FAULT_VARIANTS if variants is None else variants)
    elif a.what == "ablation":
        rows = ablation(seeds, a.workers, variants)
    else:
        rows = must(seeds, a.workers)
    if a.json:
        with open(a.json, "w") as fh:
            json.dump(rows, fh, indent=1, default=float)
    return 0


if __name__ == "__main__":
    sys.exit(main())
