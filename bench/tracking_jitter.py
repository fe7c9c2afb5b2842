"""How much a healthy UAV's acceleration jitters in calm cruise, and why the braking test must subtract it.

    .venv/bin/python bench/tracking_jitter.py [--families circle,paper,swap4] [--n 1000] [--seed 83] [--steps 300]

Prints the gains of eq. 8's tracking feedback at the start weights (the LQ value model, TrackingParams' cost): the
acceleration per metre of position error and per m/s of velocity error, and the velocity loop's gain over one
control period (kv dt; above 1 a velocity error comes back with the opposite sign a period later). Then, per calm
flight (MFG default, no fault): the spread of every UAV's along-track acceleration in cruise (its velocity change
over a control period / dt, along its previous velocity, while it and the sample before and after fly 3.4-4.6 m/s;
the plan's particles cruise at a constant 4 m/s there), the share of samples below -0.9 and -0.6 m/s^2, the spread
of the command alone and the wind's (V_o sqrt(dt) / dt per axis). Last, each flight again with the braking test not
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
    a = ap.parse_args(argv)
    p = preset_by_name("default")
    sigma_H = make_sigma_H(p.learner.state_scale)
    w = lqr_value_weights(sigma_H, p.tracking_cost)[None, :]
    kp = -optimal_action(sigma_H.grad_psi(np.array([[0.1, 0.0, 0.0, 0.0]]), w), p.cost.c3)[0, 0] / 0.1
    kv = -optimal_action(sigma_H.grad_psi(np.array([[0.0, 0.0, 0.1, 0.0]]), w), p.cost.c3)[0, 0] / 0.1
    print(f"eq. 8 at the start weights: {kp:.2f} m/s^2 per m of position error, {kv:.2f} m/s^2 per m/s of velocity "
          f"error; over the {p.dt_s:g} s period kv dt = {kv * p.dt_s:.2f}")
    wind = float(np.max(np.abs(np.diag(p.cost.V_o))))
    print(f"the wind alone: {wind * np.sqrt(p.dt_s) / p.dt_s:.3f} m/s^2 rms per axis (V_o sqrt(dt) / dt)\n")
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
