"""How fast a vehicle failed into Hold drifts after it first stopped: over flights already flown with a failure.

    .venv/bin/python bench/hold_drift.py DIR [DIR ...] [--stopped-m-s 0.3] [--hover-m-s 1.0]

DIR: a `mfg-swarm sim` output folder, or a folder of them (`bench/safety_sweep.py --out`). For each flight whose
metrics.json names one failed vehicle: the first step after its failure at which it is slower than --stopped-m-s, and
its largest speed from then on (its drift in Hold: in a gust beyond the modelled wind PX4's position loop fights it with
its integrator and, when the gust ends, flies back towards the Hold point). Prints the flights with the largest drift
and the distribution (median, 90th percentile, largest, how many exceed --hover-m-s: the backstop's
hover_max_speed_m_s).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np


def hold_drift(vel_m_s: np.ndarray, t_s: np.ndarray, k: int, fail_at_s: float, stopped_m_s: float):
    """(time it first stopped, largest speed from then on, time of it) of vehicle k, or None if it never stopped.
    vel_m_s (T, N, 2), t_s (T,)."""
    v = np.linalg.norm(vel_m_s[:, k], axis=-1)
    idx = np.flatnonzero((t_s > fail_at_s) & (v < stopped_m_s))
    if not idx.size:
        return None
    k0 = int(idx[0])
    j = k0 + int(np.argmax(v[k0:]))
    return float(t_s[k0]), float(v[j]), float(t_s[j])


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dirs", nargs="+", type=Path)
    ap.add_argument("--stopped-m-s", type=float, default=0.3)
    ap.add_argument("--hover-m-s", type=float, default=1.0)
    ap.add_argument("--top", type=int, default=10)
    a = ap.parse_args(argv)
    rows, never = [], []
    for d in a.dirs:
        for m in sorted(d.rglob("metrics.json")):
            meta = json.loads(m.read_text())
            k, t_fail = meta.get("fail_vehicle"), meta.get("fail_at_s")
            traj = m.with_name("trajectories.npz")
            if not isinstance(k, int) or t_fail is None or not traj.exists():
                continue
            z = np.load(traj)
            r = hold_drift(z["vel_m_s"], z["t_s"], k, float(t_fail), a.stopped_m_s)
            (never.append(m.parent.name) if r is None else rows.append((m.parent.name, meta.get("hold_model", "pd"), *r)))
    if not rows:
        print("no flight with one failed vehicle that stopped")
        return
    rows.sort(key=lambda r: -r[3])
    print("| flight | Hold | stopped at (s) | largest drift (m/s) | at (s) |")
    print("|---|---|---|---|---|")
    for name, hold, t0, vmax, tm in rows[:a.top]:
        print(f"| {name} | {hold} | {t0:.1f} | {vmax:.2f} | {tm:.1f} |")
    s = np.array([r[3] for r in rows])
    print(f"\n{len(rows)} flights ({len(never)} never stopped): drift median {np.median(s):.2f} m/s, 90th percentile "
          f"{np.quantile(s, 0.9):.2f}, largest {s.max():.2f}; above {a.hover_m_s:g} m/s: {int((s > a.hover_m_s).sum())}")


if __name__ == "__main__":
    main()
