"""How much a healthy UAV's acceleration jitters in calm cruise, and why the braking test must subtract it.

    .venv/bin/python bench/tracking_jitter.py [--families circle,paper,swap4] [--n 1000] [--seed 83] [--steps 300]
                                              [--loop-only]

Prints the gains of eq. 8's tracking feedback at the start weights (the LQ value model, TrackingParams' cost): the
acceleration per metre of position error and per m/s of velocity error, and the velocity loop's gain over one
control period (kv dt; above 1 a velocity error comes back with the opposite sign a period later). Then, per calm
flight (MFG default, no fault): the spread of every UAV's along-track acceleration in cruise (its velocity change
over a control period / dt, along its previous velocity, while it and the sample before and after fly 3.4-4.6 m/s;
the plan's particles cruise at a constant 4 m/s there), the share of samples below -0.9 and -0.6 m/s^2, the spread
of the command alone and the wind's (V_o sqrt(dt) / dt per axis). Then the held loop per axis, linear, wind only
(``held_loop``): eq. 8's gains held over the period on eq. 9 with drag c0 (zero-order hold), its closed-loop
eigenvalues, and the command and tracking-error spread it makes of the wind, next to the discrete-time LQ design of
the same weights (Q dt, R dt: the held command's Riccati equation) - the alternative the sixteenth session proposed.
Last, each flight again with the braking test not
subtracting the neighbour's own tracking (BackstopParams.plan_mismatch_brake_expected False, 0.9 m/s^2: the
fifteenth session's test): smallest separation and backstop interventions, both ways.
"""

from __future__ import annotations

import argparse
from dataclasses import replace

import numpy as np


def along_track_stats(vel_m_s: np.ndarray, acc_m_s2: np.ndarray, dt_s: float) -> dict:
    """vel (T + 1, N, 2), applied acc (T, N, 2): the cruise samples' along-track acceleration (velocity change / dt)
    and command, as described in the module docstring."""
    sp = np.linalg.norm(vel_m_s, axis=2)
    k = np.arange(2, vel_m_s.shape[0] - 1)
    dv = (vel_m_s[k] - vel_m_s[k - 1]) / dt_s
    vh = vel_m_s[k - 1] / np.maximum(sp[k - 1], 1e-9)[..., None]
    along = np.sum(dv * vh, axis=2)
    cmd = np.sum(acc_m_s2[k - 1] * vh, axis=2)
    cruise = (np.abs(sp[k - 1] - 4.0) < 0.6) & (np.abs(sp[k - 2] - 4.0) < 0.6) & (np.abs(sp[k + 1] - 4.0) < 0.6)
    x, c = along[cruise], cmd[cruise]
    x = x - x.mean()
    return {"samples": int(x.size), "rms": float(x.std()), "below_0.9": float(np.mean(x < -0.9)),
            "below_0.6": float(np.mean(x < -0.6)), "command_rms": float(c.std())}


def held_loop(kp: float, kv: float, c0_per_s: float, dt_s: float, wind_m_s_sqrt_s: float, steps: int,
              rng: np.random.Generator, lag_s: float = 0.0) -> dict:
    """One axis of the tracking error (position, velocity) under eq. 9 with drag c0 and the command a = -kp e_r - kv e_v
    held for dt (zero-order hold, exact), the wind a velocity kick N(0, (V_o sqrt(dt))^2) per period. ``lag_s`` > 0:
    the airframe flies the command through a first-order lag (``PlantParams.acc_lag_s``; the acceleration flown is a
    third state, exact over the period). Returns the closed-loop eigenvalues, their largest magnitude, and over
    ``steps`` periods the rms of the command, of the position and velocity errors, and the command's correlation with
    itself a period later (< 0: it alternates)."""
    from scipy.linalg import expm

    if lag_s > 0.0:       # [e_r, e_v, a_flown]' = [[0 1 0] [0 -c0 1] [0 0 -1/tau]] x + [0 0 1/tau]' u
        m = np.zeros((4, 4))
        m[0, 1], m[1, 1], m[1, 2], m[2, 2], m[2, 3] = 1.0, -c0_per_s, 1.0, -1.0 / lag_s, 1.0 / lag_s
        e = expm(m * dt_s)
        ad, bd = e[:3, :3], e[:3, 3]
        k = np.array([kp, kv, 0.0])
    else:
        m = np.zeros((3, 3))
        m[0, 1], m[1, 1], m[1, 2] = 1.0, -c0_per_s, 1.0
        e = expm(m * dt_s)
        ad, bd = e[:2, :2], e[:2, 2]
        k = np.array([kp, kv])
    eig = np.linalg.eigvals(ad - np.outer(bd, k))
    x, xs, us = np.zeros(k.size), np.empty((steps, k.size)), np.empty(steps)
    kick = rng.normal(0.0, wind_m_s_sqrt_s * np.sqrt(dt_s), steps)
    for t in range(steps):
        u = -float(k @ x)
        xs[t], us[t] = x, u
        x = ad @ x + bd * u
        x[1] += kick[t]
    return {"eig": eig, "radius": float(np.max(np.abs(eig))), "cmd_rms": float(us.std()), "pos_rms": float(xs[:, 0].std()),
            "vel_rms": float(xs[:, 1].std()), "cmd_lag1": float(np.corrcoef(us[1:], us[:-1])[0, 1])}


def discrete_lq_gains(c1: float, c2: float, c3: float, c0_per_s: float, dt_s: float) -> tuple[float, float]:
    """(kp, kv) of the discrete-time LQ design for the held command: the discrete Riccati equation of one axis of eq. 9
    (zero-order hold) with the per-period weights Q = diag(c1, c2) dt, R = c3 dt."""
    from scipy.linalg import expm, solve_discrete_are

    m = np.zeros((3, 3))
    m[0, 1], m[1, 1], m[1, 2] = 1.0, -c0_per_s, 1.0
    e = expm(m * dt_s)
    ad, bd = e[:2, :2], e[:2, 2:]
    q, r = np.diag([c1, c2]) * dt_s, np.array([[c3 * dt_s]])
    P = solve_discrete_are(ad, bd, q, r)
    k = np.linalg.solve(r + bd.T @ P @ bd, bd.T @ P @ ad)[0]
    return float(k[0]), float(k[1])


def riccati_gains(c1_track: float, cost) -> tuple[float, float]:
    """(kp, kv) of eq. 8 at the start weights for a tracking cost with ``c1_track`` (TrackingParams.c1_track) and
    the preset's c0, c2, c3: the continuous Riccati gains [0 1] P / c3 (``lqr_riccati_axis``)."""
    from mfg_autopilot.paper.model import lqr_riccati_axis

    P = lqr_riccati_axis(replace(cost, c1=c1_track))
    return float(P[1, 0] / cost.c3), float(P[1, 1] / cost.c3)


LAGS_S = (0.0, 0.05, 0.1, 0.154, 0.2, 0.25, 0.3)


def lag_table(p, c1_values=(24.0, 12.0, 6.0, 3.0, 1.5), lags_s=LAGS_S, periods: int = 200_000) -> list[dict]:
    """The held loop against an airframe lag: per c1_track, its gains and per lag the largest closed-loop eigenvalue
    magnitude (> 1: the tracking error grows) and the position error rms the wind alone makes of it (seed 0)."""
    wind = float(np.max(np.abs(np.diag(p.cost.V_o))))
    rows = []
    for c1 in c1_values:
        kp, kv = riccati_gains(c1, p.tracking_cost)
        cells = []
        for lag in lags_s:
            first = held_loop(kp, kv, p.cost.c0_per_s, p.dt_s, wind, 10, np.random.default_rng(0), lag_s=lag)
            cells.append(first if first["radius"] >= 1.0 else       # unstable: no spread to measure
                         held_loop(kp, kv, p.cost.c0_per_s, p.dt_s, wind, periods, np.random.default_rng(0), lag_s=lag))
        rows.append({"c1_track": c1, "kp": kp, "kv": kv, "radius": [c["radius"] for c in cells],
                     "pos_rms": [c["pos_rms"] if c["radius"] < 1.0 else float("inf") for c in cells]})
    return rows


def main(argv=None) -> None:
    from mfg_autopilot.paper.features import make_sigma_H
    from mfg_autopilot.paper.model import lqr_value_weights, optimal_action
    from mfg_autopilot.presets import preset_by_name
    from mfg_swarm.scenarios import make_scenario
    from mfg_swarm.sim import SimConfig, simulate

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--families", default="circle,paper,swap4")
    ap.add_argument("--n", type=int, default=1000)
    ap.add_argument("--seed", type=int, default=83)
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--loop-only", action="store_true", help="print the gains and the held loop only (no flights)")
    ap.add_argument("--lag", action="store_true",
                    help="print the held loop against the airframe's acceleration lag only (PlantParams.acc_lag_s)")
    a = ap.parse_args(argv)
    if a.lag:
        p = preset_by_name("default")
        print(f"the held loop against an acceleration lag tau (one axis, linear; dt = {p.dt_s:g} s, c0 = "
              f"{p.cost.c0_per_s:g} /s; PX4's attitude loop: tau ~ 1 / MC_ROLL_P = 0.154 s). Each cell: the largest "
              f"closed-loop eigenvalue magnitude (the error's factor per period; >= 1 unstable), then the position "
              f"error rms the wind alone makes (200,000 periods, seed 0)\n")
        print("| c1_track | kp (/s^2) | kv (/s) | " + " | ".join(f"tau = {t:g} s" for t in LAGS_S) + " |")
        print("|---" * (3 + len(LAGS_S)) + "|")
        for r in lag_table(p):
            cells = " | ".join(f"{rad:.3f}, " + ("unstable" if not np.isfinite(e) else f"{100 * e:.1f} cm")
                               for rad, e in zip(r["radius"], r["pos_rms"]))
            mark = " (the default)" if r["c1_track"] == p.tracking.c1_track else ""
            print(f"| {r['c1_track']:g}{mark} | {r['kp']:.2f} | {r['kv']:.2f} | {cells} |")
        return
    p = preset_by_name("default")
    sigma_H = make_sigma_H(p.learner.state_scale)
    w = lqr_value_weights(sigma_H, p.tracking_cost)[None, :]
    kp = -optimal_action(sigma_H.grad_psi(np.array([[0.1, 0.0, 0.0, 0.0]]), w), p.cost.c3)[0, 0] / 0.1
    kv = -optimal_action(sigma_H.grad_psi(np.array([[0.0, 0.0, 0.1, 0.0]]), w), p.cost.c3)[0, 0] / 0.1
    print(f"eq. 8 at the start weights: {kp:.2f} m/s^2 per m of position error, {kv:.2f} m/s^2 per m/s of velocity "
          f"error; over the {p.dt_s:g} s period kv dt = {kv * p.dt_s:.2f}")
    wind = float(np.max(np.abs(np.diag(p.cost.V_o))))
    print(f"the wind alone: {wind * np.sqrt(p.dt_s) / p.dt_s:.3f} m/s^2 rms per axis (V_o sqrt(dt) / dt)\n")
    tc, c0 = p.tracking_cost, p.cost.c0_per_s
    print("the held loop, one axis, wind only (200,000 periods, seed 0):\n")
    print("| gains | kp (/s^2) | kv (/s) | closed-loop eigenvalues | largest magnitude | command rms (m/s^2) | "
          "position error rms (m) | velocity error rms (m/s) | command's lag-1 correlation |")
    print("|---|---|---|---|---|---|---|---|---|")
    for name, (gp, gv) in (("eq. 8 at the start weights (continuous Riccati)", (kp, kv)),
                           ("discrete LQ, the same weights", discrete_lq_gains(tc.c1, tc.c2, tc.c3, c0, p.dt_s))):
        r = held_loop(gp, gv, c0, p.dt_s, wind, 200_000, np.random.default_rng(0))
        ev = ", ".join(f"{z.real:.3f}{z.imag:+.3f}j" for z in r["eig"])
        print(f"| {name} | {gp:.2f} | {gv:.2f} | {ev} | {r['radius']:.3f} | {r['cmd_rms']:.3f} | {r['pos_rms']:.4f} | "
              f"{r['vel_rms']:.4f} | {r['cmd_lag1']:+.2f} |")
    print()
    if a.loop_only:
        return
    print("| family | N | seed | cruise samples | along-track acc rms (m/s^2) | below -0.9 | below -0.6 | command rms | "
          "with the tracking subtracted: min sep (m), interventions | without (0.9 m/s^2): min sep (m), interventions |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    old = replace(p, backstop=replace(p.backstop, plan_mismatch_brake_expected=False, plan_mismatch_brake_m_s2=0.9))
    for fam in a.families.split(","):
        sc = make_scenario(fam, a.n, a.seed)
        tr, m = simulate(SimConfig(scenario=sc, mode="mfg", preset=p, seed=a.seed, steps=a.steps), progress=False)
        _, m_old = simulate(SimConfig(scenario=sc, mode="mfg", preset=old, seed=a.seed, steps=a.steps), progress=False)
        s = along_track_stats(tr.vel_m_s, tr.acc_m_s2, tr.dt_s)
        print(f"| {fam} | {a.n} | {a.seed} | {s['samples']} | {s['rms']:.3f} | {s['below_0.9']:.2e} | {s['below_0.6']:.2e} | "
              f"{s['command_rms']:.3f} | {m['min_separation_m']:.3f}, {m['safety_interventions']} | "
              f"{m_old['min_separation_m']:.3f}, {m_old['safety_interventions']} |")


if __name__ == "__main__":
    main()
