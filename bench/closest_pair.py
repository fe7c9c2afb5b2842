"""The closest pair of flights already flown, step by step around its closest approach: where a trace of the
controller starts (docs/default_controller.md "Where it does not hold yet" traces pairs this way).

    .venv/bin/python bench/closest_pair.py DIR [DIR ...] [--before 6] [--after 2]

DIR: a `mfg-swarm sim` output folder, or a folder of them (`bench/safety_sweep.py --out`). For each flight, the pair
and step of metrics.json's `closest_pair` (the smallest distance along the step segments), then one line per control
step from --before steps before it to --after after: the distance at the step, the closing speed (-d|r|/dt, positive
when closing), each UAV's speed, commanded acceleration (norm, and its component towards the other: positive when it
accelerates into the other) and whether the backstop acted on it: the safety layers that made its command
(`backstop_layer`, `mfg_autopilot.safety.backstop.Layer`; `-` for none) where the flight recorded them, else
`backstop_active` as 1 / 0.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from mfg_autopilot.safety.layers import layer_names


def pair_rows(pos_m: np.ndarray, vel_m_s: np.ndarray, acc_m_s2: np.ndarray, active: np.ndarray | None, i: int, j: int,
              k0: int, k1: int, layer: np.ndarray | None = None) -> list[dict]:
    """One dict per step k in [k0, k1] (clipped to the flight): distance, closing speed, and per UAV i / j its speed,
    commanded acceleration norm, its component towards the other, the backstop flag and its layers' names (None where
    not recorded; layer: the (T, N) Layer bits)."""
    out = []
    T = pos_m.shape[0] - 1
    for k in range(max(0, k0), min(T, k1) + 1):
        d = pos_m[k, j] - pos_m[k, i]
        dist = float(np.linalg.norm(d))
        n = d / max(dist, 1e-12)
        u = vel_m_s[k, j] - vel_m_s[k, i]
        row = {"step": k, "dist_m": dist, "closing_m_s": float(-(u @ n))}
        for name, a, sgn in (("i", i, 1.0), ("j", j, -1.0)):
            acc = acc_m_s2[k, a] if k < acc_m_s2.shape[0] else np.full(2, np.nan)
            row[f"speed_{name}_m_s"] = float(np.linalg.norm(vel_m_s[k, a]))
            row[f"acc_{name}_m_s2"] = float(np.linalg.norm(acc))
            row[f"acc_{name}_towards_m_s2"] = float(sgn * (acc @ n))
            row[f"backstop_{name}"] = None if active is None or k >= active.shape[0] else bool(active[k, a])
            row[f"layer_{name}"] = None if layer is None or k >= layer.shape[0] else layer_names(layer[k, a])
        out.append(row)
    return out


def report(run: Path, before: int, after: int) -> str:
    m = json.loads((run / "metrics.json").read_text())
    cp = m.get("closest_pair")
    if not cp:
        return f"{run}: no closest pair recorded (fewer than two UAVs?)"
    i, j, k = (int(x) for x in cp)
    z = np.load(run / "trajectories.npz")
    active = z["backstop_active"] if "backstop_active" in z.files else None
    layer = z["backstop_layer"] if "backstop_layer" in z.files else None
    dt = float(m.get("dt_s") or z["dt_s"])
    lines = [f"{run}: UAVs {i} and {j}, {m['min_pair_distance_m']:.3f} m on the segment from step {k} (t = {k * dt:g} s); "
             f"{m.get('collision_pairs')} collided pairs, start spacing {m.get('start_spacing_m')} m",
             "| step | t s | dist m | closing m/s | speed i / j m/s | acc i / j m/s^2 | towards i / j m/s^2 | backstop i / j |",
             "|---|---|---|---|---|---|---|---|"]
    for r in pair_rows(z["pos_m"], z["vel_m_s"], z["acc_m_s2"], active, i, j, k - before, k + after, layer):
        if r["layer_i"] is not None:
            b = f"{r['layer_i']} / {r['layer_j']}"
        else:
            b = "-" if r["backstop_i"] is None else f"{int(r['backstop_i'])} / {int(r['backstop_j'])}"
        lines.append(f"| {r['step']} | {r['step'] * dt:g} | {r['dist_m']:.3f} | {r['closing_m_s']:+.2f} | "
                     f"{r['speed_i_m_s']:.2f} / {r['speed_j_m_s']:.2f} | {r['acc_i_m_s2']:.2f} / {r['acc_j_m_s2']:.2f} | "
                     f"{r['acc_i_towards_m_s2']:+.2f} / {r['acc_j_towards_m_s2']:+.2f} | {b} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dirs", nargs="+", type=Path)
    ap.add_argument("--before", type=int, default=6, help="control steps before the closest approach")
    ap.add_argument("--after", type=int, default=2, help="control steps after it")
    a = ap.parse_args(argv)
    runs = []
    for d in a.dirs:
        runs += [d] if (d / "metrics.json").exists() else sorted(p.parent for p in d.glob("*/metrics.json"))
    if not runs:
        ap.error("no metrics.json under the folders given")
    print("\n\n".join(report(r, a.before, a.after) for r in runs))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
