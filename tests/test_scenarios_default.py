"""Scenarios of issue 7: crossing and dense (paper's is tested with the simulator)."""

import numpy as np
import pytest

from mfg_swarm.scenarios import make_scenario


def test_crossing_swaps_two_groups_through_each_other():
    sc = make_scenario("crossing", 50)
    a, b = sc.group == 0, sc.group == 1
    assert a.sum() == 25 and b.sum() == 25
    np.testing.assert_allclose(sc.initial_pos_m[a].mean(axis=0), [-60.0, 0.0], atol=1e-9)
    np.testing.assert_allclose(sc.initial_pos_m[b].mean(axis=0), [60.0, 0.0], atol=1e-9)
    assert np.all(sc.destination_m[a] == [60.0, 0.0]) and np.all(sc.destination_m[b] == [-60.0, 0.0])
    d = np.linalg.norm(sc.initial_pos_m[:, None] - sc.initial_pos_m[None], axis=2) + np.eye(50) * 1e9
    assert abs(d.min() - np.sqrt(2.0)) < 1e-9


def test_dense_is_the_paper_grid_at_half_a_metre():
    sc, p = make_scenario("dense", 81), make_scenario("paper", 81)
    np.testing.assert_allclose(sc.initial_pos_m.mean(axis=0), [150.0, 100.0])
    d = np.linalg.norm(sc.initial_pos_m[:, None] - sc.initial_pos_m[None], axis=2) + np.eye(81) * 1e9
    assert abs(d.min() - 0.5) < 1e-9
    np.testing.assert_array_equal(sc.destination_m, p.destination_m)


def test_unknown_scenario_and_too_small_crossing_are_clear_errors():
    with pytest.raises(ValueError, match="unknown scenario"):
        make_scenario("nowhere", 4)
    with pytest.raises(ValueError, match="crossing needs"):
        make_scenario("crossing", 1)
