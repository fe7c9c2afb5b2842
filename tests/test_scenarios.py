"""Scenario families (issue 18): seeded, sized, spaced as stated, and refused when they cannot be flown."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from mfg_swarm.metrics import collisions
from mfg_swarm.scenarios import SCENARIOS, ScenarioError, check_flyable, make_scenario

FAMILIES = sorted(SCENARIOS)


@pytest.mark.parametrize("name", FAMILIES)
@pytest.mark.parametrize("n", [4, 37, 300])
def test_every_family_has_n_vehicles_and_the_spacing_it_states(name, n):
    sc = make_scenario(name, n, seed=11)
    assert sc.initial_pos_m.shape == (n, 2) and sc.destination_m.shape == (n, 2) and sc.group.shape == (n,)
    assert np.all(np.isfinite(sc.initial_pos_m)) and np.all(np.isfinite(sc.destination_m))
    d = np.linalg.norm(sc.initial_pos_m[:, None] - sc.initial_pos_m[None], axis=2) + np.eye(n) * 1e9
    assert d.min() == pytest.approx(sc.min_start_spacing_m)
    s = sc.slots_m
    ds = np.linalg.norm(s[:, None] - s[None], axis=2) + np.eye(n) * 1e9
    assert ds.min() == pytest.approx(sc.slot_spacing_m)
    assert sc.min_start_spacing_m >= 0.5 - 1e-9 and sc.slot_spacing_m >= 0.5 - 1e-9    # dense is the tightest (0.5 m)


@pytest.mark.parametrize("name", ["swap4", "circle", "merge", "random"])
def test_seeded_families_repeat_for_a_seed(name):
    a, b = make_scenario(name, 64, seed=5), make_scenario(name, 64, seed=5)
    assert np.array_equal(a.initial_pos_m, b.initial_pos_m) and np.array_equal(a.destination_m, b.destination_m)


@pytest.mark.parametrize("name", ["merge", "random"])
def test_random_families_differ_between_seeds(name):
    a, b = make_scenario(name, 64, seed=1), make_scenario(name, 64, seed=2)
    assert not np.array_equal(a.initial_pos_m, b.initial_pos_m)


def test_family_shapes():
    sw = make_scenario("swap4", 100, seed=0)
    assert len(set(sw.group.tolist())) == 4
    centres = np.array([sw.initial_pos_m[sw.group == g].mean(axis=0) for g in range(4)])
    for g in range(4):                                                     # each group to the opposite side
        assert np.allclose(sw.destination_m[sw.group == g], -centres[g], atol=1e-9)
    ci = make_scenario("circle", 50, seed=0)
    assert np.allclose(ci.destination_m, -ci.initial_pos_m)               # antipodes
    r = np.linalg.norm(ci.initial_pos_m, axis=1)
    assert np.allclose(r, r[0])
    me = make_scenario("merge", 60, seed=3)
    assert 2 <= len(set(me.group.tolist())) <= 6
    start_r = np.linalg.norm(me.initial_pos_m, axis=1)
    site_r = np.linalg.norm(me.destination_m, axis=1)
    assert start_r.min() >= 70.0 and site_r.max() < 0.5 * start_r.min()      # every source converges on the centre area
    de = make_scenario("dense", 100)                                      # packed on a pad: at rest, not airborne
    assert de.initial_vel_m_s is not None and np.all(de.initial_vel_m_s == 0.0) and de.initial_vel_m_s.shape == (100, 2)
    assert make_scenario("paper", 100).initial_vel_m_s is None             # the paper's start: each UAV at its wind velocity
    ra = make_scenario("random", 200, seed=4)
    assert len({tuple(s) for s in ra.destination_m.tolist()}) < len(set(ra.group.tolist()))     # groups share sites
    assert ra.min_start_spacing_m >= 1.5


def test_a_scenario_that_cannot_be_flown_is_refused_naming_what_and_the_bound():
    check_flyable(make_scenario("dense", 16), 0.2)                       # 0.5 m spacing, 0.4 m clearance: flyable
    with pytest.raises(ScenarioError, match=r"'dense' \(N = 16\).*start spacing 0.500 m is below twice the safety radius \(0.600 m\)"):
        check_flyable(make_scenario("dense", 16), 0.3)


def test_unknown_scenario_names_the_known_ones():
    with pytest.raises(ValueError, match="known: circle, crossing, dense, merge, paper, random, swap4"):
        make_scenario("spiral", 10)


def test_the_cli_refuses_an_unflyable_scenario_before_flying(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "mfg_swarm.cli", "sim", "--scenario", "dense", "--n", "16", "--safety-radius-m", "0.3",
                           "--out", str(tmp_path / "o")], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2 and "cannot be flown safely" in proc.stderr
    assert not (tmp_path / "o" / "metrics.json").exists()


@pytest.mark.parametrize("name", ["swap4", "circle", "merge", "random"])
def test_a_new_family_flies_in_the_simulator_and_reports_the_safety_metrics(tmp_path, name):
    out = tmp_path / name
    proc = subprocess.run([sys.executable, "-m", "mfg_swarm.cli", "sim", "--scenario", name, "--n", "24", "--seed", "3", "--steps", "40",
                           "--out", str(out), "--no-progress"], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    m = json.loads((out / "metrics.json").read_text())
    sc = make_scenario(name, 24, seed=3)
    assert m["start_spacing_m"] == pytest.approx(sc.min_start_spacing_m) and m["slot_spacing_m"] == pytest.approx(sc.slot_spacing_m)
    assert m["min_separation_m"] == m["min_pair_distance_m"] <= sc.min_start_spacing_m + 1e-9
    i, j, k = m["closest_pair"]
    pos = np.load(out / "trajectories.npz")["pos_m"]
    col = collisions(pos)
    assert tuple(m["closest_pair"]) == col["closest_pair"] and i < j and 0 <= k < pos.shape[0]
    assert m["safety_interventions"] == m["backstop_activations"] >= 0
    # the certified plan's guarantee, checked on this flight: the plan keeps its clearance, the UAVs its bound
    g = m["guarantee"]
    assert g["certified"] is True and g["uavs"] == 24 and g["min_separation_m"] == pytest.approx(m["min_separation_m"])
    # (along straight step segments: a turning pair's chord is shorter than its distance, by < 0.1 % here)
    assert g["plan_min_separation_m"] >= m["plan"]["clearance_m"] * (1 - 1e-3)
    assert 0.0 < g["tracking_error_max_m"] < 1.0
    assert g["min_separation_m"] >= g["separation_bound_m"] == pytest.approx(g["plan_min_separation_m"] - 2 * g["tracking_error_max_m"])


def test_the_guarantee_is_reported_for_plans_only(tmp_path):
    # HJB_d has no plan: no "guarantee" in its metrics
    out = tmp_path / "hjb"
    proc = subprocess.run([sys.executable, "-m", "mfg_swarm.cli", "sim", "--scenario", "paper", "--n", "9", "--mode", "hjb", "--range-m", "100",
                           "--steps", "4", "--out", str(out), "--no-progress"], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert "guarantee" not in json.loads((out / "metrics.json").read_text())


def test_closest_pair_is_found_between_samples():
    """Two vehicles passing through each other between two samples: the minimum is on the segment."""
    pos = np.array([[[0.0, 0.0], [10.0, 0.05]], [[10.0, 0.0], [0.0, 0.05]], [[20.0, 0.0], [-10.0, 0.05]]])
    col = collisions(pos)
    assert col["min_pair_distance_m"] == pytest.approx(0.05) and col["closest_pair"] == (0, 1, 0)
    assert col["collision_pairs"] == 1


@pytest.mark.parametrize("name,n", [("paper", 25), ("crossing", 16), ("dense", 9), ("swap4", 36), ("circle", 12), ("merge", 30)])
def test_a_grid_scenario_becomes_a_field_mission_with_the_same_starts_and_sites(name, n):
    from mfg_swarm.scenarios import mission_of_scenario, scenario_from_mission

    sc = make_scenario(name, n)
    m = mission_of_scenario(sc, on_arrival="land")
    back = scenario_from_mission(m)
    assert m.n == n and m.on_arrival == "land"
    assert np.allclose(back.initial_pos_m, sc.initial_pos_m, atol=1e-6)
    assert np.allclose(back.destination_m, sc.destination_m, atol=1e-6)


@pytest.mark.parametrize("name,why", [("random", "square grid")])
def test_a_scenario_a_mission_file_cannot_describe_is_refused(name, why):
    from mfg_autopilot.mission import MissionError
    from mfg_swarm.scenarios import mission_of_scenario

    with pytest.raises((ScenarioError, MissionError), match=why):
        mission_of_scenario(make_scenario(name, 16, seed=0))
