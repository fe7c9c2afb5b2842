"""The in-process swarm simulator: the controller core driving all N vehicles at once.

One loop per control step t_k = k dt:
1. every UAV observes its own state (rounded to float32, as MAVLink's
   LOCAL_POSITION_NED carries it, so that the simulator and a lockstep process swarm
   see the same numbers);
2. HJB_d: each UAV receives the states of the UAVs within radio range d (k-d tree);
   MFG: the N - 1 states at t = 0 only;
3. the learners (one numpy bank for all UAVs) return accelerations, rounded to
   float32 as SET_POSITION_TARGET_LOCAL_NED carries them;
4. the plant (eq. 9, each vehicle's own noise stream from (seed, id)) advances dt.
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from mfg_autopilot.controller import MODES, Neighbours, Observation, make_controller
from mfg_autopilot.params import Preset
from mock_vehicle.plant import PlantParams, SwarmPlant, WindParams

from .results import Trajectories, compute_metrics
from .scenarios import Scenario

__all__ = ["SimConfig", "simulate", "plant_params_for", "as_f32"]


def as_f32(x: np.ndarray) -> np.ndarray:
    """Round to float32 and back: what a MAVLink float field carries."""
    return np.asarray(x, dtype=np.float32).astype(np.float64)


@dataclass(frozen=True)
class SimConfig:
    scenario: Scenario
    mode: str                      # "mfg" or "hjb"
    preset: Preset
    seed: int = 0
    steps: int = 200
    range_m: float | None = None   # HJB_d radio range d
    physics_dt_s: float = 0.1
    link_float32: bool = True

    @property
    def gossips(self) -> bool:
        """HJB_d modes exchange states with neighbours in range at every step."""
        return self.mode.startswith("hjb")

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise ValueError(f"mode must be one of {', '.join(MODES)}, got {self.mode!r}")
        if self.gossips and not (self.range_m is not None and self.range_m >= 0):
            raise ValueError("HJB_d needs a radio range: give --range-m D or --power-mw P")
        if self.steps < 1:
            raise ValueError(f"steps must be >= 1, got {self.steps}")
        if self.seed < 0:
            raise ValueError(f"seed must be >= 0, got {self.seed}")


def plant_params_for(preset: Preset, physics_dt_s: float = 0.1) -> PlantParams:
    """The plant that matches the preset's model (same c0, v_o, V_o, acceleration limit)."""
    c = preset.cost
    return PlantParams(wind=WindParams(c0_per_s=c.c0_per_s, mean_wind_m_s=tuple(c.mean_wind_m_s),
                                       wind_diffusion_m_s=tuple(map(tuple, c.wind_diffusion_m_s))),
                       acc_limit_m_s2=preset.learner.acc_max_m_s2, physics_dt_s=physics_dt_s)


class _Progress:
    def __init__(self, total: int, enabled: bool) -> None:
        self.total, self.enabled, self.last = total, enabled, -1.0

    def update(self, k: int) -> None:
        if not self.enabled:
            return
        now = time.monotonic()
        if now - self.last < 0.2 and k < self.total:
            return
        self.last = now
        width = 30
        done = int(width * k / self.total)
        sys.stderr.write(f"\r  [{'#' * done}{'.' * (width - done)}] step {k}/{self.total}")
        if k >= self.total:
            sys.stderr.write("\n")
        sys.stderr.flush()


def simulate(cfg: SimConfig, progress: bool | None = None) -> tuple[Trajectories, dict]:
    """Fly the scenario; return the trajectories and metrics.json's contents."""
    t_wall = time.perf_counter()
    sc, preset = cfg.scenario, cfg.preset
    n, T, dt = sc.n, cfg.steps, preset.dt_s
    plant = SwarmPlant(sc.initial_pos_m, plant_params_for(preset, cfg.physics_dt_s), cfg.seed)
    f32 = as_f32 if cfg.link_float32 else (lambda x: np.asarray(x, dtype=float))

    pos = np.empty((T + 1, n, 2)); vel = np.empty((T + 1, n, 2)); acc_log = np.empty((T, n, 2))
    comm = np.zeros((T + 1, n), dtype=np.int64); grad = np.zeros((T, n), dtype=np.int64)
    mfe = np.zeros((T, n), dtype=np.int64); reg = np.zeros((T, n), dtype=bool)

    ctrl = make_controller(cfg.mode, preset, sc.destination_m)
    ids = np.arange(n)
    if getattr(ctrl, "uses_t0_exchange", not cfg.gossips):
        ctrl.exchange_t0(f32(plant.states), ids, ids, sc.destination_m)       # the t = 0 exchange
        comm[0] += n - 1
    sensor_range_m = getattr(ctrl, "sensor_range_m", None)
    w_ref = np.empty((T + 1, ctrl.weights()["w_H"].shape[1]))
    bar = _Progress(T, sys.stderr.isatty() if progress is None else progress)

    for k in range(T):
        obs = f32(plant.states)
        pos[k], vel[k] = plant.states[:, 0:2], plant.states[:, 2:4]
        w_ref[k] = ctrl.weights()["w_H"][0]
        heard = sensed = None
        if cfg.gossips:
            pairs = cKDTree(obs[:, 0:2]).query_pairs(cfg.range_m, output_type="ndarray") if n > 1 else np.zeros((0, 2), int)
            heard = Neighbours.from_pairs(obs, pairs)
            comm[k] += heard.counts(n)
        if sensor_range_m is not None and n > 1:
            # onboard proximity sensor: true neighbour states within its range, no communication
            sensed = Neighbours.from_pairs(obs, cKDTree(obs[:, 0:2]).query_pairs(sensor_range_m, output_type="ndarray"))
        info = ctrl.step(Observation(k, k * dt, obs, heard, sensed))
        acc_cmd = f32(info.acc_m_s2)
        acc_log[k] = plant.step(acc_cmd, dt)
        grad[k], mfe[k], reg[k] = info.grad_evals, info.mf_evals, info.reg_active
        bar.update(k + 1)
    pos[T], vel[T] = plant.states[:, 0:2], plant.states[:, 2:4]
    w_ref[T] = ctrl.weights()["w_H"][0]

    traj = Trajectories(dt_s=dt, pos_m=pos, vel_m_s=vel, acc_m_s2=acc_log, dest_m=np.asarray(ctrl.destinations_m, dtype=float).copy(),
                        comm_states=comm, grad_evals=grad, mf_evals=mfe, reg_active=reg, w_H_ref=w_ref)
    metrics = compute_metrics(traj, n=n, mode=cfg.mode, range_m=cfg.range_m if cfg.gossips else None,
                              seed=cfg.seed, wall_s=time.perf_counter() - t_wall, scenario=sc.name,
                              preset=preset.name, path="sim")
    return traj, metrics
