"""The rigid plan (issue 18): conflict-free by construction where the target layout is a half turn."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial import cKDTree

from mfg_autopilot.guidance.rigid_plan import RigidPlan, rigid_plan_for, trapezoid
from mfg_autopilot.paper.params import CostParams
from mfg_swarm.scenarios import make_scenario

COST = CostParams()


def _states(pos, rng, v=(1.0, -1.0), spread=0.2):
    vel = np.asarray(v)[None, :] + spread * rng.standard_normal((len(pos), 2))
    return np.concatenate([pos, vel], axis=1)


def _min_distance_over(plan: RigidPlan, dt=0.1) -> float:
    dmin = np.inf
    for t in np.arange(0.0, plan.T + 30.0, dt):
        s, _ = plan.at(t)
        d, _ = cKDTree(s[:, :2]).query(s[:, :2], k=2)
        dmin = min(dmin, float(d[:, 1].min()))
    return dmin


def _groups_around_a_centre(rng, n_groups, per_group, radius, spacing):
    """Groups on grids at different distances around a random centre (rings), each flying to the mirror image of its
    centroid: (start positions (N, 2), sites (N, 2), group index (N,), the centre (2,))."""
    centre = rng.uniform(-100, 100, size=2)
    ang = np.sort(rng.uniform(0, 2 * np.pi, size=n_groups))
    pos, sites, grp = [], [], []
    for g, a in enumerate(ang):
        c = centre + radius * np.array([np.cos(a), np.sin(a)]) * (1 + 0.3 * g)    # different distances: rings
        idx = np.arange(per_group)
        cols = int(np.ceil(np.sqrt(per_group)))
        grid = np.stack([idx // cols, idx % cols], axis=1) * spacing
        p = c + grid - grid.mean(axis=0)
        pos.append(p)
        sites.append(np.tile(2 * centre - p.mean(axis=0), (per_group, 1)))
        grp.append(np.full(per_group, g))
    return np.concatenate(pos), np.concatenate(sites), np.concatenate(grp), centre


@settings(max_examples=25, deadline=None, derandomize=True)
@given(n_groups=st.integers(2, 6), per_group=st.integers(1, 12), radius=st.floats(20.0, 300.0),
       spacing=st.floats(0.3, 3.0), seed=st.integers(0, 2**31 - 1))
def test_property_a_half_turn_plan_keeps_every_pair_at_its_start_distance(n_groups, per_group, radius, spacing, seed):
    """Given groups on grids around a centre, each flying to the mirror image of its centroid, when the
    rigid plan is flown, then no pair is ever closer than at the start, and everyone ends in its slot."""
    rng = np.random.default_rng(seed)
    pos, sites, _, centre = _groups_around_a_centre(rng, n_groups, per_group, radius, spacing)
    d0, _ = cKDTree(pos).query(pos, k=2)
    if d0[:, 1].min() < 0.2:                       # groups that overlap at the start are not a scenario
        return
    plan = rigid_plan_for(_states(pos, rng), sites, 0.5, COST, 4.0, 0.5)
    assert plan is not None and plan.kind == "turn"
    assert _min_distance_over(plan) >= d0[:, 1].min() - 1e-9
    s_end, _ = plan.at(plan.T + 60.0)
    assert np.max(np.abs(s_end[:, :2] - plan.slots_m)) < 1e-6
    assert np.allclose(plan.slots_m, 2 * centre - pos)


def test_limits_and_profile():
    assert trapezoid(10.0, 4.0, 0.5, 0.0) == (0.0, 0.0, 0.0)
    x, v, a = trapezoid(10.0, 4.0, 0.5, 1e9)
    assert (x, v, a) == (10.0, 0.0, 0.0)
    sc = make_scenario("circle", 200, seed=0)
    plan = rigid_plan_for(_states(sc.initial_pos_m, np.random.default_rng(1), v=(0.0, 0.0), spread=0.0), sc.destination_m,
                          0.5, COST, 4.0, 0.5)
    for t in np.arange(0.0, plan.T, 0.25):
        s, a = plan.at(t)
        assert np.max(np.linalg.norm(s[:, 2:4], axis=1)) <= 4.0 + 1e-9
        assert np.max(np.linalg.norm(a, axis=1)) <= 0.5 * np.sqrt(2) + 1e-9        # tangential and centripetal, each <= a/2


@pytest.mark.parametrize("name,translation", [("swap4", False), ("paper", True)])
def test_the_plan_command_held_over_each_step_reproduces_the_plan_samples(name, translation):
    # given a half turn (airborne start: the common wind offset too) and a one-group translation from rest, and
    # eq. 9 without noise driven by the plan's command held over each control step (the autopilot's zero-order
    # hold), in Euler sub-steps of 0.01 s (the plant's 0.1 s add their own lag, below)
    from mock_vehicle.plant import WindParams, euler_maruyama_step
    sc = make_scenario(name, 36, seed=3)
    v = (0.0, 0.0) if translation else (1.0, -1.0)
    plan = rigid_plan_for(_states(sc.initial_pos_m, np.random.default_rng(5), v=v, spread=0.0), sc.destination_m, 0.5,
                          COST, 4.0, 0.5, translation=translation)
    wind = WindParams(c0_per_s=COST.c0_per_s, mean_wind_m_s=tuple(COST.v_o), wind_diffusion_m_s=((0.0, 0.0), (0.0, 0.0)))
    x = plan.states.copy()
    dv, dr1 = [], None
    for k in range(int(plan.T / 0.5) + 4):
        a = plan.action()
        for _ in range(50):
            x = euler_maruyama_step(x, a, 0.01, wind, np.zeros((x.shape[0], 2)))
        plan.advance()
        dv.append(float(np.max(np.linalg.norm(x[:, 2:4] - plan.states[:, 2:4], axis=1))))
        if dr1 is None:
            dr1 = float(np.max(np.linalg.norm(x[:, 0:2] - plan.states[:, 0:2], axis=1)))
    # then the velocities stay on the plan's samples to within 1 cm/s with no feedback at all, and the first step
    # ends within a centimetre of the plan (the acceleration at the instant t_k instead, 0 at a trapezoid's start,
    # left the UAVs 0.25 m/s and 6 cm behind after it). What remains is explicit Euler's: its drag sees the sub-steps'
    # start velocities, and its position update lags a constant acceleration a by (dt h / 2) a per step (0.025 a with
    # the plant's h = 0.1 s); the feedback absorbs both.
    assert max(dv) < 0.01, max(dv)
    assert dr1 < 0.01, dr1


def test_only_a_half_turn_gets_a_rigid_plan():
    rng = np.random.default_rng(0)
    for name, expected in (("crossing", "turn"), ("swap4", "turn"), ("circle", "turn"), ("paper", None), ("dense", None),
                           ("merge", None), ("random", None)):
        sc = make_scenario(name, 40, seed=2)
        plan = rigid_plan_for(_states(sc.initial_pos_m, rng), sc.destination_m, 0.5, COST, 4.0, 0.5)
        assert (None if plan is None else plan.kind) == expected, name


def test_the_plan_is_the_same_on_every_vehicle():
    sc = make_scenario("swap4", 64, seed=1)
    S0 = _states(sc.initial_pos_m, np.random.default_rng(4))
    a, b = (rigid_plan_for(S0.copy(), sc.destination_m, 0.5, COST, 4.0, 0.5) for _ in range(2))
    for k in range(0, 200, 17):
        a.k = b.k = k
        np.testing.assert_array_equal(a.states, b.states)
        np.testing.assert_array_equal(a.action(), b.action())


@pytest.mark.parametrize("name,n,seed,extra", [
    ("crossing", 64, 21, []), ("swap4", 48, 22, []), ("circle", 40, 23, []),
    ("crossing", 50, 110, ["--fail-vehicle", "10", "--fail-at", "20"]),
    ("swap4", 64, 24, ["--gust"]),
])
def test_half_turn_families_fly_without_collision(tmp_path, name, n, seed, extra):
    """Sizes and seeds the plan was not tuned on (it has nothing tuned to them): 0 collided pairs,
    everyone arrives (but a failed vehicle), separation >= half the start spacing."""
    out = tmp_path / name
    proc = subprocess.run([sys.executable, "-m", "mfg_swarm.cli", "sim", "--scenario", name, "--n", str(n), "--seed", str(seed),
                           "--steps", "300", "--out", str(out), "--no-progress", *extra], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    m = json.loads((out / "metrics.json").read_text())
    assert m["collision_pairs"] == 0
    assert (m.get("arrived_fraction_others") or m["arrived_fraction"]) == 1.0
    assert m["min_separation_m"] >= 0.5 * m["start_spacing_m"] or "--fail-vehicle" in extra or "--gust" in extra


@settings(max_examples=25, deadline=None, derandomize=True)
@given(n=st.integers(2, 400), spacing=st.floats(0.3, 2.0), cruise=st.floats(0.0, 3.0), dist=st.floats(5.0, 400.0),
       bearing=st.floats(0.0, 2 * np.pi))
def test_property_the_translation_spreads_in_cruise_as_a_similarity(n, spacing, cruise, dist, bearing):
    """Given one group on a grid flying dist to its site with a cruise spacing, when the translation plan spreads:
    then every pairwise distance only grows until the spread is complete and only shrinks after the plan starts closing,
    never below its start value; the neighbours are max(1, min(cruise / spacing, what fits in the flight time)) x their
    start distance apart in between; the plan ends on the slots at rest; and no particle accelerates by more than the
    translation's and the spread's limits added (0.5 m/s^2 each)."""
    pos = make_scenario("paper", n, 0).initial_pos_m
    pos = (pos - pos.mean(axis=0)) * (spacing / np.sqrt(2.0))
    site = dist * np.array([np.cos(bearing), np.sin(bearing)])
    plan = rigid_plan_for(np.concatenate([pos, np.zeros_like(pos)], axis=1), np.tile(site, (n, 1)), 0.5, COST, 4.0, 0.5,
                          translation=True, cruise_spacing_m=cruise)
    assert plan is not None and plan.kind == "translation"
    i, j = np.triu_indices(n, 1)
    d0 = np.linalg.norm(pos[i] - pos[j], axis=1)
    lam_c = plan.cruise_scale
    assert 1.0 <= lam_c <= max(1.0, cruise / spacing) + 1e-9
    assert 2.0 * plan.T_spread <= plan.T + 1e-9
    prev, t_prev = d0, 0.0
    for t in np.arange(0.0, plan.T + 2.0, 0.25):
        s, a = plan.at(t)
        d = np.linalg.norm(s[i, 0:2] - s[j, 0:2], axis=1)
        assert np.all(d >= d0 - 1e-9)
        assert np.all(d <= lam_c * d0 * (1 + 1e-9))
        if t <= plan.T_spread:
            assert np.all(d >= prev - 1e-9)
        elif t >= plan.T - plan.T_spread:
            if t_prev >= plan.T - plan.T_spread:
                assert np.all(d <= prev + 1e-9)
        else:
            np.testing.assert_allclose(d, lam_c * d0, rtol=1e-9)
        assert np.max(np.linalg.norm(a, axis=1)) <= 1.0 + 1e-9
        prev, t_prev = d, t
    s_end, _ = plan.at(plan.T + 1.0)
    np.testing.assert_allclose(s_end[:, 0:2], plan.slots_m, atol=1e-9)
    np.testing.assert_allclose(s_end[:, 2:4], 0.0, atol=1e-12)


def test_the_dense_pad_spreads_to_the_cruise_spacing_and_closes_before_the_site():
    """dense N = 1,000 (0.5 m grid, 180 m flight): the plan reaches the default cruise spacing (2.1 m) between
    neighbours and holds it through the middle of the flight (the gust window of --gust, 20-25 s, included)."""
    from mfg_autopilot.guidance.params import DEFAULT
    cruise = DEFAULT.cruise_spacing_m
    assert cruise == pytest.approx(2.1)
    sc = make_scenario("dense", 1000, 1)
    S0 = np.concatenate([sc.initial_pos_m, np.zeros((1000, 2))], axis=1)
    plan = rigid_plan_for(S0, sc.destination_m, 0.5, COST, 4.0, 0.5, translation=True, cruise_spacing_m=cruise)
    assert plan.cruise_scale == pytest.approx(cruise / 0.5)
    assert plan.T_spread < 20.0
    for t, want in ((0.0, 0.5), (20.0, cruise), (25.0, cruise), (plan.T + 1.0, 0.5)):
        s, _ = plan.at(t)
        d, _ = cKDTree(s[:, :2]).query(s[:, :2], k=2)
        assert d[:, 1].min() == pytest.approx(want, rel=1e-6), t


def test_the_dense_pad_at_ten_thousand_spreads_nearly_to_the_cruise_spacing_before_the_gust_window():
    """dense N = 10,000 (0.5 m grid, 35 m from its centroid to its corners, 53 s of flight): at the spread's 1.5 m/s
    the pad reached only 1.0 m, still growing through the --gust window (20-25 s), and flew that gust 0.21 m apart
    (below half its start spacing). At 3 m/s at the farthest particle: >= 1.2 m at 20 s, 1.38 m from 26.5 s, the same
    0.5 m/s^2; distances still only grow (a similarity) and the speed the spread adds stays within 3 m/s."""
    from mfg_autopilot.guidance.params import DEFAULT
    sc = make_scenario("dense", 10000, 1)
    S0 = np.concatenate([sc.initial_pos_m, np.zeros((10000, 2))], axis=1)
    plan = rigid_plan_for(S0, sc.destination_m, 0.5, COST, 4.0, 0.5, translation=True,
                          cruise_spacing_m=DEFAULT.cruise_spacing_m)
    assert plan.spacing_m * plan.cruise_scale >= 1.35
    tree_min = lambda s: cKDTree(s[:, :2]).query(s[:, :2], k=2)[0][:, 1].min()     # noqa: E731
    assert tree_min(plan.at(20.0)[0]) >= 1.2
    assert tree_min(plan.at(25.0)[0]) >= 1.35
    t = np.linspace(0.0, plan.T_spread, 60)
    rate = np.array([plan._scale(x)[1] for x in t])
    assert np.all(rate >= 0.0) and rate.max() * plan.spread_rho_m <= 3.0 + 1e-9


@settings(max_examples=20, deadline=None, derandomize=True)
@given(n_groups=st.integers(2, 5), per_group=st.integers(1, 40), radius=st.floats(10.0, 150.0),
       spacing=st.floats(0.3, 2.0), cruise=st.floats(0.0, 4.0), seed=st.integers(0, 2**31 - 1))
def test_property_the_half_turn_spreads_each_group_and_keeps_every_pair_apart(n_groups, per_group, radius, spacing,
                                                                              cruise, seed):
    """Given groups on grids around a centre, each flying to the mirror image of its centroid, with a cruise spacing:
    when the half turn spreads each group about its own centroid (``RigidPlan._init_group_offsets``), then no pair -
    inside a group or between groups - is ever closer than the smallest start distance; inside a group the neighbours
    are cruise_scale x their start distance apart in the middle of the flight, where cruise_scale <= cruise / spacing;
    the plan ends on its slots at rest; and its velocity and acceleration are the derivatives of its positions
    (central differences, 1e-3 s, inside the spread's moves and in the middle of the turn)."""
    rng = np.random.default_rng(seed)
    pos, sites, grp, _ = _groups_around_a_centre(rng, n_groups, per_group, radius, spacing)
    d0, _ = cKDTree(pos).query(pos, k=2)
    if d0[:, 1].min() < 0.2:                       # groups that overlap at the start are not a scenario
        return
    s0 = float(d0[:, 1].min())
    plan = rigid_plan_for(_states(pos, rng), sites, 0.5, COST, 4.0, 0.5, cruise_spacing_m=cruise)
    assert plan is not None and plan.kind == "turn"
    assert 1.0 <= plan.cruise_scale <= max(1.0, cruise / s0) + 1e-9
    assert 2.0 * plan.T_spread <= plan.T + 1e-9
    assert _min_distance_over(plan, dt=0.25) >= s0 - 1e-9
    same = grp[:, None] == grp[None, :]
    i, j = np.nonzero(np.triu(same, 1))
    if i.size:
        mid, _ = plan.at(0.5 * plan.T)
        np.testing.assert_allclose(np.linalg.norm(mid[i, :2] - mid[j, :2], axis=1),
                                   plan.cruise_scale * np.linalg.norm(pos[i] - pos[j], axis=1), rtol=1e-9)
    for t in (0.37 * plan.T_spread, 0.5 * plan.T, plan.T - 0.41 * plan.T_spread) if plan.T_spread > 0.0 else (0.5 * plan.T,):
        h = 1e-3
        (sm, am), (s1, a1), (sp, ap) = plan.at(t - h), plan.at(t), plan.at(t + h)
        np.testing.assert_allclose((sp[:, :2] - sm[:, :2]) / (2 * h), s1[:, 2:4], atol=1e-5)
        np.testing.assert_allclose((sp[:, 2:4] - sm[:, 2:4]) / (2 * h), a1, atol=1e-3)
    s_end, _ = plan.at(plan.T + 60.0)
    np.testing.assert_allclose(s_end[:, :2], plan.slots_m, atol=1e-6)


def test_the_half_turn_spreads_to_the_default_cruise_spacing_where_the_groups_leave_room():
    """crossing / swap4 at N = 1,000 (groups far apart): each group reaches the default cruise spacing between its
    neighbours in the middle of the turn; crossing N = 10,000 (two 5,000-UAV grids whose discs would meet) keeps its
    start spacing (the disc certificate refuses a spread); circle (one UAV per group) has nothing to spread."""
    from mfg_autopilot.guidance.params import DEFAULT
    cruise = DEFAULT.cruise_spacing_m
    for name, n, want in (("crossing", 1000, cruise), ("swap4", 1000, cruise), ("crossing", 10000, np.sqrt(2.0)),
                          ("circle", 300, np.sqrt(2.0))):
        sc = make_scenario(name, n, 3)
        S0 = np.concatenate([sc.initial_pos_m, np.zeros((n, 2))], axis=1)
        plan = rigid_plan_for(S0, sc.destination_m, 0.5, COST, 4.0, 0.5, cruise_spacing_m=cruise)
        s, _ = plan.at(0.5 * plan.T)
        d, _ = cKDTree(s[:, :2]).query(s[:, :2], k=2)
        assert d[:, 1].min() == pytest.approx(want, rel=1e-6), name
