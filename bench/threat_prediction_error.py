"""How far off is the escape's prediction of a vehicle it escapes from? For a flight already flown, one vehicle (a
failed one, say) and a range of control steps: the distance between where the escape's two hypotheses put it and where
it was flown, at each horizon of 1 to --horizon control periods.

    .venv/bin/python bench/threat_prediction_error.py DIR --vehicle 10 --steps 41-49 [--horizon 4] [--a-max 2.0]

DIR: a `mfg-swarm sim` output folder (trajectories.npz). The hypotheses (`mfg_autopilot.safety.backstop.escape_acc`):
constant velocity, r + t v; and braking to a stop along its velocity at a_max (--a-max, BackstopParams.a_max_m_s2).
The escape takes the closer of the two to the own vehicle, so what it certifies holds only as far as the flown track
stays near one of them: docs/benchmarks.md, thirty-fourth round (a failed vehicle in PX4's Hold is 0.2-0.7 m off both
1-2 s ahead while it brakes, more while the Hold flies it back).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np


def hypotheses_m(pos_m: np.ndarray, vel_m_s: np.ndarray, t_s: np.ndarray, a_max_m_s2: float) -> tuple[np.ndarray, np.ndarray]:
    """(constant velocity, braking at a_max to a stop) positions (len(t_s), 2) from one state (pos_m, vel_m_s)."""
    t = np.asarray(t_s, dtype=float)[:, None]
    v = np.asarray(vel_m_s, dtype=float)
    vn = float(np.linalg.norm(v))
    h = v / max(vn, 1e-12)
    tb = np.minimum(t, vn / a_max_m_s2)
    return pos_m + t * v, pos_m + tb * v - 0.5 * a_max_m_s2 * tb ** 2 * h


def prediction_errors(pos_m: np.ndarray, vel_m_s: np.ndarray, dt_s: float, steps: range, horizon: int,
                      a_max_m_s2: float) -> list[dict]:
    """Per step k: the vehicle's speed and, at t = j dt_s for j = 1..horizon (within the flight), the distance of each
    hypothesis from the flown position at step k + j. pos_m, vel_m_s: (T + 1, 2), one vehicle's track."""
    out = []
    for k in steps:
        j = np.arange(1, horizon + 1)
        j = j[k + j < pos_m.shape[0]]
        if j.size == 0:
            continue
        cv, br = hypotheses_m(pos_m[k], vel_m_s[k], j * dt_s, a_max_m_s2)
        flown = pos_m[k + j]
        out.append({"step": int(k), "speed_m_s": float(np.linalg.norm(vel_m_s[k])), "t_s": (j * dt_s).tolist(),
                    "const_vel_m": np.linalg.norm(flown - cv, axis=1).tolist(),
                    "braking_m": np.linalg.norm(flown - br, axis=1).tolist()})
    return out


def main(argv: list[str] | None = None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dir", type=Path)
    ap.add_argument("--vehicle", type=int, required=True)
    ap.add_argument("--steps", required=True, help="first-last control steps, e.g. 41-49")
    ap.add_argument("--horizon", type=int, default=4, help="control periods ahead (the escape looks 2 s ahead)")
    ap.add_argument("--a-max", type=float, default=2.0, help="the braking hypothesis' deceleration, m/s^2")
    a = ap.parse_args(argv)
    z = np.load(a.dir / "trajectories.npz")
    k0, k1 = (int(x) for x in a.steps.split("-"))
    dt = float(np.asarray(z["dt_s"]).reshape(-1)[0])
    rows = prediction_errors(z["pos_m"][:, a.vehicle], z["vel_m_s"][:, a.vehicle], dt, range(k0, k1 + 1), a.horizon,
                             a.a_max)
    if not rows:
        raise SystemExit(f"{a.dir}: no step of {a.steps} has a later step in the flight ({z['pos_m'].shape[0]} samples)")
    print(f"{a.dir}: vehicle {a.vehicle}; error of the escape's hypotheses against the flown track, m")
    print("| step | t s | speed m/s | " + " | ".join(f"{t:g} s const-vel / braking" for t in rows[0]["t_s"]) + " |")
    print("|---|---|---|" + "---|" * len(rows[0]["t_s"]))
    for r in rows:
        cells = " | ".join(f"{c:.2f} / {b:.2f}" for c, b in zip(r["const_vel_m"], r["braking_m"]))
        print(f"| {r['step']} | {r['step'] * dt:g} | {r['speed_m_s']:.2f} | {cells} |")
    return rows


if __name__ == "__main__":
    main()
