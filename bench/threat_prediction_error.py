"""How far off is the escape's prediction of a vehicle it escapes from? For a flight already flown, one vehicle (a
failed one, say) and a range of control steps: the distance between where the escape's two hypotheses put it and where
it was flown, at each horizon of 1 to --horizon control periods.

    .venv/bin/python bench/threat_prediction_error.py DIR --vehicle 10 --steps 41-49 [--horizon 4] [--a-max 2.0] \\
        [--hold-point tail | --hold-point X,Y]

DIR: a `mfg-swarm sim` output folder (trajectories.npz). The hypotheses (`mfg_autopilot.safety.backstop.escape_acc`):
constant velocity, r + t v; and braking to a stop along its velocity at a_max (--a-max, BackstopParams.a_max_m_s2).
The escape takes the closer of the two to the own vehicle, so what it certifies holds only as far as the flown track
stays near one of them: docs/benchmarks.md, thirty-fourth round (a failed vehicle in PX4's Hold is 0.2-0.7 m off both
1-2 s ahead while it brakes, more while the Hold flies it back).

--hold-point adds a third hypothesis, what an observer that knew the failed vehicle's Hold point could predict: PX4's
Hold itself (`mock_vehicle.smoothing.Px4AutoXY`, the model `sim` flies the failed vehicle with), activated at the step
from the sensed state and the acceleration of the last period, flown towards the Hold point through PX4's lag in a
noise-free plant with the default preset's mean wind. `tail`: the Hold point is the mean of the last 60 samples (a
failed vehicle ends the flight holding there). It is no nearer than the a_max stop (docs/benchmarks.md, thirty-fifth
round): the floor is the failed vehicle's own gust, which its position loop rejects only after it stopped.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from mock_vehicle.plant import PX4_ACC_LAG_S, WindParams, lag_coefficients
from mock_vehicle.smoothing import Px4AutoXY


def hypotheses_m(pos_m: np.ndarray, vel_m_s: np.ndarray, t_s: np.ndarray, a_max_m_s2: float) -> tuple[np.ndarray, np.ndarray]:
    """(constant velocity, braking at a_max to a stop) positions (len(t_s), 2) from one state (pos_m, vel_m_s)."""
    t = np.asarray(t_s, dtype=float)[:, None]
    v = np.asarray(vel_m_s, dtype=float)
    vn = float(np.linalg.norm(v))
    h = v / max(vn, 1e-12)
    tb = np.minimum(t, vn / a_max_m_s2)
    return pos_m + t * v, pos_m + tb * v - 0.5 * a_max_m_s2 * tb ** 2 * h


def hold_hypothesis_m(pos_m: np.ndarray, vel_m_s: np.ndarray, acc_m_s2: np.ndarray, hold_point_m: np.ndarray,
                      t_s: np.ndarray, a_max_m_s2: float = 2.0, wind: WindParams | None = None,
                      acc_lag_s: float = PX4_ACC_LAG_S, h_s: float = 0.1) -> np.ndarray:
    """PX4's Hold from one state: positions (len(t_s), 2) at t_s (multiples of h_s) of a vehicle whose Hold
    (Px4AutoXY, PX4's defaults) is activated now at (pos_m, vel_m_s) with the acceleration it flies acc_m_s2, towards
    hold_point_m, flown through a first-order lag acc_lag_s at a_max_m_s2 in eq. 9 without noise (wind: its mean
    v_o and c0; default WindParams())."""
    wind = WindParams() if wind is None else wind
    model = Px4AutoXY()
    x = np.concatenate([np.asarray(pos_m, dtype=float), np.asarray(vel_m_s, dtype=float)])
    a = np.asarray(acc_m_s2, dtype=float).copy()
    model.activate(x, np.asarray(hold_point_m, dtype=float), a)
    end, mean = lag_coefficients(h_s, acc_lag_s)
    k_of = np.rint(np.asarray(t_s, dtype=float) / h_s).astype(int)
    out = np.empty((k_of.size, 2))
    for k in range(int(k_of.max(initial=0)) + 1):
        out[k_of == k] = x[0:2]
        cmd = model.acc_m_s2(x, h_s, a_max_m_s2)
        norm = float(np.hypot(*cmd))
        cmd = cmd * (a_max_m_s2 / norm) if norm > a_max_m_s2 else cmd
        a_mean, a = a + (cmd - a) * mean, a + (cmd - a) * end
        v = x[2:4]
        x = np.concatenate([x[0:2] + v * h_s, v + (a_mean - wind.c0_per_s * (v - wind.v_o)) * h_s])
    return out


def prediction_errors(pos_m: np.ndarray, vel_m_s: np.ndarray, dt_s: float, steps: range, horizon: int,
                      a_max_m_s2: float, hold_point_m: np.ndarray | None = None) -> list[dict]:
    """Per step k: the vehicle's speed and, at t = j dt_s for j = 1..horizon (within the flight), the distance of each
    hypothesis from the flown position at step k + j. pos_m, vel_m_s: (T + 1, 2), one vehicle's track. hold_point_m
    (2,): also PX4's Hold towards it (hold_hypothesis_m, the acceleration of the period before k; "hold_m")."""
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
        if hold_point_m is not None:
            acc = (vel_m_s[k] - vel_m_s[k - 1]) / dt_s if k > 0 else np.zeros(2)
            hold = hold_hypothesis_m(pos_m[k], vel_m_s[k], acc, hold_point_m, j * dt_s, a_max_m_s2)
            out[-1]["hold_m"] = np.linalg.norm(flown - hold, axis=1).tolist()
    return out


def main(argv: list[str] | None = None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dir", type=Path)
    ap.add_argument("--vehicle", type=int, required=True)
    ap.add_argument("--steps", required=True, help="first-last control steps, e.g. 41-49")
    ap.add_argument("--horizon", type=int, default=4, help="control periods ahead (the escape looks 2 s ahead)")
    ap.add_argument("--a-max", type=float, default=2.0, help="the braking hypothesis' deceleration, m/s^2")
    ap.add_argument("--hold-point", help="also PX4's Hold towards this point: X,Y in m, or tail (the mean of the "
                                         "vehicle's last 60 samples)")
    a = ap.parse_args(argv)
    z = np.load(a.dir / "trajectories.npz")
    k0, k1 = (int(x) for x in a.steps.split("-"))
    dt = float(np.asarray(z["dt_s"]).reshape(-1)[0])
    pos, vel = z["pos_m"][:, a.vehicle], z["vel_m_s"][:, a.vehicle]
    hold = None
    if a.hold_point == "tail":
        hold = pos[-60:].mean(axis=0)
    elif a.hold_point:
        try:
            hold = np.array([float(x) for x in a.hold_point.split(",")])
            assert hold.shape == (2,) and np.all(np.isfinite(hold))
        except (ValueError, AssertionError):
            raise SystemExit(f"--hold-point takes tail or X,Y in metres, got {a.hold_point!r}") from None
    rows = prediction_errors(pos, vel, dt, range(k0, k1 + 1), a.horizon, a.a_max, hold)
    if not rows:
        raise SystemExit(f"{a.dir}: no step of {a.steps} has a later step in the flight ({z['pos_m'].shape[0]} samples)")
    where = "" if hold is None else f"; PX4's Hold towards ({hold[0]:.2f}, {hold[1]:.2f}) m"
    print(f"{a.dir}: vehicle {a.vehicle}; error of the escape's hypotheses against the flown track, m{where}")
    names = "const-vel / braking" + ("" if hold is None else " / PX4 Hold")
    print("| step | t s | speed m/s | " + " | ".join(f"{t:g} s {names}" for t in rows[0]["t_s"]) + " |")
    print("|---|---|---|" + "---|" * len(rows[0]["t_s"]))
    for r in rows:
        cols = [r["const_vel_m"], r["braking_m"]] + ([r["hold_m"]] if hold is not None else [])
        cells = " | ".join(" / ".join(f"{c:.2f}" for c in cs) for cs in zip(*cols))
        print(f"| {r['step']} | {r['step'] * dt:g} | {r['speed_m_s']:.2f} | {cells} |")
    return rows


if __name__ == "__main__":
    main()
