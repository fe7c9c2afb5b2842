"""Mission metrics (paper Sec. V, SPEC section 6), computed from flown trajectories.

All functions are pure. Trajectories: positions pos_m (T+1, N, 2) at the control
instants t_k = k dt, velocities vel_m_s (T+1, N, 2), applied accelerations
acc_m_s2 (T, N, 2) held over [t_k, t_k+1).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from .spatial import GRID_MIN_N, pairs_within_reach

__all__ = ["COLLISION_DISTANCE_M", "ARRIVAL_TOLERANCE_M", "segment_min_distance", "collisions", "arrivals", "motion_energy",
           "separation_guarantee"]

COLLISION_DISTANCE_M = 0.1
ARRIVAL_TOLERANCE_M = 1.0


def segment_min_distance(d0: np.ndarray, d1: np.ndarray) -> np.ndarray:
    """Closest approach of pairs whose relative position moves linearly from d0 to d1
    (rows (p, 2)) over one step: min over tau in [0, 1] of |d0 + tau (d1 - d0)|. (p,)."""
    dd = d1 - d0
    den = np.einsum("pd,pd->p", dd, dd)
    tau = np.where(den > 0, -np.einsum("pd,pd->p", d0, dd) / np.maximum(den, 1e-300), 0.0)
    tau = np.clip(tau, 0.0, 1.0)
    closest = d0 + tau[:, None] * dd
    return np.linalg.norm(closest, axis=1)


def collisions(pos_m: np.ndarray, radius_m: float = COLLISION_DISTANCE_M) -> dict:
    """Collisions checked along each step's straight position segment (SPEC 6).

    Returns {"collision_pairs": distinct pairs ever closer than radius,
    "collision_pair_steps": (pair, step) count, "min_pair_distance_m": the smallest
    distance between any two UAVs over all segments, "closest_pair": (i, j, step) where it is
    attained (step k: the segment from t_k to t_k+1), "pairs": sorted list of (i, j)}.
    Candidates per step: a pair can come within b during a step only if it starts within
    b + |delta_j - delta_i| <= b + e_i + e_j, delta_k the step's displacement of UAV k and
    e_k = |delta_k - c| (c: the median displacement) - a swarm flying together has small e_k
    (spatial.pairs_within_reach), and of those only the pairs whose segments come within b (the reach's
    closest-approach test, the displacements as velocities over tau in [0, 1]). One search per step with b = max(radius, the smallest distance
    found so far) (at the first step: the nearest start distance, which some pair attains): every
    pair within the radius is a candidate, and a step whose smallest distance beats the smallest
    so far has its closest pair among the candidates, so min_pair_distance_m is exact too.
    """
    T1, N, _ = pos_m.shape
    if N < 2:
        return {"collision_pairs": 0, "collision_pair_steps": 0, "min_pair_distance_m": float("inf"), "closest_pair": None,
                "pairs": []}
    pairs_hit: set[tuple[int, int]] = set()
    pair_steps = 0
    nn, nn_idx = cKDTree(pos_m[0]).query(pos_m[0], k=2)
    dmin = float(np.min(nn[:, 1]))          # attained at t = 0 (that pair is a candidate of the first step)
    i0 = int(np.argmin(nn[:, 1]))
    closest = (min(i0, int(nn_idx[i0, 1])), max(i0, int(nn_idx[i0, 1])), 0)
    for k in range(max(T1 - 1, 1)):
        p0 = pos_m[k]
        p1 = pos_m[k + 1] if T1 > 1 else p0
        delta = p1 - p0
        extra = np.linalg.norm(delta - np.median(delta, axis=0)[None, :], axis=1)
        tree = cKDTree(p0) if N < GRID_MIN_N else None       # the grid kernel of larger swarms needs none
        # the reach's closest-approach test over tau in [0, 1] with the displacements as velocities is the segment
        # test itself: only the pairs that come within b during the step are candidates (swap4 N = 10,000: four
        # streams make e_k ~2 m, and the distance test alone passed ~40 pairs per vehicle per step)
        cand = pairs_within_reach(tree, p0, (max(radius_m, dmin) + 1e-9, extra, 1.0), np.inf, vel=delta)
        if cand.size == 0:
            continue
        dseg = segment_min_distance(p0[cand[:, 1]] - p0[cand[:, 0]], p1[cand[:, 1]] - p1[cand[:, 0]])
        m = int(np.argmin(dseg))
        if dseg[m] < dmin:
            dmin = float(dseg[m])
            a, b = int(cand[m, 0]), int(cand[m, 1])
            closest = (min(a, b), max(a, b), k)
        hit = dseg < radius_m
        if np.any(hit):
            pair_steps += int(hit.sum())
            pairs_hit.update(map(tuple, np.sort(cand[hit], axis=1).tolist()))
    return {"collision_pairs": len(pairs_hit), "collision_pair_steps": pair_steps,
            "min_pair_distance_m": dmin, "closest_pair": closest, "pairs": sorted(pairs_hit)}


def separation_guarantee(pos_m: np.ndarray, plan_pos_m: np.ndarray, tracking: np.ndarray | None = None,
                         min_separation_m: float | None = None) -> dict:
    """The plan-tracking guarantee of docs/default_controller.md ("The statement"), evaluated on one flight.

    pos_m, plan_pos_m: (T+1, N, 2) each UAV's position and its own plan particle's at the control instants;
    tracking: (T+1, N) bool, the (step, UAV) samples that fly the plan (default: all; a UAV that failed and went to
    Hold is not tracking from its failure on, and its pairs are the backstop's). Among the UAVs tracking throughout,
    along each step's straight segments (as ``collisions``): if every UAV stays within e of its particle, the
    triangle inequality gives |r_i - r_j| >= |p_i - p_j| - 2 e at every point of every segment (the interpolated
    error is at most the larger of its two ends), so

        min_separation >= plan_min_separation - 2 e_max.

    Returns {"plan_min_separation_m": the particles' smallest distance along the segments,
    "tracking_error_max_m": e_max, "separation_bound_m": plan_min_separation - 2 e_max (negative: no guarantee),
    "min_separation_m": the UAVs' smallest distance, the same set, "uavs": how many tracked throughout}.
    ``min_separation_m``: the whole swarm's, if already known (``collisions(pos_m)``): used when every UAV tracked."""
    pos = np.asarray(pos_m, dtype=float)
    plan = np.asarray(plan_pos_m, dtype=float)
    if pos.shape != plan.shape or pos.ndim != 3 or pos.shape[2] != 2:
        raise ValueError(f"pos_m and plan_pos_m must both be (T+1, N, 2), got {pos.shape} and {plan.shape}")
    keep = np.ones(pos.shape[1], dtype=bool) if tracking is None else np.all(np.asarray(tracking, dtype=bool), axis=0)
    pos, plan = pos[:, keep], plan[:, keep]
    e_max = float(np.max(np.linalg.norm(pos - plan, axis=2))) if pos.size else 0.0
    plan_min = collisions(plan)["min_pair_distance_m"]
    flown = min_separation_m if (min_separation_m is not None and keep.all()) else collisions(pos)["min_pair_distance_m"]
    return {"plan_min_separation_m": float(plan_min), "tracking_error_max_m": e_max,
            "separation_bound_m": float(plan_min - 2.0 * e_max), "min_separation_m": float(flown), "uavs": int(keep.sum())}


def arrivals(pos_m: np.ndarray, dest_m: np.ndarray, dt_s: float, tol_m: float = ARRIVAL_TOLERANCE_M) -> tuple[np.ndarray, np.ndarray]:
    """Per UAV: arrived (within tol of its destination at the end and from some time
    on), and the arrival time, the first instant from which it stays within tol
    (NaN if not arrived). Returns (arrived (N,) bool, time_s (N,))."""
    inside = np.linalg.norm(pos_m - dest_m[None], axis=2) <= tol_m      # (T+1, N)
    T1, N = inside.shape
    arrived = inside[-1].copy()
    # index of the first sample of the final run of True values
    outside_rev = ~inside[::-1]
    last_out_from_end = np.where(outside_rev.any(axis=0), np.argmax(outside_rev, axis=0), T1)
    first_in = T1 - last_out_from_end
    time_s = np.where(arrived, first_in * dt_s, np.nan)
    return arrived, time_s


def motion_energy(vel_m_s: np.ndarray, acc_m_s2: np.ndarray, dt_s: float) -> np.ndarray:
    """Motion energy per UAV: sum over steps of (|v|^2 + |a|^2) dt (Sec. V), (N,)."""
    T = acc_m_s2.shape[0]
    v = vel_m_s[:T]
    return (np.sum(v * v, axis=(0, 2)) + np.sum(acc_m_s2 * acc_m_s2, axis=(0, 2))) * dt_s
