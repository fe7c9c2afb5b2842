"""Exact per-vehicle count of the vehicles within a radius: HJB_d's communication metric.

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
in another order than a pair list would give (rounding only; tests/test_neighbour_count.py).
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial import cKDTree

__all__ = ["count_within", "pos_sums_by_tree", "GRID_MIN_N", "CELLS_PER_RANGE"]

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


_kernel = None


def _compile():
    global _kernel
    if _kernel is not None:
        return _kernel
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

    _kernel = grid_count
    return _kernel


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
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    ext = np.maximum(hi - lo, 1e-9)
    s = r / CELLS_PER_RANGE
    if (ext[0] / s + 1) * (ext[1] / s + 1) > 4 * n + 1024:      # a spread-out swarm: coarser cells, bounded memory
        s = float(math.sqrt(ext[0] * ext[1] / (4 * n))) + max(ext[0], ext[1]) / (4 * n)
    ncx, ncy = int(ext[0] // s) + 1, int(ext[1] // s) + 1
    x0, y0 = float(lo[0]), float(lo[1])
    cx = np.clip(np.floor((pts[:, 0] - x0) / s).astype(np.int64), 0, ncx - 1)
    cy = np.clip(np.floor((pts[:, 1] - y0) / s).astype(np.int64), 0, ncy - 1)
    cell = cy * ncx + cx
    order = np.argsort(cell, kind="stable")
    cell_start = np.zeros(ncx * ncy + 1, dtype=np.int64)
    np.cumsum(np.bincount(cell, minlength=ncx * ncy), out=cell_start[1:])
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
