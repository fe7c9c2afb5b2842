"""The exact within-range count (HJB_d's communication metric) by the grid kernel equals the
k-d tree's count, bit for bit, also for points exactly at the range and coincident points."""

import numpy as np
import pytest
from scipy.spatial import cKDTree

from mfg_swarm.spatial import count_within, pairs_within_reach, pos_sums_by_tree


def _tree_count(pts: np.ndarray, r: float) -> np.ndarray:
    return cKDTree(pts).query_ball_point(pts, r, return_length=True).astype(np.int64) - 1


@pytest.mark.parametrize("seed,n,side,r", [(0, 3000, 300.0, 100.0), (1, 2500, 60.0, 100.0), (2, 4000, 2000.0, 100.0),
                                           (3, 3000, 500.0, 7.3)])
def test_grid_count_equals_the_tree_count(seed, n, side, r):
    # given scattered vehicles (dense, all-in-range, sparse, short range) with coincident ones
    rng = np.random.default_rng(seed)
    pts = rng.uniform(-side / 2, side / 2, (n, 2)) + np.array([1234.5, -987.25])
    pts[10:20] = pts[0]
    pts = pts.astype(np.float32).astype(np.float64)          # what the simulator counts (float32 states)
    # when counted by the grid kernel (forced) and by the k-d tree
    got = count_within(pts, r, min_grid_n=0)
    # then the counts are the same
    np.testing.assert_array_equal(got, _tree_count(pts, r))
    assert got.dtype == np.int64


def test_grid_count_is_exact_for_points_exactly_at_the_range():
    # given an integer lattice and r = 5: (3, 4) offsets are exactly at the range, (0, 5) too
    g = np.arange(-30, 31, dtype=float)
    pts = np.stack(np.meshgrid(g, g), axis=-1).reshape(-1, 2)
    for r in (5.0, 5.0 * (1 + 1e-15), 5.0 * (1 - 1e-15), 4.0, 25.0):
        # when counted both ways
        got = count_within(pts, r, min_grid_n=0)
        # then equal; an interior point at r = 5 hears the 80 lattice points within its disc
        np.testing.assert_array_equal(got, _tree_count(pts, r))
    assert count_within(pts, 5.0, min_grid_n=0)[pts.shape[0] // 2] == 80


def test_grid_count_of_a_single_far_outlier_and_of_a_line():
    # given a swarm with one vehicle far away (coarser cells: bounded memory) and vehicles on a line
    rng = np.random.default_rng(7)
    pts = np.concatenate([rng.uniform(0.0, 50.0, (3000, 2)), [[1e6, -1e6]]])
    np.testing.assert_array_equal(count_within(pts, 10.0, min_grid_n=0), _tree_count(pts, 10.0))
    line = np.stack([np.linspace(0.0, 500.0, 3001), np.zeros(3001)], axis=1)
    np.testing.assert_array_equal(count_within(line, 1.0 / 6.0, min_grid_n=0), _tree_count(line, 1.0 / 6.0))


def test_grid_position_sums_equal_the_pair_sums_to_rounding():
    # given a dense block of vehicles (float32 positions) and d = 100 m
    rng = np.random.default_rng(3)
    pts = (rng.uniform(0.0, 150.0, (3000, 2)) + np.array([500.0, 200.0])).astype(np.float32).astype(np.float64)
    # when the sums of the positions in range come from the grid and from the tree's pairs
    cnt, s = count_within(pts, 100.0, pos_sums=True, min_grid_n=0)
    ref = pos_sums_by_tree(cKDTree(pts), pts, 100.0)
    # then the counts are exact and the sums equal to rounding (another summation order)
    np.testing.assert_array_equal(cnt, _tree_count(pts, 100.0))
    np.testing.assert_allclose(s, ref, rtol=1e-12, atol=1e-9)
    # and below the grid threshold the tree's sums are returned unchanged
    cnt2, s2 = count_within(pts, 100.0, pos_sums=True, min_grid_n=10**6)
    np.testing.assert_array_equal(s2, ref)
    np.testing.assert_array_equal(cnt2, cnt)


def test_count_within_rejects_bad_input():
    with pytest.raises(ValueError, match="range_m"):
        count_within(np.zeros((3, 2)), -1.0)
    with pytest.raises(ValueError, match=r"\(N, 2\)"):
        count_within(np.zeros((3, 3)), 1.0)
    with pytest.raises(ValueError, match="finite"):
        count_within(np.array([[0.0, np.nan], [1.0, 1.0]]), 1.0)
    assert count_within(np.zeros((0, 2)), 1.0).shape == (0,)


def _brute_reach_pairs(pts, base, extra, cap=np.inf, vel=None, h=None, wide=None):
    d = np.linalg.norm(pts[:, None] - pts[None, :], axis=2)
    ok = d <= base + extra[:, None] + extra[None, :]
    if vel is not None:
        dd, uu = pts[None, :] - pts[:, None], vel[None, :] - vel[:, None]
        u2 = np.sum(uu * uu, axis=2)
        tau = np.clip(-np.sum(dd * uu, axis=2) / np.where(u2 > 0, u2, 1.0), 0.0, h) * (u2 > 0)
        near = np.linalg.norm(dd + tau[..., None] * uu, axis=2) <= base
        if wide is not None:
            near |= wide[:, None] | wide[None, :]
        ok &= near
    if np.isfinite(cap):
        dx = pts[:, None] - pts[None, :]
        ok &= (dx[..., 0] * dx[..., 0] + dx[..., 1] * dx[..., 1]) <= cap * cap
    i, j = np.nonzero(np.triu(ok, k=1))
    return np.stack([i, j], axis=1)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_grid_pairs_within_reach_equal_the_tree_ones_and_the_brute_force_ones(seed):
    # given scattered vehicles (some coincident), a few with a large reach, and velocities
    rng = np.random.default_rng(seed)
    n = 900
    pts = rng.uniform(0.0, 80.0, (n, 2))
    pts[3] = pts[4]
    extra = np.abs(rng.standard_normal(n)) * 0.5
    extra[rng.integers(0, n, 12)] = 6.0
    extra[7] = extra[8]                              # equal reach: the tie is broken by the index
    vel = rng.standard_normal((n, 2))
    tree = cKDTree(pts)
    # when listed by the grid kernel (forced) and by the k-d tree, with and without the velocity test
    for reach, v in (((1.0, extra), None), ((1.0, extra, 2.0), vel)):
        grid = pairs_within_reach(tree, pts, reach, 100.0, vel=v, min_grid_n=0)
        kd = pairs_within_reach(tree, pts, reach, 100.0, vel=v, min_grid_n=10**9)
        # then both are the sorted brute-force pairs
        ref = _brute_reach_pairs(pts, 1.0, extra, vel=v, h=None if v is None else 2.0)
        np.testing.assert_array_equal(grid, ref)
        np.testing.assert_array_equal(kd, ref)
    # (the closest-approach test removes pairs: the case is not trivial)
    assert len(_brute_reach_pairs(pts, 1.0, extra, vel=vel, h=2.0)) < len(_brute_reach_pairs(pts, 1.0, extra))
    # and clipped at a cap below the reach: the pairs within both (never None)
    got = pairs_within_reach(None, pts, (1.0, extra), 5.0, clip=True)
    np.testing.assert_array_equal(got, _brute_reach_pairs(pts, 1.0, extra, cap=5.0))
    assert pairs_within_reach(tree, pts, (1.0, extra), 5.0) is None
    with pytest.raises(ValueError, match="velocities"):
        pairs_within_reach(tree, pts, (1.0, extra, 2.0), 100.0)


@pytest.mark.parametrize("seed", [0, 1])
def test_wide_vehicles_skip_the_closest_approach_test(seed):
    # given streams crossing at 8 m/s closing speed (a stream mate keeps u ~ 0, an oncoming vehicle does not) and a few
    # wide vehicles (a controller's rows near a vehicle off the plan: they need every vehicle within their reach)
    from mfg_swarm.spatial import rows_within_reach
    from mock_vehicle.proximity import sensed_rows

    rng = np.random.default_rng(seed)
    n = 800
    pts = rng.uniform(0.0, 40.0, (n, 2))
    vel = np.where((np.arange(n) % 2 == 0)[:, None], [4.0, 0.0], [-4.0, 0.0]) + rng.normal(0.0, 0.05, (n, 2))
    extra = 2.0 * np.linalg.norm(vel - np.median(vel, axis=0), axis=1)
    wide = np.zeros(n, dtype=bool)
    wide[rng.choice(n, 25, replace=False)] = True
    extra[wide] = 10.0
    tree = cKDTree(pts)
    # when listed with the horizon and the wide vehicles, by the grid kernel, the k-d tree and as sensed rows
    reach = (1.5, extra, 2.0, wide)
    grid = pairs_within_reach(tree, pts, reach, 100.0, vel=vel, min_grid_n=0)
    kd = pairs_within_reach(tree, pts, reach, 100.0, vel=vel, min_grid_n=10**9)
    ref = _brute_reach_pairs(pts, 1.5, extra, vel=vel, h=2.0, wide=wide)
    # then each is the brute force: a wide vehicle's pairs by the distance test alone, the others' also by the
    # closest approach
    np.testing.assert_array_equal(grid, ref)
    np.testing.assert_array_equal(kd, ref)
    rows = rows_within_reach(pts, reach, 10.0, vel=vel)
    ref_rows = sensed_rows(pairs_within_reach(None, pts, reach, 10.0, clip=True, vel=vel))
    for a, b in zip(rows, ref_rows):
        np.testing.assert_array_equal(a, b)
    # (not trivial: the exemption keeps pairs the test removes, and the test removes pairs of the others)
    no_wide = _brute_reach_pairs(pts, 1.5, extra, vel=vel, h=2.0)
    dist_only = _brute_reach_pairs(pts, 1.5, extra)
    assert len(no_wide) < len(ref) < len(dist_only)
    # a wide vehicle senses every vehicle within its reach and the sensor range (10 m)
    w = int(np.flatnonzero(wide)[0])
    d_w = np.linalg.norm(pts - pts[w], axis=1)
    near_w = np.flatnonzero((d_w <= 1.5 + extra[w] + extra) & (d_w <= 10.0))
    assert set(rows[1][rows[0] == w]) == set(near_w) - {w}
    # and a malformed wide mask or one without the horizon is refused
    with pytest.raises(ValueError, match="wide"):
        pairs_within_reach(tree, pts, (1.5, extra, 2.0, wide[:-1]), 100.0, vel=vel)
    with pytest.raises(ValueError, match="horizon"):
        pairs_within_reach(tree, pts, (1.5, extra, None, wide), 100.0, vel=vel)


@pytest.mark.parametrize("seed", range(6))
def test_rows_within_reach_equal_the_sorted_rows_of_the_pairs(seed):
    """rows_within_reach (grid pairs in kernel order, two counting passes) gives the rows of
    sensed_rows(pairs_within_reach(..., clip=True)), bit for bit: scalar reaches, per-vehicle extras,
    a closest-approach horizon; crowds, coincident vehicles, no pair, one pair, one vehicle."""
    from mfg_swarm.spatial import rows_within_reach
    from mock_vehicle.proximity import sensed_rows

    rng = np.random.default_rng(seed)
    n = [2, 3, 40, 500, 3000, 1200][seed]
    pts = rng.normal(0.0, [1.0, 30.0, 3.0, 5.0, 20.0, 2.0][seed], (n, 2)).astype(np.float32).astype(np.float64)
    if n > 20:
        pts[5:15] = pts[0]
    vel = rng.uniform(-4.0, 4.0, (n, 2))
    reaches = [0.0, 0.5, 3.0, (0.1, rng.uniform(0.0, 3.0, n)), (1.0, rng.uniform(0.0, 0.5, n), 2.0), (0.1, np.full(n, 20.0))]
    for reach in reaches:
        ref = sensed_rows(pairs_within_reach(None, pts, reach, 10.0, clip=True, vel=vel))
        got = rows_within_reach(pts, reach, 10.0, vel=vel)
        for a, b in zip(got, ref):
            assert a.dtype == np.int64
            np.testing.assert_array_equal(a, b)
    one = rows_within_reach(np.array([[0.0, 0.0], [1.0, 0.0], [50.0, 0.0]]), 2.0, 10.0)   # one pair within reach
    assert one[0].tolist() == [0, 1] and one[1].tolist() == [1, 0]
    assert all(a.size == 0 for a in rows_within_reach(np.array([[0.0, 0.0], [20.0, 0.0]]), 0.0, 10.0))   # none
    assert all(a.size == 0 for a in rows_within_reach(np.zeros((1, 2)), 1.0, 10.0))                      # one vehicle
