"""CPU per control step of a bank of ONE default-MFG controller with sensed traffic, by backstop case.

    .venv/bin/python bench/backstop_step_bench.py [--steps 300] [--seed 0] [--scenario dense --n 81 --row 40]

Dense scenario (N = 81, 0.5 m slots, in cruise), the bank's row is vehicle 40; each step senses the
3-10 nearest other vehicles (at most N - 1; on their plan particles, +-1 cm):
  idle     nothing closer than the trigger: the backstop computes and does nothing
  planned  one planned neighbour 0.1 m off the own position: backstop_acc acts (half-plane push)
  escape   one of them off-plan (1 m ahead, closing at 2 m/s): escape_acc acts
Prints CPU time (time.process_time_ns) per step() and per _backstop call: p50 / p99 in ms.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from mfg_autopilot.interface import Neighbours, Observation
from mfg_autopilot.presets import make_controller, preset_by_name
from mfg_swarm.scenarios import make_scenario
from mfg_swarm.sim import as_f32, plant_params_for
from mock_vehicle.plant import SwarmPlant

K0 = 30


def _obs(c, k: int, case: str, rng: np.random.Generator) -> Observation:
    x = c.plan.states
    ROW = int(c.own_index[0])
    own = x[ROW:ROW + 1].copy()
    own[:, 0:2] += rng.uniform(-0.02, 0.02, 2)
    own[:, 2:4] += rng.uniform(-0.05, 0.05, 2)
    m = min(int(rng.integers(3, 11)), x.shape[0] - 1)
    d = np.linalg.norm(x[:, 0:2] - x[ROW, 0:2], axis=1)
    d[ROW] = np.inf
    ids = np.argsort(d, kind="stable")[:m]
    s = x[ids].copy()
    s[:, 0:2] += rng.uniform(-0.01, 0.01, (m, 2))
    v = x[ROW, 2:4]
    v_hat = v / max(np.linalg.norm(v), 1e-9) if np.linalg.norm(v) > 0.1 else np.array([1.0, 0.0])
    if case == "planned":
        s[0] = own[0]
        s[0, 0:2] += 0.1 * np.array([-v_hat[1], v_hat[0]])
    elif case == "escape":
        s[0, 0:2] = own[0, 0:2] + 1.0 * v_hat
        s[0, 2:4] = own[0, 2:4] - 2.0 * v_hat
    return Observation(k, k * c.preset.dt_s, own, None, Neighbours(s, np.zeros(m, dtype=np.int64), ids.astype(np.int64)))


def run(case: str, steps: int, seed: int, scenario: str = "dense", n: int = 81, row: int = 40) -> tuple[np.ndarray, np.ndarray, float]:
    preset = preset_by_name("default")
    sc = make_scenario(scenario, n)
    ROW = row
    S0 = as_f32(SwarmPlant(sc.initial_pos_m, plant_params_for(preset), seed=seed).states)
    ids = np.arange(sc.n)
    c = make_controller("mfg", preset, sc.destination_m[ROW:ROW + 1])
    c.exchange_t0(S0, ids, np.array([ROW]), sc.destination_m)
    rng = np.random.default_rng(seed)
    for _ in range(K0):
        c.plan.advance()
    inner = c._backstop
    t_bs = []

    def timed(*a):
        t0 = time.process_time_ns()
        r = inner(*a)
        t_bs.append(time.process_time_ns() - t0)
        return r

    c._backstop = timed
    t_step, act = [], 0
    for k in range(K0, K0 + steps):
        obs = _obs(c, k, case, rng)
        t0 = time.process_time_ns()
        c.step(obs)
        t_step.append(time.process_time_ns() - t0)
        act += int(c.backstop_active[0])
    return np.array(t_step) / 1e6, np.array(t_bs) / 1e6, act / steps


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--scenario", default="dense")
    ap.add_argument("--n", type=int, default=81)
    ap.add_argument("--row", type=int, default=40)
    args = ap.parse_args()
    where = (args.scenario, args.n, args.row)
    for case in ("idle", "planned", "escape"):
        run(case, 20, args.seed + 1, *where)                      # warm caches
        ts, tb, frac = run(case, args.steps, args.seed, *where)
        print(f"{case:8s} active {frac:5.0%}  step p50 {np.percentile(ts, 50):6.3f} p99 {np.percentile(ts, 99):6.3f} ms"
              f"   _backstop p50 {np.percentile(tb, 50):6.3f} p99 {np.percentile(tb, 99):6.3f} ms")


if __name__ == "__main__":
    main()
