"""Solved (finite-difference, Algorithms 1 and 2) against learned (Algorithms 3 and 4) controllers.

    .venv/bin/python bench/pde_bench.py --out DIR [--n 25] [--steps 60] [--levels 4:1,2:0.5,1:0.25]

Reports, in DIR/pde_bench.json (and on stdout):
(a) distances along flown trajectories: the learned controller flies the paper scenario
    (`mfg-swarm sim` semantics); at every recorded state the solved controller of the same
    family is evaluated. Value: learned psi_hat = w_H^T sigma_H(s) of vehicle 0 (the simulator
    logs vehicle 0's w_H) against the solved psi(s) - psi(0); control: |a_learned - a_solved|
    over all vehicles and steps. For w_H_init = "zero" (the paper) and "lqr".
(b) time per control decision, solved / learned, measured in the same replay loop (both
    controllers called alternately on the same recorded observations), per grid level, plus the
    solve times: the stationary solve (Algorithm 1 solved once; a warm-started re-solve is what
    Algorithm 1 taken literally would pay per vehicle and step) and the MFG fixed point at t = 0.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from mfg_autopilot.interface import Neighbours, Observation
from mfg_autopilot.paper.features import make_sigma_H
from mfg_autopilot.paper.params import PAPER
from mfg_autopilot.pde.control import HJBPDEController, MFGPDEController, PDEParams
from mfg_autopilot.pde.solver import solve_stationary_hjb
from mfg_autopilot.presets import make_controller
from mfg_swarm.scenarios import make_scenario
from mfg_swarm.sim import SimConfig, simulate

__all__ = ["bench_pde", "main"]


def _obs(traj, k: int, range_m: float | None) -> Observation:
    s = np.concatenate([traj.pos_m[k], traj.vel_m_s[k]], axis=1)
    nb = None
    if range_m is not None:
        pairs = cKDTree(s[:, 0:2]).query_pairs(range_m, output_type="ndarray")
        nb = Neighbours.from_pairs(s, pairs)
    return Observation(k, k * traj.dt_s, s, nb)


def _distances(traj, solved, mode: str, range_m: float | None) -> dict:
    """Value and control distances of the learned flight `traj` to the solved controller."""
    sigma_H = make_sigma_H(PAPER.learner.state_scale)
    steps = traj.acc_m_s2.shape[0]
    n = traj.pos_m.shape[1]
    if mode == "mfg-pde":
        s0 = np.concatenate([traj.pos_m[0], traj.vel_m_s[0]], axis=1)
        solved.exchange_t0(s0, np.arange(n), np.arange(n), traj.dest_m)
    psi_l, psi_s, da = [], [], []
    for k in range(steps):
        obs = _obs(traj, k, range_m)
        a_s = solved.step(obs).acc_m_s2
        da.append(np.linalg.norm(traj.acc_m_s2[k] - a_s, axis=1))
        s_rel = obs.own_states[0:1] - np.concatenate([traj.dest_m[0], np.zeros(2)])[None]
        psi_l.append(float(sigma_H.value(s_rel)[0] @ traj.w_H_ref[k]))
        psi_s.append(float(solved.value_rel(s_rel, step=k)[0]))
    psi_l, psi_s, da = np.array(psi_l), np.array(psi_s), np.array(da)
    return {
        "value_rel_rms": float(np.sqrt(np.mean((psi_l - psi_s) ** 2)) / max(np.sqrt(np.mean(psi_s ** 2)), 1e-300)),
        "value_solved_rms": float(np.sqrt(np.mean(psi_s ** 2))),
        "value_learned_rms": float(np.sqrt(np.mean(psi_l ** 2))),
        "control_mean_m_s2": float(da.mean()),
        "control_p90_m_s2": float(np.quantile(da, 0.9)),
        "control_frac_over_1_m_s2": float(np.mean(da > 1.0)),
        "final_mean_dist_m": float(np.linalg.norm(traj.pos_m[-1] - traj.dest_m, axis=1).mean()),
    }


def _timing(traj, learned, solved, mode: str, range_m: float | None) -> dict:
    """Alternate learned.step / solved.step on the same recorded observations; seconds per decision."""
    n = traj.pos_m.shape[1]
    steps = traj.acc_m_s2.shape[0]
    s0 = np.concatenate([traj.pos_m[0], traj.vel_m_s[0]], axis=1)
    t_solve = 0.0
    if mode == "mfg-pde":
        learned.exchange_t0(s0, np.arange(n), np.arange(n), traj.dest_m)
        t = time.perf_counter(); solved.exchange_t0(s0, np.arange(n), np.arange(n), traj.dest_m)
        t_solve = time.perf_counter() - t
    else:
        t = time.perf_counter(); solved.step(_obs(traj, 0, range_m)); t_solve = time.perf_counter() - t
    tl = ts = 0.0
    for k in range(steps):
        obs = _obs(traj, k, range_m)
        t = time.perf_counter(); learned.step(obs); tl += time.perf_counter() - t
        t = time.perf_counter(); solved.step(obs); ts += time.perf_counter() - t
    per_l, per_s = tl / (steps * n), ts / (steps * n)
    out = {"learned_s_per_decision": per_l, "solved_s_per_decision": per_s, "ratio_step": per_s / per_l,
           "solve_s": t_solve, "ratio_with_solve_amortised": (per_s + t_solve / (steps * n)) / per_l}
    if mode == "hjb-pde":
        # Algorithm 1 literally: every vehicle re-solves its HJB at every step (warm start from psi_L's policy)
        st = solved.stationary
        t = time.perf_counter()
        for ax in range(2):
            solve_stationary_hjb(st[ax].grid, st[ax].problem, a0=st[ax].a_m_s2)
        t_re = time.perf_counter() - t
        out["resolve_warm_s"] = t_re
        out["ratio_resolve_per_decision"] = t_re / per_l
        out["grid_nodes"] = int(sum(g.x_m.size * g.v_m_s.size for g in solved.grids))
    else:
        out["grid_nodes"] = int(sum(g.x_m.size * g.v_m_s.size for g in solved.grids))
        out["mfg_substeps_per_period"] = solved.mfg.substeps
        out["mfg_fixed_point_change"] = [float(c) for c in solved.mfg.change]
        # Algorithm 2 literally re-iterates K times per step: one t = 0 solve per vehicle and step
        out["ratio_resolve_per_decision"] = t_solve / per_l
    return out


def bench_pde(n: int = 25, steps: int = 60, seed: int = 0, range_m: float = 100.0,
              levels: tuple[tuple[float, float], ...] = ((4.0, 1.0), (2.0, 0.5), (1.0, 0.25)),
              mfg_levels: int = 2, inits: tuple[str, ...] = ("zero", "lqr"), pde_params: PDEParams | None = None,
              flights: bool = True) -> dict:
    """Run (a) and (b); returns a JSON-able dict. `levels` are (dx_m, dv_m_s) grid levels; the MFG
    is timed on the first `mfg_levels` of them (its cost grows ~8x per halving). pde_params: the
    solved controllers' grids for (a) (default PDEParams()); flights: also fly the solved modes."""
    pde_params = pde_params or PDEParams()
    sc = make_scenario("paper", n)
    out: dict = {"n": n, "steps": steps, "seed": seed, "range_m": range_m, "distances": {}, "timing": []}
    trajs = {}
    for init in inits:
        preset = replace(PAPER, learner=replace(PAPER.learner, w_H_init=init))
        for mode, pde_mode, rng in (("hjb", "hjb-pde", range_m), ("mfg", "mfg-pde", None)):
            traj, metrics = simulate(SimConfig(sc, mode, preset, seed=seed, steps=steps, range_m=rng), progress=False)
            trajs[(init, mode)] = (traj, preset)
            solved = (HJBPDEController if pde_mode == "hjb-pde" else MFGPDEController)(preset, sc.destination_m, pde_params)
            d = _distances(traj, solved, pde_mode, rng)
            d["learned_arrived_fraction"] = metrics["arrived_fraction"]
            out["distances"][f"{mode}/{init}"] = d
    # the solved controllers' own flights, for reference
    for pde_mode, rng in ((("hjb-pde", range_m), ("mfg-pde", None)) if flights else ()):
        _, metrics = simulate(SimConfig(sc, pde_mode, PAPER, seed=seed, steps=steps, range_m=rng), progress=False)
        out[f"{pde_mode}_flight"] = {k: metrics[k] for k in ("arrived_fraction", "collision_pairs", "motion_energy_per_uav")}
    # grid convergence of the solved stationary value and action of the paper's cost at probe states
    probes = np.array([[150.0, 100.0, 1.0, -1.0], [60.0, 40.0, -8.0, -5.0], [5.0, 3.0, -3.0, -2.0], [0.5, -0.5, 0.2, 0.1]])
    out["grid_convergence"] = []
    for dx, dv in levels:
        c = HJBPDEController(PAPER, np.zeros((probes.shape[0], 2)), PDEParams(dx_m=dx, dv_m_s=dv))
        s_init = np.concatenate([sc.initial_pos_m, np.tile(PAPER.cost.v_o, (n, 1))], axis=1)
        c._solve_stationary(np.concatenate([s_init, probes]))
        a = c.step(Observation(0, 0.0, probes)).acc_m_s2
        out["grid_convergence"].append({"dx_m": dx, "dv_m_s": dv, "value_rel": c.value_rel(probes).tolist(),
                                        "acc_m_s2": a.tolist(), "howard_iterations": [st.iterations for st in c.stationary]})
    for li, (dx, dv) in enumerate(levels):
        pp = PDEParams(dx_m=dx, dv_m_s=dv)
        for mode, pde_mode, rng, cls in (("hjb", "hjb-pde", range_m, HJBPDEController), ("mfg", "mfg-pde", None, MFGPDEController)):
            if pde_mode == "mfg-pde" and li >= mfg_levels:
                continue
            traj, preset = trajs[(inits[-1], mode)]
            learned = make_controller(mode, preset, sc.destination_m)
            solved = cls(preset, sc.destination_m, pp)
            row = {"mode": pde_mode, "dx_m": dx, "dv_m_s": dv}
            row.update(_timing(traj, learned, solved, pde_mode, rng))
            out["timing"].append(row)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--n", type=int, default=25)
    ap.add_argument("--steps", type=int, default=60)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--range-m", type=float, default=100.0)
    ap.add_argument("--levels", default="4:1,2:0.5,1:0.25", help="grid levels dx_m:dv_m_s, comma separated")
    ap.add_argument("--mfg-levels", type=int, default=2, help="time the MFG on the first this many levels")
    args = ap.parse_args(argv)
    levels = tuple(tuple(float(x) for x in lv.split(":")) for lv in args.levels.split(","))
    res = bench_pde(args.n, args.steps, args.seed, args.range_m, levels, args.mfg_levels)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "pde_bench.json").write_text(json.dumps(res, indent=1))
    print(json.dumps(res, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
