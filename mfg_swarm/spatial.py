"""Spatial queries of the simulator: exact within-range counts (HJB_d's communication metric) and pairs within a per-vehicle reach.

Every UAV of HJB_d receives the state of every UAV within radio range d at every step; the
paper's communication cost is the number of states received, so the simulator must count,
for every UAV i, #{j != i : |r_j - r_i| <= d} exactly. A k-d tree visits every counted
neighbour (``query_ball_point(return_length=True)``: O(N x neighbours), ~6,000 per UAV at
N = 10,000, d = 100 m). Here a uniform grid of cells of side s (rows of cells sorted
row-major, so a run of cells of one row is one slice of the sorted points):

- per UAV and row of cells, the cells whose whole extent lies inside the disc (with a margin
  far above rounding) are counted in bulk from the sorted order (the number of points in
  columns a..b of a row is a difference of two cell starts);
- only the cells the circle crosses are checked point by point, with the same arithmetic as
  scipy's cKDTree (fl(dx^2) + fl(dy^2) <= fl(d^2)), so the count equals
  ``cKDTree(pts).query_ball_point(pts, d, return_length=True) - 1`` exactly (tested on
  random, lattice and exactly-at-distance sets).

Work per UAV: O(d / s) rows + the points in the ~2 pi d x s band the circle crosses,
instead of O(density pi d^2): the step cost grows as N (d / s + density d s), not as
N x density d^2. The loop is compiled with numba (imported on first use: small swarms use
the k-d tree and never pay numba's import).

Optionally the kernel also sums the positions of the counted vehicles (HJB_d's first-step
centroid, controller.HeardSummary): the bulk cells through prefix sums, so the sum comes out
in another order than a pair list would give (rounding only; tests/test_spatial.py).
"""

from __future__ import annotations

import functools
import math

import numpy as np
from scipy.spatial import cKDTree

__all__ = ["count_within", "pos_sums_by_tree", "pairs_within_reach", "rows_within_reach", "sorted_unique", "GRID_MIN_N", "CELLS_PER_RANGE"]

GRID_MIN_N = 2048
"""Below this many vehicles the k-d tree count is used (cheap there; numba is not imported)."""

CELLS_PER_RANGE = 16
"""Grid cell side s = d / CELLS_PER_RANGE (larger if the swarm is so spread that the grid would hold
more than ~4 cells per vehicle). Measured at N = 10,000, d = 100 m, 1.4 m spacing: 8 -> 16 -> 32 cells per
d trade the checked boundary band against rows per UAV; 16 was fastest."""

_SUM_BLOCK = 512      # rows per block when summing positions without listing every pair at once


def pos_sums_by_tree(tree: cKDTree, pts: np.ndarray, range_m: float) -> np.ndarray:
    """(N, 2) sum of the positions within range_m of each point (self excluded), from the pairs of a
    k-d tree in row blocks: memory O(block N) instead of O(pairs). pts (N, 2), tree = cKDTree(pts)."""
    n = pts.shape[0]
    pos_sum = np.zeros((n, 2))
    for b in range(0, n, _SUM_BLOCK):
        e = min(n, b + _SUM_BLOCK)
        m = cKDTree(pts[b:e]).sparse_distance_matrix(tree, range_m, output_type="ndarray")
        i, j = m["i"], m["j"]
        keep = i + b != j
        i, j = i[keep], j[keep]
        for d in range(2):
            pos_sum[b:e, d] = np.bincount(i, pts[j, d], e - b)
    return pos_sum


@functools.cache
def _compile():
    from numba import njit      # here: numba's import costs ~1 s, paid only by swarms that use the grid

    @njit(cache=True, nogil=True)
    def grid_count(xs, ys, cell_start, ncx, ncy, x0, y0, s, r, margin, want_sums, xc, yc, cum_x, cum_y,
                   out_count, out_sx, out_sy):
        r2 = r * r
        n = xs.shape[0]
        for k in range(n):
            x = xs[k]
            y = ys[k]
            cnt = 0
            sx = 0.0
            sy = 0.0
            ry0 = max(0, int(math.floor((y - r - margin - y0) / s)))
            ry1 = min(ncy - 1, int(math.floor((y + r + margin - y0) / s)))
            for ry in range(ry0, ry1 + 1):
                ylo = y0 + ry * s
                yhi = ylo + s
                if y < ylo:
                    dymin = ylo - y
                    dymax = yhi - y
                elif y > yhi:
                    dymin = y - yhi
                    dymax = y - ylo
                else:
                    dymin = 0.0
                    dymax = max(y - ylo, yhi - y)
                dymin = max(dymin - margin, 0.0)
                if dymin > r:
                    continue
                wp = math.sqrt(r2 - dymin * dymin) + margin
                a = max(0, int(math.floor((x - wp - x0) / s)))
                b = min(ncx - 1, int(math.floor((x + wp - x0) / s)))
                if a > b:
                    continue
                base = ry * ncx
                fa = b + 1
                fb = b
                dyf = dymax + margin
                if dyf < r:
                    wf = math.sqrt(r2 - dyf * dyf) - margin
                    if wf > 0.0:
                        fa = max(a, int(math.ceil((x - wf - x0) / s)))
                        fb = min(b, int(math.floor((x + wf - x0) / s)) - 1)
                if fa <= fb:
                    # whole cells fa..fb lie inside the disc: counted in bulk
                    p0 = cell_start[base + fa]
                    p1 = cell_start[base + fb + 1]
                    cnt += p1 - p0
                    if want_sums:
                        sx += cum_x[p1] - cum_x[p0]
                        sy += cum_y[p1] - cum_y[p0]
                    lo1, hi1, lo2, hi2 = a, fa - 1, fb + 1, b
                else:
                    lo1, hi1, lo2, hi2 = a, b, b + 1, b
                # the cells the circle crosses: point by point, scipy's arithmetic
                for lo, hi in ((lo1, hi1), (lo2, hi2)):
                    if lo > hi:
                        continue
                    for j in range(cell_start[base + lo], cell_start[base + hi + 1]):
                        dx = xs[j] - x
                        dy = ys[j] - y
                        if dx * dx + dy * dy <= r2:
                            cnt += 1
                            if want_sums:
                                sx += xs[j] - xc
                                sy += ys[j] - yc
            out_count[k] = cnt
            out_sx[k] = sx
            out_sy[k] = sy

    return grid_count


def count_within(pts: np.ndarray, range_m: float, tree: cKDTree | None = None, pos_sums: bool = False,
                 min_grid_n: int = GRID_MIN_N):
    """For every point i of pts (N, 2): #{j != i : |pts_j - pts_i| <= range_m} (N,) int64, exactly
    ``cKDTree(pts).query_ball_point(pts, range_m, return_length=True) - 1``.

    pos_sums: also return the sum of those points' positions (N, 2) (self excluded; summed in
    another order than a list of the pairs would give: rounding only). ``tree``, if given, is a
    cKDTree of pts (used below ``min_grid_n`` points)."""
    pts = np.ascontiguousarray(pts, dtype=np.float64)
    n = pts.shape[0]
    r = float(range_m)
    if pts.ndim != 2 or pts.shape[1] != 2:
        raise ValueError(f"pts must be (N, 2), got {pts.shape}")
    if not (r >= 0 and math.isfinite(r)):
        raise ValueError(f"range_m must be finite and >= 0, got {range_m}")
    if n == 0:
        return (np.zeros(0, np.int64), np.zeros((0, 2))) if pos_sums else np.zeros(0, np.int64)
    if not np.all(np.isfinite(pts)):
        raise ValueError("pts must be finite")
    if n < min_grid_n or r == 0.0:
        tree = cKDTree(pts) if tree is None else tree
        counts = tree.query_ball_point(pts, r, return_length=True).astype(np.int64) - 1
        return (counts, pos_sums_by_tree(tree, pts, r)) if pos_sums else counts
    order, cell_start, ncx, ncy, x0, y0, s = _grid(pts, r / CELLS_PER_RANGE)   # coarser cells for a spread-out swarm
    hi = pts.max(axis=0)
    xs, ys = pts[order, 0].copy(), pts[order, 1].copy()
    # margin: far above the rounding of the cell geometry (~1e-16 of the coordinates), far below any spacing
    margin = 1e-9 * (r + float(np.max(np.abs(pts)))) + 1e-12
    cum_x = cum_y = np.zeros(1)
    xc, yc = 0.5 * (x0 + float(hi[0])), 0.5 * (y0 + float(hi[1]))         # sums about the centre: smaller terms
    if pos_sums:
        cum_x = np.concatenate([[0.0], np.cumsum(xs - xc)])
        cum_y = np.concatenate([[0.0], np.cumsum(ys - yc)])
    cnt_s = np.empty(n, dtype=np.int64)
    sx_s, sy_s = np.empty(n), np.empty(n)
    _compile()(xs, ys, cell_start, ncx, ncy, x0, y0, float(s), r, float(margin), pos_sums, xc, yc, cum_x, cum_y, cnt_s, sx_s, sy_s)
    counts = np.empty(n, dtype=np.int64)
    counts[order] = cnt_s - 1                    # self is within range
    if not pos_sums:
        return counts
    # the kernel summed x_j - xc over the counted points, self included
    pos_sum = np.empty((n, 2))
    pos_sum[order, 0] = (sx_s - (xs - xc)) + (cnt_s - 1) * xc
    pos_sum[order, 1] = (sy_s - (ys - yc)) + (cnt_s - 1) * yc
    return counts, pos_sum


def sorted_unique(k: np.ndarray) -> np.ndarray:
    """= np.unique(k) for integer keys, by one sort (numpy 2's hash-based unique is ~5x slower on 10^6 keys)."""
    k = np.sort(k)
    return k[np.concatenate([[True], k[1:] != k[:-1]])] if k.size else k


@functools.cache
def _compile_pairs():
    from numba import njit

    @njit(cache=True, nogil=True)
    def reach_pairs(xs, ys, ex, idx, cell_start, ncx, ncy, x0, y0, s, base, cap2, rmax, n_all, us, vs, h, wd, out_keys):
        """The keys i * n + j (i < j) of the pairs, written to out_keys while they fit; returns their number
        (the caller runs it again with room for all if they did not fit). A pair is owned by its member
        with the larger (extra, index), so the other member lies within base + 2 extra of it. wd (n,) bool
        or empty: the wide points, whose pairs skip the closest-approach test. rmax >= sqrt(cap2): no point
        farther counts, so the scan stops there (a reach spanning the sensor range scans no farther)."""
        n = xs.shape[0]
        total = 0
        for k in range(n):
            x = xs[k]
            y = ys[k]
            ek = ex[k]
            ik = idx[k]
            rk = min(base + 2.0 * ek + 1e-9 * (1.0 + base + 2.0 * ek), rmax)
            ry0 = max(0, int(math.floor((y - rk - y0) / s)))
            ry1 = min(ncy - 1, int(math.floor((y + rk - y0) / s)))
            a = max(0, int(math.floor((x - rk - x0) / s)))
            b = min(ncx - 1, int(math.floor((x + rk - x0) / s)))
            for ry in range(ry0, ry1 + 1):
                if a > b:
                    break
                for m in range(cell_start[ry * ncx + a], cell_start[ry * ncx + b + 1]):
                    em = ex[m]
                    im = idx[m]
                    if em > ek or (em == ek and im >= ik):
                        continue
                    dx = xs[m] - x
                    dy = ys[m] - y
                    d2 = dx * dx + dy * dy
                    if d2 > cap2:
                        continue
                    # the test of the numpy version: |r_j - r_i| <= (base + extra_i) + extra_j with i < j
                    if ik < im:
                        lim = (base + ek) + em
                    else:
                        lim = (base + em) + ek
                    if math.sqrt(d2) <= lim:
                        if h >= 0.0 and not (wd.shape[0] > 0 and (wd[k] or wd[m])):
                            # the closest-approach test: min over 0 <= tau <= h of |d + tau u| <= base
                            du = us[m] - us[k]
                            dv = vs[m] - vs[k]
                            uu = du * du + dv * dv
                            tau = 0.0
                            if uu > 0.0:
                                tau = min(max(-(dx * du + dy * dv) / uu, 0.0), h)
                            cx = dx + tau * du
                            cy = dy + tau * dv
                            if not math.sqrt(cx * cx + cy * cy) <= base:
                                continue
                        if total < out_keys.shape[0]:
                            out_keys[total] = min(ik, im) * n_all + max(ik, im)
                        total += 1
        return total

    return reach_pairs


def _grid(pts: np.ndarray, s: float):
    """Points sorted into a row-major grid of cells of side s (coarser if that would hold more than
    ~4 cells per point): (order, cell_start, ncx, ncy, x0, y0, s)."""
    n = pts.shape[0]
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    ext = np.maximum(hi - lo, 1e-9)
    if (ext[0] / s + 1) * (ext[1] / s + 1) > 4 * n + 1024:
        s = float(math.sqrt(ext[0] * ext[1] / (4 * n))) + max(ext[0], ext[1]) / (4 * n)
    ncx, ncy = int(ext[0] // s) + 1, int(ext[1] // s) + 1
    x0, y0 = float(lo[0]), float(lo[1])
    cx = np.clip(np.floor((pts[:, 0] - x0) / s).astype(np.int64), 0, ncx - 1)
    cy = np.clip(np.floor((pts[:, 1] - y0) / s).astype(np.int64), 0, ncy - 1)
    cell = cy * ncx + cx
    order = np.argsort(cell, kind="stable")
    cell_start = np.zeros(ncx * ncy + 1, dtype=np.int64)
    np.cumsum(np.bincount(cell, minlength=ncx * ncy), out=cell_start[1:])
    return order, cell_start, ncx, ncy, x0, y0, float(s)


_KEYS_ROOM = [0]
"""The largest pair count the grid kernel has returned so far: the room the next call starts with (a crowded
swarm has far more than 16 pairs per vehicle, and a kernel run that overflows its room runs twice)."""


def _reach_keys(pts: np.ndarray, base: float, extra: np.ndarray, cap_m: float, h: float,
                vel: np.ndarray | None, wide: np.ndarray | None = None) -> np.ndarray:
    """The keys i * n + j (i < j), in no particular order, of the pairs of pairs_within_reach (also within cap_m,
    scipy's test), by the compiled grid kernel."""
    n = pts.shape[0]
    q = float(np.median(extra))
    # beyond cap_m nothing counts: the scan radius (and the cells) stop there (with a relative margin of 1e-9 over
    # the kernel's test fl(dx^2 + dy^2) <= fl(cap^2))
    rmax = float(cap_m) * (1.0 + 1e-9) + 1e-9 if math.isfinite(cap_m) else math.inf
    order, cell_start, ncx, ncy, x0, y0, s = _grid(pts, max(min(base + 2.0 * q, rmax), 1e-6))
    xs, ys = pts[order, 0].copy(), pts[order, 1].copy()
    ex = np.ascontiguousarray(extra[order], dtype=np.float64)
    idx = order.astype(np.int64)
    cap2 = float(cap_m) * float(cap_m) if math.isfinite(cap_m) else math.inf
    kern = _compile_pairs()
    us = vs = np.zeros(0)
    if vel is not None:
        us, vs = np.ascontiguousarray(vel[order, 0], dtype=np.float64), np.ascontiguousarray(vel[order, 1], dtype=np.float64)
    wd = np.zeros(0, dtype=np.bool_) if wide is None else np.ascontiguousarray(wide[order], dtype=np.bool_)
    args = (xs, ys, ex, idx, cell_start, ncx, ncy, x0, y0, s, float(base), cap2, rmax, n, us, vs, float(h) if vel is not None else -1.0,
            wd)
    keys = np.empty(max(16 * n + 1024, _KEYS_ROOM[0] + _KEYS_ROOM[0] // 4), dtype=np.int64)
    total = kern(*args, keys)
    if total > keys.size:
        keys = np.empty(total, dtype=np.int64)
        kern(*args, keys)
    _KEYS_ROOM[0] = max(_KEYS_ROOM[0], total)
    return keys[:total]


def _pairs_within_reach_grid(pts: np.ndarray, base: float, extra: np.ndarray, cap_m: float, h: float,
                             vel: np.ndarray | None, wide: np.ndarray | None = None) -> np.ndarray:
    """The pairs of pairs_within_reach (also within cap_m, scipy's test), sorted, by the compiled grid kernel."""
    n = pts.shape[0]
    keys = _reach_keys(pts, base, extra, cap_m, h, vel, wide)
    keys.sort()
    return np.stack([keys // n, keys % n], axis=1)


@functools.cache
def _compile_rows():
    from numba import njit

    @njit(cache=True, nogil=True)
    def rows_of_keys(keys, n):
        """Both directions of the pairs with keys i * n + j (distinct, i != j, any order) as (owner (2p,),
        other (2p,)) sorted by (owner, other): two counting passes, by other then (stably) by owner."""
        p = keys.shape[0]
        cnt = np.zeros(n + 1, dtype=np.int64)           # rows per vehicle: as owner = as other (both directions)
        for e in range(p):
            i = keys[e] // n
            j = keys[e] - i * n
            cnt[i + 1] += 1
            cnt[j + 1] += 1
        for v in range(n):
            cnt[v + 1] += cnt[v]
        by_other = np.empty(2 * p, dtype=np.int64)     # the owners, grouped by other
        fill = cnt[:n].copy()
        for e in range(p):
            i = keys[e] // n
            j = keys[e] - i * n
            by_other[fill[j]] = i
            fill[j] += 1
            by_other[fill[i]] = j
            fill[i] += 1
        owner = np.empty(2 * p, dtype=np.int64)
        other = np.empty(2 * p, dtype=np.int64)
        fill = cnt[:n].copy()
        for o in range(n):                             # others ascending: within an owner, its others ascending
            for t in range(cnt[o], cnt[o + 1]):
                w = by_other[t]
                owner[fill[w]] = w
                other[fill[w]] = o
                fill[w] += 1
        return owner, other

    return rows_of_keys


def _parse_reach(reach, n: int, vel: np.ndarray | None):
    """A controller's reach as (base, extra (n,), horizon or None, wide (n,) bool or None, vel or None): a scalar
    base, or (base, extra[, horizon_s[, wide]]) (pairs_within_reach's docstring)."""
    if np.isscalar(reach):
        base, extra, h, wide = reach, None, None, None
    else:
        base, extra, h, wide = (tuple(reach) + (None, None))[:4]
    if h is not None and vel is None:
        raise ValueError("a reach with a relative-velocity horizon needs the velocities (vel)")
    if wide is not None and h is None:
        raise ValueError("wide rows are exempt from the closest-approach test: a reach with them needs its horizon")
    vel = None if h is None else np.asarray(vel, dtype=np.float64).reshape(-1, 2)
    extra = np.zeros(n) if extra is None else np.asarray(extra, dtype=float)
    if wide is not None:
        wide = np.asarray(wide, dtype=bool)
        if wide.shape != (n,):
            raise ValueError(f"the reach's wide rows must be ({n},), got {wide.shape}")
        if not wide.any():
            wide = None
    return float(base), extra, h, wide, vel


def rows_within_reach(pts: np.ndarray, reach, cap_m: float, vel: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(owner (m,), other (m,)) = ``mock_vehicle.proximity.sensed_rows(pairs_within_reach(None, pts, reach, cap_m,
    clip=True, vel=vel))``, bit for bit, without sorting: the grid kernel's pairs, in the order it finds them, go
    through two linear counting passes (by other, then by owner) instead of a sort of the pairs and the rows'
    sort by (owner, other) - most of a simulator step when thousands of vehicles crowd (~10^6 rows)."""
    n = pts.shape[0]
    if n < 2:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    base, extra, h, wide, vel = _parse_reach(reach, n, vel)
    keys = _reach_keys(np.ascontiguousarray(pts, dtype=np.float64), base, extra, float(cap_m),
                       -1.0 if h is None else float(h), vel, wide)
    return _compile_rows()(keys, n)


def pairs_within_reach(tree: cKDTree, pts: np.ndarray, reach, cap_m: float, clip: bool = False,
                       vel: np.ndarray | None = None, min_grid_n: int = GRID_MIN_N) -> np.ndarray | None:
    """Undirected pairs (p, 2), i < j, sorted, with |r_j - r_i| <= base + extra_i + extra_j for a
    controller-declared reach = (base_m, extra_m (N,)) (or a scalar: extra = 0); None if that can
    reach cap_m (the caller then lists everything within cap_m), unless ``clip``: then the pairs
    that are also within cap_m (scipy's test, fl(dx^2 + dy^2) <= fl(cap^2), as ``query_pairs``)
    are returned. A reach (base_m, extra_m, horizon_s) also requires the closest approach over the
    horizon, min over 0 <= tau <= horizon_s of |d + tau u| (d = r_j - r_i, u = v_j - v_i), to be <= base
    (vel (N, 2): the velocities of the states the reach was declared for; it implies
    |d| <= base + horizon_s |u|, so extra_k >= horizon_s |v_k - c| for any c keeps the scan complete).
    A fourth element, wide (N,) bool, exempts the pairs of the wide vehicles from that closest-approach test
    (a controller's rows that need every vehicle within base + extra_i + extra_j: give them extra >= cap_m).

    From ``min_grid_n`` points on (or with clip), a compiled grid kernel: each pair is found from
    its member with the larger extra, within base + 2 extra of it, so one fast vehicle costs its
    own neighbourhood only. Below, with the k-d tree: all pairs within base + 2 q (q the 90th
    percentile of extra), plus, for the few vehicles with extra > q, all pairs within
    base + extra + max(extra) by a second tree query. Both end with the same exact per-pair test
    (tests/test_scaling.py, tests/test_spatial.py)."""
    n = pts.shape[0]
    base, extra, h, wide, vel = _parse_reach(reach, n, vel)
    emax = float(extra.max()) if n else 0.0
    if not clip and not base + 2.0 * emax < cap_m:
        return None
    if n >= 2 and (n >= min_grid_n or clip):
        return _pairs_within_reach_grid(np.ascontiguousarray(pts, dtype=np.float64), float(base), extra, float(cap_m),
                                        -1.0 if h is None else float(h), vel, wide)
    q = float(np.quantile(extra, 0.9)) if n else 0.0
    keys = [None]
    p0 = tree.query_pairs(base + 2.0 * q + 1e-9, output_type="ndarray").astype(np.int64)
    keys[0] = p0[:, 0] * n + p0[:, 1]
    fast = np.flatnonzero(extra > q)
    if fast.size:
        m = cKDTree(pts[fast]).sparse_distance_matrix(tree, base + 2.0 * emax + 1e-9, output_type="ndarray")
        i, j = fast[m["i"]].astype(np.int64), m["j"].astype(np.int64)
        ne = i != j
        i, j = i[ne], j[ne]
        keys.append(np.minimum(i, j) * n + np.maximum(i, j))
    k = sorted_unique(np.concatenate(keys)) if len(keys) > 1 else np.sort(keys[0])
    pairs = np.stack([k // n, k % n], axis=1)
    d = np.linalg.norm(pts[pairs[:, 1]] - pts[pairs[:, 0]], axis=1)
    keep = d <= base + extra[pairs[:, 0]] + extra[pairs[:, 1]]
    if h is not None:
        dd, uu = pts[pairs[:, 1]] - pts[pairs[:, 0]], vel[pairs[:, 1]] - vel[pairs[:, 0]]
        u2 = np.einsum("pd,pd->p", uu, uu)
        tau = np.where(u2 > 0, np.clip(-np.einsum("pd,pd->p", dd, uu) / np.where(u2 > 0, u2, 1.0), 0.0, h), 0.0)
        near = np.linalg.norm(dd + tau[:, None] * uu, axis=1) <= base
        if wide is not None:
            near |= wide[pairs[:, 0]] | wide[pairs[:, 1]]
        keep &= near
    return pairs[keep]
