"""Metric bookkeeping on hand-made trajectories (SPEC section 6)."""

import numpy as np
import pytest

from mfg_autopilot.paper.params import radio_range_m
from mfg_swarm.metrics import arrivals, collisions, motion_energy, segment_min_distance, separation_guarantee


def test_pair_passing_through_each_other_between_samples_is_a_collision():
    # Two UAVs swap places in one step: 2 m apart at both samples, 0 m mid-step.
    pos = np.array([[[0.0, 0.0], [2.0, 0.0]], [[2.0, 0.0], [0.0, 0.0]]])
    col = collisions(pos)
    assert col["collision_pairs"] == 1 and col["collision_pair_steps"] == 1
    assert col["min_pair_distance_m"] < 1e-12
    assert col["pairs"] == [(0, 1)]


def test_near_miss_is_not_a_collision_and_min_distance_is_exact():
    # UAV 1 flies past UAV 0 at a lateral offset of 0.15 m.
    pos = np.array([[[0.0, 0.0], [-5.0, 0.15], [50.0, 50.0]], [[0.0, 0.0], [5.0, 0.15], [50.0, 50.0]]])
    col = collisions(pos)
    assert col["collision_pairs"] == 0
    np.testing.assert_allclose(col["min_pair_distance_m"], 0.15)


def test_collision_counted_per_pair_and_per_step():
    # Three UAVs sitting 0.05 m apart in a row for 3 steps: pairs (0,1),(1,2),(0,2 is 0.1 -> not <0.1)
    p = np.array([[0.0, 0.0], [0.05, 0.0], [0.10, 0.0]])
    pos = np.repeat(p[None], 4, axis=0)
    col = collisions(pos)
    assert col["collision_pairs"] == 2 and col["collision_pair_steps"] == 6


def test_segment_min_distance_closed_form():
    d = segment_min_distance(np.array([[1.0, 1.0]]), np.array([[1.0, -1.0]]))
    np.testing.assert_allclose(d, [1.0])


def test_arrival_time_is_from_when_it_stays():
    dest = np.zeros((2, 2))
    x0 = [5.0, 0.5, 3.0, 0.9, 0.2, 0.1]     # in at k=1, out at k=2, in from k=3 on
    x1 = [5.0, 4.0, 3.0, 2.0, 1.5, 1.2]     # never within 1 m
    pos = np.stack([np.stack([x0, np.zeros(6)], 1), np.stack([x1, np.zeros(6)], 1)], axis=1)
    arrived, t = arrivals(pos, dest, dt_s=0.5)
    assert arrived.tolist() == [True, False]
    assert t[0] == 1.5 and np.isnan(t[1])


def test_motion_energy_sums_v2_plus_a2_dt():
    vel = np.array([[[1.0, 0.0]], [[2.0, 0.0]], [[9.0, 9.0]]])
    acc = np.array([[[0.0, 1.0]], [[0.0, 0.0]]])
    np.testing.assert_allclose(motion_energy(vel, acc, 0.5), [(1 + 1 + 4 + 0) * 0.5])


def test_radio_range_formula_and_erratum_2():
    np.testing.assert_allclose(radio_range_m(1e-3), np.sqrt(0.5))
    np.testing.assert_allclose(radio_range_m(10.0), np.sqrt(0.5) * 100)


def _brute_collisions(pos, radius=0.1):
    from mfg_swarm.metrics import segment_min_distance as smd
    T1, N, _ = pos.shape
    i, j = np.triu_indices(N, 1)
    hits, steps, dmin = set(), 0, np.inf
    for k in range(T1 - 1):
        d = smd(pos[k, j] - pos[k, i], pos[k + 1, j] - pos[k + 1, i])
        dmin = min(dmin, float(d.min()))
        h = d < radius
        steps += int(h.sum())
        hits.update(zip(i[h].tolist(), j[h].tolist()))
    return len(hits), steps, dmin, sorted(hits)


@pytest.mark.parametrize("seed,n", [(0, 60), (1, 300), (2, 2100)])
def test_collisions_equal_the_all_pairs_check(seed, n):
    # given random walks of a swarm drifting together (some pairs collide, most steps have none)
    rng = np.random.default_rng(seed)
    side = np.sqrt(n) * 1.5
    p0 = rng.uniform(0.0, side, (n, 2))
    steps = rng.normal(0.0, 0.15, (12, n, 2)) + np.array([0.8, -0.3])
    steps[:, : n // 20] *= 6.0                                 # a few fast, erratic vehicles
    pos = np.concatenate([p0[None], p0[None] + np.cumsum(steps, axis=0)], axis=0)
    # when checked with the candidate pruning and against every pair
    col = collisions(pos)
    ref = _brute_collisions(pos)
    # then the same pairs, pair-steps and smallest distance
    assert (col["collision_pairs"], col["collision_pair_steps"]) == ref[:2]
    assert col["min_pair_distance_m"] == ref[2]
    assert [tuple(p) for p in col["pairs"]] == ref[3]


def test_collisions_of_crossing_streams_equal_the_all_pairs_check():
    # given four streams flying through each other at 4 m/s (swap4's shape: the displacements differ by 2 m per step,
    # and the candidates are the pairs whose segments come within the smallest distance so far)
    rng = np.random.default_rng(7)
    n = 400
    head = np.array([[1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [0.0, -1.0]])[np.arange(n) % 4]
    p0 = rng.uniform(-15.0, 15.0, (n, 2)) - 20.0 * head
    steps = 2.0 * head[None] + rng.normal(0.0, 0.05, (20, n, 2))
    pos = np.concatenate([p0[None], p0[None] + np.cumsum(steps, axis=0)], axis=0)
    # when checked with the pruning and against every pair
    col, ref = collisions(pos), _brute_collisions(pos)
    # then the same pairs, pair-steps and smallest distance (and some pairs collide)
    assert (col["collision_pairs"], col["collision_pair_steps"]) == ref[:2] and ref[0] > 0
    assert col["min_pair_distance_m"] == ref[2]
    assert [tuple(p) for p in col["pairs"]] == ref[3]


@pytest.mark.parametrize("n_side", [8, 47])
def test_min_distance_exact_without_collisions(n_side):
    # given a jittered lattice flying together, no pair ever within the radius (the min-distance-only path;
    # 47 x 47 = 2209 vehicles takes the grid kernel)
    rng = np.random.default_rng(n_side)
    g = np.stack(np.meshgrid(np.arange(n_side), np.arange(n_side)), axis=-1).reshape(-1, 2) * 1.5
    steps = rng.normal(0.0, 0.05, (10, g.shape[0], 2)) + np.array([0.5, 0.2])
    pos = np.concatenate([g[None], g[None] + np.cumsum(steps, axis=0)], axis=0)
    col = collisions(pos)
    ref = _brute_collisions(pos)
    assert ref[0] == 0 and ref[2] > 0.1
    assert (col["collision_pairs"], col["collision_pair_steps"], col["min_pair_distance_m"]) == ref[:3]


def test_separation_guarantee_bounds_the_flown_separation_by_the_plan_and_the_tracking_error():
    # given plan particles on crossing straight lines and UAVs off their particles by up to 0.2 m, one UAV far off
    rng = np.random.default_rng(7)
    t = np.linspace(0.0, 1.0, 21)[:, None, None]
    start = rng.uniform(-10, 10, size=(1, 12, 2))
    plan = start + t * rng.uniform(-20, 20, size=(1, 12, 2))
    err = rng.normal(size=plan.shape)
    err *= (0.2 * rng.uniform(size=plan.shape[:2]) / np.linalg.norm(err, axis=2))[:, :, None]
    pos = plan + err
    pos[10:, 3] += 5.0                                   # UAV 3 leaves its particle at step 10 (a failure)
    tracking = np.ones(plan.shape[:2], dtype=bool)
    tracking[10:, 3] = False
    g = separation_guarantee(pos, plan, tracking)
    keep = np.arange(12) != 3
    # then the figures are those of the tracking UAVs, and the bound holds
    assert g["uavs"] == 11
    assert g["tracking_error_max_m"] == pytest.approx(np.max(np.linalg.norm(err[:, keep], axis=2)))
    assert g["plan_min_separation_m"] == pytest.approx(collisions(plan[:, keep])["min_pair_distance_m"])
    assert g["min_separation_m"] == pytest.approx(collisions(pos[:, keep])["min_pair_distance_m"])
    assert g["separation_bound_m"] == pytest.approx(g["plan_min_separation_m"] - 2 * g["tracking_error_max_m"])
    assert g["min_separation_m"] >= g["separation_bound_m"]
    # and with the failed UAV counted as tracking, its 5 m error makes the bound say nothing
    assert separation_guarantee(pos, plan)["tracking_error_max_m"] > 5.0
    with pytest.raises(ValueError, match="both be"):
        separation_guarantee(pos, plan[:, :5])


@pytest.mark.parametrize("seed", [0, 3, 11])
def test_property_the_guarantee_bound_never_exceeds_the_flown_separation(seed):
    # random plans and tracking errors, seeded: the triangle inequality along step segments
    rng = np.random.default_rng(seed)
    n, steps = 20, 30
    vel = rng.normal(scale=2.0, size=(n, 2))
    plan = rng.uniform(-15, 15, size=(1, n, 2)) + np.arange(steps + 1)[:, None, None] * 0.5 * vel[None]
    pos = plan + rng.normal(scale=0.3, size=plan.shape)
    g = separation_guarantee(pos, plan)
    assert g["min_separation_m"] >= g["separation_bound_m"] - 1e-12


def test_separation_guarantee_reuses_a_known_min_separation_only_when_every_uav_tracked():
    rng = np.random.default_rng(2)
    plan = rng.uniform(-5, 5, size=(1, 6, 2)) + np.arange(5)[:, None, None] * 0.1
    pos = plan + 0.05
    assert separation_guarantee(pos, plan, min_separation_m=-1.0)["min_separation_m"] == -1.0
    tracking = np.ones((5, 6), dtype=bool)
    tracking[3:, 0] = False
    assert separation_guarantee(pos, plan, tracking, min_separation_m=-1.0)["min_separation_m"] > 0
