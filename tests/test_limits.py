"""The physical limit behind a vehicle that fails into Hold (mfg_swarm/limits.py)."""

import numpy as np

from mfg_swarm.limits import follower_best_clearance_m


def test_without_delay_the_follower_keeps_its_gap_by_braking_as_hard():
    r = follower_best_clearance_m(delay_s=0.0, restarts=1)
    assert abs(r["constant_m"] - np.sqrt(2.0)) < 1e-9 and r["direction_deg"] == 180.0


def test_one_control_period_of_delay_leaves_less_than_half_the_lattice_spacing():
    """The default controller sees the braking one period (0.5 s) late: no acceleration of norm 2 m/s^2, in any
    piecewise-constant direction, keeps the UAV 1.41 m behind in the lane half the spacing (0.707 m) from it; the best
    is ~0.48 m, braking and swerving together (~120 deg from straight ahead). A quarter period (0.25 s) would allow it."""
    r = follower_best_clearance_m(delay_s=0.5)
    assert 0.44 < r["constant_m"] < 0.5
    assert r["piecewise_m"] < np.sqrt(2.0) / 2
    # the constant direction is (within a millimetre) the optimum over piecewise-constant ones: the bound is tight
    assert r["piecewise_m"] - r["constant_m"] < 1e-3
    assert 100.0 < r["direction_deg"] < 140.0
    assert follower_best_clearance_m(delay_s=0.25, restarts=1)["constant_m"] > np.sqrt(2.0) / 2


def test_the_clearance_falls_with_the_delay_and_rises_with_the_gap():
    c = [follower_best_clearance_m(delay_s=d, restarts=0)["constant_m"] for d in (0.0, 0.1, 0.25, 0.5)]
    assert all(a > b for a, b in zip(c, c[1:]))
    assert follower_best_clearance_m(gap_m=2.0, restarts=0)["constant_m"] > c[-1]
