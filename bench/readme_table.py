"""The README's issue-18 table from one or more ``bench/safety_sweep.py`` results.

    .venv/bin/python bench/readme_table.py DIR1/safety_sweep.json [DIR2/safety_sweep.json ...] [--seed 1]

One row per (family, N), one column per mode (MFG default, HJB_100, ORCA); a later file's point replaces an
earlier one's for the same (family, N, mode, seed). Each cell: collided pairs / smallest separation / arrived (MFG,
HJB: in the slot; ORCA, which has no slots: in its group's slot area) (time of the last arrival, when all arrived)
/ motion energy per UAV / states received per UAV / simulator wall time. A point not in any file is "not run".
Nothing is computed here beyond formatting what the sweep measured.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

FAMILIES = ("paper", "dense", "crossing", "swap4", "circle", "merge", "random")
MODES = ("mfg", "hjb", "orca")


def _g(x: float, digits: int = 2) -> str:
    return f"{x:.{digits}g}"


def cell(p: dict) -> str:
    if p.get("error"):
        return f"error: {p['error']}"
    arrived = p["arrived_area_fraction"] if p["mode"] == "orca" else p["arrived_fraction"]
    when = f" ({_g(p['arrival_time_s'], 3)} s)" if p.get("arrival_time_s") is not None and arrived == 1.0 else ""
    comm = p["comm_states_per_uav"]
    comm_s = f"{comm:.0f}" if comm < 1e4 else f"{comm:.3g}"
    return (f"{p['collision_pairs']} / {_g(p['min_separation_m'])} m / {100 * arrived:.0f} %{when} / "
            f"{p['motion_energy_per_uav']:.0f} / {comm_s} / {p['wall_s']:.0f} s")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("files", nargs="+", type=Path)
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args(argv)
    points: dict[tuple, dict] = {}
    for f in args.files:
        for p in json.loads(f.read_text()):
            points[(p["family"], p["n"], p["mode"], p["seed"])] = p
    sizes = sorted({k[1] for k in points})
    print("| family | N | MFG default | HJB_100 | ORCA |")
    print("|---|---|---|---|---|")
    for fam in FAMILIES:
        for n in sizes:
            row = [points.get((fam, n, m, args.seed)) for m in MODES]
            if not any(row):
                continue
            cells = [cell(p) if p else "not run" for p in row]
            print(f"| `{fam}` | {n:,} | " + " | ".join(cells) + " |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
