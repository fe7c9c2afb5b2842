"""Run outputs: metrics.json and trajectories.npz (format in docs/formats.md).

Files are written atomically (temporary file in the same folder, then os.replace),
so a reader never sees a half-written file.
"""

from __future__ import annotations

import json
import math
import os
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from . import metrics as M

__all__ = ["Trajectories", "compute_metrics", "write_json_atomic", "write_npz_atomic", "load_trajectories", "METRIC_KEYS"]

METRIC_KEYS = ("n", "mode", "range_m", "seed", "steps", "collision_pairs", "collision_pair_steps",
               "min_pair_distance_m", "min_separation_m", "closest_pair", "arrived_fraction", "arrival_time_s", "comm_states_per_uav",
               "grad_evals_per_uav", "motion_energy_per_uav", "regularizer_activations", "wall_s")


@dataclass
class Trajectories:
    """What a swarm flew. T control steps, N UAVs."""

    dt_s: float
    pos_m: np.ndarray               # (T+1, N, 2)
    vel_m_s: np.ndarray             # (T+1, N, 2)
    acc_m_s2: np.ndarray            # (T, N, 2) applied acceleration
    dest_m: np.ndarray              # (N, 2)
    comm_states: np.ndarray         # (T+1, N) states received at t_k (index 0: the t = 0 exchange)
    grad_evals: np.ndarray          # (T, N)
    mf_evals: np.ndarray            # (T, N)
    reg_active: np.ndarray          # (T, N) bool
    w_H_ref: np.ndarray | None = None   # (T+1, M_H) HJB weights of vehicle 0 (Fig. 3, right)
    extra: dict = field(default_factory=dict)

    @property
    def t_s(self) -> np.ndarray:
        return np.arange(self.pos_m.shape[0]) * self.dt_s

    def arrays(self) -> dict:
        out = dict(t_s=self.t_s, pos_m=self.pos_m, vel_m_s=self.vel_m_s, acc_m_s2=self.acc_m_s2, dest_m=self.dest_m,
                   comm_states=self.comm_states, grad_evals=self.grad_evals, mf_evals=self.mf_evals,
                   reg_active=self.reg_active, dt_s=np.array(self.dt_s))
        if self.w_H_ref is not None:
            out["w_H_ref"] = self.w_H_ref
        out.update(self.extra)
        return out


def _finite_or_none(x: float):
    return None if (x is None or not math.isfinite(x)) else float(x)


def compute_metrics(traj: Trajectories, *, n: int, mode: str, range_m: float | None, seed: int, wall_s: float, **extra) -> dict:
    """metrics.json contents (SPEC section 6 definitions) from flown trajectories."""
    col = M.collisions(traj.pos_m)
    arrived, t_arr = M.arrivals(traj.pos_m, traj.dest_m, traj.dt_s)
    energy = M.motion_energy(traj.vel_m_s, traj.acc_m_s2, traj.dt_s)
    out = {
        "n": int(n),
        "mode": mode,
        "range_m": _finite_or_none(range_m) if range_m is not None else None,
        "seed": int(seed),
        "steps": int(traj.acc_m_s2.shape[0]),
        "dt_s": float(traj.dt_s),
        "collision_pairs": col["collision_pairs"],
        "collision_pair_steps": col["collision_pair_steps"],
        "min_pair_distance_m": _finite_or_none(col["min_pair_distance_m"]),
        "min_separation_m": _finite_or_none(col["min_pair_distance_m"]),      # the same figure under issue 18's name
        "closest_pair": None if col["closest_pair"] is None else list(col["closest_pair"]),
        "arrived_fraction": float(arrived.mean()),
        "arrival_time_s": _finite_or_none(float(np.max(t_arr))) if arrived.all() else None,
        "arrival_time_mean_s": _finite_or_none(float(np.nanmean(t_arr))) if arrived.any() else None,
        "final_distance_mean_m": float(np.linalg.norm(traj.pos_m[-1] - traj.dest_m, axis=1).mean()),
        "comm_states_per_uav": float(traj.comm_states.sum(axis=0).mean()),
        "grad_evals_per_uav": float(traj.grad_evals.sum(axis=0).mean()),
        "mf_evals_per_uav": float(traj.mf_evals.sum(axis=0).mean()),
        "motion_energy_per_uav": float(energy.mean()),
        "regularizer_activations": int(traj.reg_active.sum()),
        "wall_s": float(wall_s),
        "collided_pairs_list": [list(p) for p in col["pairs"][:1000]],
    }
    out.update(extra)
    return out


def _atomic_write(path: Path, write) -> None:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            write(fh)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def write_json_atomic(path, obj) -> None:
    _atomic_write(Path(path), lambda fh: fh.write((json.dumps(obj, indent=2, sort_keys=True) + "\n").encode()))


def write_npz_atomic(path, arrays: dict) -> None:
    _atomic_write(Path(path), lambda fh: np.savez_compressed(fh, **arrays))


def load_trajectories(path) -> Trajectories:
    with np.load(path) as z:
        d = {k: z[k] for k in z.files}
    known = {"t_s", "pos_m", "vel_m_s", "acc_m_s2", "dest_m", "comm_states", "grad_evals", "mf_evals", "reg_active", "dt_s", "w_H_ref"}
    return Trajectories(dt_s=float(d["dt_s"]), pos_m=d["pos_m"], vel_m_s=d["vel_m_s"], acc_m_s2=d["acc_m_s2"],
                        dest_m=d["dest_m"], comm_states=d["comm_states"], grad_evals=d["grad_evals"],
                        mf_evals=d["mf_evals"], reg_active=d["reg_active"].astype(bool), w_H_ref=d.get("w_H_ref"),
                        extra={k: v for k, v in d.items() if k not in known})
