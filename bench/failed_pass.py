"""How close the other UAVs pass a vehicle that failed, read from flights already flown (the figures of
docs/default_controller.md "Where it does not hold yet", twelfth session, and the README's detour line).

    .venv/bin/python bench/failed_pass.py DIR [DIR ...] [--after-s 5]

DIR: a `mfg-swarm sim --fail-vehicle K --fail-at T` output folder, or a folder of them (`bench/safety_sweep.py --out`).
For each flight: the smallest distance of any other UAV to vehicle K along the step segments
(mfg_swarm.metrics.segment_min_distance) from its failure on ("from the failure") and from --after-s seconds after it
("after the onset": the failed vehicle has stopped and hovers, the lanes near it are deflected), with the UAV and step.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from mfg_swarm.metrics import segment_min_distance


def closest_pass(pos_m: np.ndarray, K: int, k0: int) -> tuple[float, int, int]:
    """(distance, UAV, step): the closest approach of any vehicle but K to K over the step segments from step k0 on."""
    d = np.delete(pos_m - pos_m[:, K:K + 1], K, axis=1)[k0:]
    if d.shape[0] < 2:
        return float("nan"), -1, -1
    seg = segment_min_distance(d[:-1].reshape(-1, 2), d[1:].reshape(-1, 2)).reshape(d.shape[0] - 1, d.shape[1])
    k, j = np.unravel_index(int(np.argmin(seg)), seg.shape)
    return float(seg[k, j]), int(j + (j >= K)), int(k + k0)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dirs", nargs="+", type=Path)
    ap.add_argument("--after-s", type=float, default=5.0, help="'after the onset': this long after the failure")
    a = ap.parse_args(argv)
    runs = []
    for d in a.dirs:
        runs += [d] if (d / "metrics.json").exists() else sorted(p.parent for p in d.glob("*/metrics.json"))
    print("| flight | from the failure (m, UAV, step) | after the onset (m, UAV, step) |")
    print("|---|---|---|")
    for r in runs:
        m = json.loads((r / "metrics.json").read_text())
        if m.get("fail_vehicle") is None:
            continue
        z = np.load(r / "trajectories.npz")
        dt = float(z["dt_s"])
        ks, ts = np.atleast_1d(m["fail_vehicle"]), np.atleast_1d(m["fail_at_s"])
        ts = np.broadcast_to(ts, ks.shape)
        for K, t_fail in zip(ks, ts):           # several failed vehicles: a line each
            k_fail = int(np.ceil(t_fail / dt - 1e-9))
            k_on = int(np.ceil((t_fail + a.after_s) / dt - 1e-9))
            f, on = closest_pass(z["pos_m"], int(K), k_fail), closest_pass(z["pos_m"], int(K), k_on)
            name = r.name if ks.size == 1 else f"{r.name}, vehicle {int(K)}"
            print(f"| {name} | {f[0]:.3f}, {f[1]}, {f[2]} | {on[0]:.3f}, {on[1]}, {on[2]} |")


if __name__ == "__main__":
    main()
