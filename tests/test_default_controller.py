"""The default preset (issue 7): bank-of-1 == bank-of-N, the backstop, the plan, and the
must-show flights on a representative subset (the full sweep: bench/default_controller_sweep.py)."""

import dataclasses

from _traced import TRACED_CRUISE_SPACING_M
import numpy as np
import pytest
from scipy.spatial import cKDTree

from mfg_autopilot.guidance.params import DefaultPreset, TrackingParams
from mfg_autopilot.guidance.planner import MeanFieldPlan, slots_from_sites
from mfg_autopilot.interface import Neighbours, Observation
from mfg_autopilot.presets import make_controller, preset_by_name, with_inner_loop
from mfg_autopilot.safety.backstop import apply_backstop, backstop_acc, escape_acc
from mfg_autopilot.safety.params import BackstopParams
from mfg_swarm.scenarios import make_scenario
from mfg_swarm.sim import GustParams, SimConfig, as_f32, plant_params_for, simulate
from mock_vehicle.plant import SwarmPlant

DEFAULT = preset_by_name("default")
# the held flight (TrackingParams.inner_loop off; the default since the twenty-eighth session): where a test stages a
# situation the held flight made and measures a rule against its absence there
HELD = with_inner_loop(DEFAULT, False)


def _fly(scenario, n, mode, seed=0, preset=DEFAULT, **kw):
    cfg = SimConfig(scenario=make_scenario(scenario, n), mode=mode, preset=preset, seed=seed, steps=200,
                    range_m=100.0 if mode == "hjb" else None, **kw)
    return simulate(cfg, progress=False)[1]


def _split(nb: Neighbours, row: int) -> Neighbours:
    m = nb.owner == row
    return Neighbours(nb.states[m], np.zeros(int(m.sum()), dtype=np.int64), None if nb.ids is None else nb.ids[m])


@pytest.mark.parametrize("rigid", [False, True])
def test_bank_of_one_gives_bit_identical_actions_to_a_bank_of_n(rigid):
    # given the crossing scenario (interacting plan: the groups meet at ~16 s, so the plan's repulsion
    # acts; rigid plan: the half turn) and one bank for all N next to N banks of one, fed the same
    # observations and sensor data
    from dataclasses import replace

    from mfg_autopilot.guidance.rigid_plan import RigidPlan

    preset = replace(DEFAULT, rigid_plan=rigid, group_plan=rigid)
    sc = make_scenario("crossing", 10)
    n = sc.n
    plant = SwarmPlant(sc.initial_pos_m, plant_params_for(preset), seed=3)
    S0 = as_f32(plant.states)
    ids = np.arange(n)
    bank = make_controller("mfg", preset, sc.destination_m)
    bank.exchange_t0(S0, ids, ids, sc.destination_m)
    assert isinstance(bank.plan, RigidPlan) == rigid
    singles = []
    for i in range(n):
        c = make_controller("mfg", preset, sc.destination_m[i:i + 1])
        c.exchange_t0(S0, ids, np.array([i]), sc.destination_m)
        singles.append(c)
    np.testing.assert_array_equal(bank.destinations_m, np.concatenate([c.destinations_m for c in singles]))
    rep_seen = False
    for k in range(60):
        obs = as_f32(plant.states)
        sensed = Neighbours.from_pairs(obs, cKDTree(obs[:, :2]).query_pairs(bank.sensor_range_m, output_type="ndarray"))
        a_bank = bank.step(Observation(k, k * preset.dt_s, obs, None, sensed)).acc_m_s2
        rep_seen |= bool(bank.plan.rep_active.any())
        a_single = np.concatenate([c.step(Observation(k, k * preset.dt_s, obs[i:i + 1], None, _split(sensed, i))).acc_m_s2
                                   for i, c in enumerate(singles)])
        # then every row's action is bit-identical
        np.testing.assert_array_equal(a_bank, a_single)
        plant.step(as_f32(a_bank), preset.dt_s)
    np.testing.assert_array_equal(bank.w_H, np.concatenate([c.w_H for c in singles]))
    assert rep_seen or rigid, "the test should cover the plan's interaction"


@pytest.mark.parametrize("K", [1, 3])
def test_prepare_act_finish_is_bit_identical_to_step(K):
    # given two banks of one on the crossing scenario with the learner's K HJB/FPK iterations per step:
    # one steps with step(obs), the other as a real-time loop does: prepare(k) at the tick, act(obs)
    # between the position and the setpoint, finish() after the setpoint (runtime.Autopilot)
    preset = dataclasses.replace(DEFAULT, learner=dataclasses.replace(DEFAULT.learner, K=K))
    sc = make_scenario("crossing", 10)
    plant = SwarmPlant(sc.initial_pos_m, plant_params_for(preset), seed=5)
    S0 = as_f32(plant.states)
    ids = np.arange(sc.n)
    whole, split = (make_controller("mfg", preset, sc.destination_m[2:3]) for _ in range(2))
    for c in (whole, split):
        c.exchange_t0(S0, ids, np.array([2]), sc.destination_m)
    bank = make_controller("mfg", preset, sc.destination_m)      # flies the others
    bank.exchange_t0(S0, ids, ids, sc.destination_m)
    for k in range(40):
        obs = as_f32(plant.states)
        sensed = Neighbours.from_pairs(obs, cKDTree(obs[:, :2]).query_pairs(bank.sensor_range_m, output_type="ndarray"))
        o = Observation(k, k * preset.dt_s, obs[2:3], None, _split(sensed, 2))
        a_whole = whole.step(o)
        split.prepare(k)
        split.prepare(k)                                    # idempotent
        a_split = split.act(o)
        w_F_before = split.w_F.copy()
        # act() leaves the last FPK update and the plan's advance to finish()
        assert split.plan.k == k
        split.finish()
        split.finish()                                      # nothing pending: a no-op
        # then the action, the step's counters and both models are bit-identical
        for f in ("acc_m_s2", "grad_evals", "reg_active", "residual", "mf_evals"):
            np.testing.assert_array_equal(getattr(a_whole, f), getattr(a_split, f))
        np.testing.assert_array_equal(whole.w_H, split.w_H)
        np.testing.assert_array_equal(whole.w_F, split.w_F)
        assert k == 0 or not np.array_equal(w_F_before, split.w_F)
        assert split.plan.k == whole.plan.k == k + 1
        a = bank.step(Observation(k, k * preset.dt_s, obs, None, sensed)).acc_m_s2
        plant.step(as_f32(a), preset.dt_s)


def test_act_before_exchange_and_act_twice_without_finish_are_clear_errors():
    c = make_controller("mfg", DEFAULT, np.zeros((1, 2)))
    own = np.array([[150.0, 100.0, 0.0, 0.0]])
    with pytest.raises(RuntimeError, match="t = 0 exchange"):
        c.act(Observation(0, 0.0, own))
    c.exchange_t0(own, np.array([0]), np.array([0]), np.zeros((1, 2)))
    c.act(Observation(0, 0.0, own))
    with pytest.raises(RuntimeError, match="not finished"):
        c.act(Observation(1, 0.5, own))
    c.finish()
    c.act(Observation(1, 0.5, own))


def test_slots_are_site_plus_offset_from_the_group_centroid():
    pos = np.array([[0.0, 0.0], [2.0, 0.0], [10.0, 10.0], [12.0, 14.0]])
    sites = np.array([[5.0, 5.0], [5.0, 5.0], [-1.0, 0.0], [-1.0, 0.0]])
    np.testing.assert_allclose(slots_from_sites(pos, sites), [[4.0, 5.0], [6.0, 5.0], [-2.0, -2.0], [0.0, 2.0]])


def test_plan_is_deterministic_and_arrives_without_conflicts():
    sc = make_scenario("crossing", 20)
    S0 = as_f32(SwarmPlant(sc.initial_pos_m, plant_params_for(DEFAULT), seed=0).states)
    p, q = (MeanFieldPlan(S0, sc.destination_m, DEFAULT.dt_s, DEFAULT.cost, DEFAULT.guidance, DEFAULT.repulsion) for _ in range(2))
    dmin = np.inf
    for _ in range(160):
        np.testing.assert_array_equal(p.action(), q.action())
        p.advance(); q.advance()
        dmin = min(dmin, cKDTree(p.states[:, :2]).query(p.states[:, :2], k=2)[0][:, 1].min())
    assert dmin > 0.3, dmin                     # the plan keeps its pairs apart (radius 0.71 m here)
    assert np.max(np.linalg.norm(p.states[:, :2] - p.slots_m, axis=1)) < 0.05


def test_backstop_is_inactive_for_a_dense_hovering_neighbour_and_pushes_away_on_a_head_on_approach():
    bp = BackstopParams()
    own = np.array([[0.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]])
    # given row 0 with a hovering neighbour 0.5 m away (the dense slot spacing), row 1 with a
    # vehicle 3 m ahead closing head-on at 2 m/s
    sensed = np.array([[0.5, 0.0, 0.0, 0.0], [3.0, 0.0, -1.0, 0.0]])
    da = backstop_acc(own, sensed, np.array([0, 1]), bp)
    assert np.all(da[0] == 0.0)
    assert np.linalg.norm(da[1]) > 0 and da[1, 0] <= 0.0 and da[1, 1] != 0.0      # brakes and sidesteps
    a_nom = np.array([[0.3, 0.0], [1.9, 0.0]])
    a, act = apply_backstop(a_nom, da, bp.a_max_m_s2)
    np.testing.assert_array_equal(a[0], a_nom[0])                                  # unchanged where inactive
    assert list(act) == [False, True] and np.linalg.norm(a[1]) <= bp.a_max_m_s2 + 1e-12


def _min_dist_const_acc(own, a, other, horizon_s=2.0, dt_s=0.05):
    """Smallest distance over the horizon: own under constant acceleration a, other at constant velocity."""
    t = np.arange(1, int(horizon_s / dt_s) + 1) * dt_s
    p = own[:2] + own[2:] * t[:, None] + 0.5 * a * t[:, None] ** 2
    q = other[:2] + other[2:] * t[:, None]
    return float(np.min(np.linalg.norm(p - q, axis=1)))


def test_escape_is_inactive_without_a_threat_in_the_way():
    bp = BackstopParams()
    own = np.array([[0.0, 0.0, 4.0, 0.0]])
    a_nom = np.array([[0.2, -0.1]])
    # given a hovering (unplanned) vehicle 3 m to the side and a planned one 0.6 m ahead flying along
    sensed = np.array([[0.0, 3.0, 0.0, 0.0], [0.6, 0.0, 4.0, 0.0]])
    a, act = escape_acc(own, a_nom, sensed, np.array([0, 0]), np.array([True, False]), np.array([0.6, 0.0]),
                        np.array([0.8, 0.5]), bp, 0.5)
    # then the command is unchanged (minimal intervention: a planned vehicle alone never triggers it)
    assert not act[0]
    np.testing.assert_array_equal(a, a_nom)


def test_escape_avoids_a_hovering_vehicle_ahead_without_turning_into_a_planned_neighbour():
    bp = BackstopParams()
    # given own row flying +x at 4 m/s, a failed vehicle hovering 5 m ahead (slightly to the left), and a
    # planned neighbour 1.4 m to the right flying alongside: the escape must pass the failed one on the left
    own = np.array([[0.0, 0.0, 4.0, 0.0]])
    failed = np.array([5.0, 0.1, 0.0, 0.0])
    nb = np.array([0.0, -1.4, 4.0, 0.0])
    a_nom = np.zeros((1, 2))
    a, act = escape_acc(own, a_nom, np.stack([failed, nb]), np.array([0, 0]), np.array([True, False]),
                        np.array([0.6, 0.0]), np.array([0.8, 0.5]), bp, 0.5)
    assert act[0] and np.linalg.norm(a[0]) <= bp.a_max_m_s2 + 1e-12
    # then the predicted closest approach to the failed vehicle opens (coasting would hit it), and it
    # does not buy that by flying into the neighbour
    assert _min_dist_const_acc(own[0], a_nom[0], failed) < 0.2
    assert _min_dist_const_acc(own[0], a[0], failed) > _min_dist_const_acc(own[0], a_nom[0], failed) + 0.3
    # the full-authority sidestep to the right would put it into the neighbour's lane (test is meaningful) ...
    assert _min_dist_const_acc(own[0], np.array([0.0, -2.0]), nb) < 0.1
    # ... the chosen command keeps the neighbour's clearance (0.5 m) under the same prediction
    assert _min_dist_const_acc(own[0], a[0], nb) >= 0.5, a


def test_a_gust_that_blows_everyone_alike_does_not_trigger_the_unplanned_response():
    # given the crossing plan, every vehicle 0.8 m and 1 m/s off its particle in the same direction (common
    # mode, as a uniform gust would leave them), sensed by its neighbours
    sc = make_scenario("crossing", 10)
    S0 = as_f32(SwarmPlant(sc.initial_pos_m, plant_params_for(DEFAULT), seed=0).states)
    ids = np.arange(sc.n)

    interacting = dataclasses.replace(DEFAULT, rigid_plan=False, group_plan=False)      # the plan whose groups pass through each other

    def backstop_rows(offset_fn, preset=interacting, k0=34):
        c = make_controller("mfg", preset, sc.destination_m)
        c.exchange_t0(S0, ids, ids, sc.destination_m)
        for k in range(k0):                                 # fly the plan to where the groups approach (17 s)
            c.plan.advance()
        obs = c.plan.states + offset_fn(c.plan.states)
        sensed = Neighbours.from_pairs(obs, cKDTree(obs[:, :2]).query_pairs(c.sensor_range_m, output_type="ndarray"))
        c.step(Observation(k0, k0 * DEFAULT.dt_s, obs, None, sensed))
        return c.backstop_active.copy()

    gust = lambda x: np.tile([0.8, 0.0, 1.0, 0.0], (x.shape[0], 1))     # noqa: E731
    assert not backstop_rows(gust).any()
    # (without the common-mode check every vehicle is 'unplanned' to every other and the approaching groups'
    # planned passes, closer than the unplanned trigger, set the escape off ...
    no_cm = dataclasses.replace(interacting, backstop=dataclasses.replace(DEFAULT.backstop, common_mode=False,
                                                                       escape_max_unplanned_fraction=1.0))
    assert backstop_rows(gust, no_cm).any()
    # ... unless a row that senses mostly off-plan vehicles falls back to the half-plane push, which leaves these
    # 0.7 m passes alone; the crowd's barrier filter, which replaces that push by default since the twentieth session,
    # does not: the groups pass through each other head-on, faster than a pair braking at 1 m/s^2 could stop, and it
    # brakes every row. Only the common-mode check, first above, keeps a uniform gust from making rows crowded)
    no_cm_crowd = dataclasses.replace(interacting, backstop=dataclasses.replace(DEFAULT.backstop, common_mode=False,
                                                                                crowd_cbf=False))
    assert not backstop_rows(gust, no_cm_crowd).any()
    no_cm_cbf = dataclasses.replace(interacting, backstop=dataclasses.replace(DEFAULT.backstop, common_mode=False))
    assert backstop_rows(gust, no_cm_cbf).all()
    # when instead one vehicle stops (vehicle 3, group A's front row: vehicle 0 flies 1.41 m behind it in its
    # lane) while the others fly the plan, the one behind reacts
    def one_stops(x):
        off = np.zeros_like(x)
        off[3, 2:4] = -x[3, 2:4]
        return off
    assert backstop_rows(one_stops, k0=30)[0]


@pytest.mark.parametrize("scenario,n,seed", [("paper", 25, 0), ("paper", 9, 1), ("crossing", 50, 0), ("dense", 81, 0)])
def test_default_mfg_flies_collision_free_into_every_slot_talking_once(scenario, n, seed):
    m = _fly(scenario, n, "mfg", seed)
    h = _fly(scenario, n, "hjb", seed)
    assert m["collision_pairs"] == 0, m["collided_pairs_list"]
    assert m["arrived_fraction"] == 1.0, m["final_distance_mean_m"]
    assert m["comm_states_per_uav"] == n - 1
    # MFG's motion energy: within 10 % of HJB_100's with the interacting plan; the rigid half turn of `crossing` flies
    # semicircles (pi / 2 times the straight line) for its separation by construction and pays up to 50 % more
    factor = 1.5 if scenario == "crossing" else 1.1
    assert m["motion_energy_per_uav"] <= factor * h["motion_energy_per_uav"], (m["motion_energy_per_uav"], h["motion_energy_per_uav"])
    if scenario != "dense":
        assert h["collision_pairs"] == 0, h["collided_pairs_list"]       # default HJB_100: paper and crossing
        assert h["comm_states_per_uav"] > 100 * (n - 1)


def test_default_hjb_crossing_seed_2_head_on_pair_is_kept_apart_by_the_heard_guard():
    # UAVs 8 and 44 meet head-on at t = 18 s, inside the repulsion radius and heard every step; the sum of the
    # pushes from the interleaving rows outweighed their own pair's push and they passed 0.046 m apart
    # (1 collided pair) before the guard on heard vehicles (hjb_repulsion.heard_guard_fraction)
    # (held, as measured: with the inner loop the pair passes 0.1 m apart without the guard too; both flights are flown)
    # (on the paper's plant, as measured: with PX4's lag, the default airframe, HJB_100 default collides here, UAVs 2 and
    # 33 at 0.068 m, and held 2 pairs: issue 18)
    for h in (_fly("crossing", 50, "hjb", 2, acc_lag_s=0.0), _fly("crossing", 50, "hjb", 2, preset=HELD, acc_lag_s=0.0)):
        assert h["collision_pairs"] == 0, h["collided_pairs_list"]
        assert h["arrived_fraction"] == 1.0
        assert h["min_pair_distance_m"] > 0.1
    off = dataclasses.replace(HELD, hjb_repulsion=dataclasses.replace(DEFAULT.hjb_repulsion, heard_guard_fraction=0.0))
    cfg = SimConfig(scenario=make_scenario("crossing", 50), mode="hjb", preset=off, seed=2, steps=200, range_m=100.0, acc_lag_s=0.0)
    m_off = simulate(cfg, progress=False)[1]
    assert m_off["collision_pairs"] >= 1          # the case still exercises the mechanism without the guard


def test_failed_vehicle_is_avoided_and_the_others_arrive():
    # vehicle 22 is the middle of group A's front row: the UAVs behind it in its row head straight at it
    m = _fly("crossing", 50, "mfg", 0, fail_vehicle=22, fail_at_s=10.0)
    assert m["failed_vehicle_collision_pairs"] == 0
    assert m["arrived_fraction_others"] == 1.0


def test_failed_vehicle_where_the_groups_cross_causes_no_collision_among_the_others():
    # vehicle 27 (middle of group B's front row) stops at 15 s, just before the formations pass through each
    # other; with the single half-plane response the UAVs pushed off their plan collided with the other group
    # (seed 1: 3 pairs among the others, none with vehicle 27)
    m = _fly("crossing", 50, "mfg", 1, fail_vehicle=27, fail_at_s=15.0)
    assert m["collision_pairs"] == 0, m["collided_pairs_list"]
    assert m["arrived_fraction_others"] == 1.0


def test_gust_beyond_v_o_is_applied_and_reported():
    calm = _fly("paper", 25, "mfg", 0)
    gust = _fly("paper", 25, "mfg", 0, gust=GustParams())
    assert gust["gust"]["acc_m_s2"] == 1.0
    assert gust["motion_energy_per_uav"] != calm["motion_energy_per_uav"]
    assert gust["collision_pairs"] == 0 and gust["arrived_fraction"] == 1.0


def test_dense_formation_in_a_gust_is_held_apart_by_the_relative_error_priority():
    # the 0.5 m grid flying its rigid translation *without* the spread in cruise (cruise_spacing_m = 0: the grid stays
    # 0.5 m), each UAV blown by its own 0.5-1.5 m/s^2 (+-30 deg) gust for 5 s. Not a safety promise at this spacing:
    # single pairs close below 0.1 m (docs/default_controller.md "Gusts"); what the relative-error priority does is
    # measured against each UAV fighting the gust alone to its own particle (seed 2: 25 collided pairs without it, 1
    # with it, smallest separation 0 m against 0.097 m). Held (no inner loop), as measured: with the inner loop each UAV
    # fights the gust inside the period and the grid keeps 3 pairs with the priority, 2 without
    tight = DefaultPreset(cruise_spacing_m=0.0, tracking=TrackingParams(inner_loop=False))
    # (the paper's plant, as this was measured: with PX4's lag this staged gust flight's test fails (its measure: 180 vs 63); issue 18)
    on = simulate(SimConfig(scenario=make_scenario("dense", 144), mode="mfg", preset=tight, seed=2, steps=200,
                            gust=GustParams(), acc_lag_s=0.0), progress=False)[1]
    alone = DefaultPreset(cruise_spacing_m=0.0, tracking=TrackingParams(relative_priority=False, inner_loop=False))
    off = simulate(SimConfig(scenario=make_scenario("dense", 144), mode="mfg", preset=alone, seed=2, steps=200,
                             gust=GustParams(), acc_lag_s=0.0), progress=False)[1]
    assert on["arrived_fraction"] == 1.0 and off["arrived_fraction"] == 1.0
    assert 10 * on["collision_pairs"] <= off["collision_pairs"], (on["collision_pairs"], off["collision_pairs"])
    assert on["min_separation_m"] > off["min_separation_m"] + 0.05


@pytest.mark.parametrize("n,seed", [(144, 2), (256, 11)])
def test_dense_pad_spreads_in_cruise_and_flies_a_gust_without_collision(n, seed):
    # the default preset: the 0.5 m pad spreads to the cruise spacing (2.1 m; 1.4 m until the thirty-third session) after
    # take-off and closes before the site, so the gust (20-25 s) meets neighbours that far apart; seeds and sizes the
    # spread was not measured on
    m = _fly("dense", n, "mfg", seed, gust=GustParams())
    assert m["collision_pairs"] == 0, m["collided_pairs_list"]
    assert m["arrived_fraction"] == 1.0
    assert m["min_separation_m"] >= 0.5 * m["start_spacing_m"], m["min_separation_m"]


def test_cli_fault_options_reach_the_simulator_and_bad_ones_are_clear_errors(tmp_path, capsys):
    import json

    from mfg_swarm.cli import main
    out = tmp_path / "f"
    assert main(["sim", "--scenario", "crossing", "--n", "6", "--steps", "6", "--fail-vehicle", "1", "--fail-at", "1.0",
                 "--gust", "--out", str(out), "--no-progress"]) == 0
    m = json.loads((out / "metrics.json").read_text())
    assert m["preset"] == "default" and m["fail_vehicle"] == 1 and m["gust"]["duration_s"] == 5.0
    assert main(["sim", "--n", "4", "--steps", "2", "--fail-vehicle", "4", "--out", str(tmp_path / "g"), "--no-progress"]) == 2
    assert "fail_vehicle" in capsys.readouterr().err


@pytest.mark.parametrize("fail_vehicle,fail_at_s,seed", [(40, 20.0, 2), (10, 15.0, 3)])
def test_failed_vehicle_in_the_dense_formation_is_avoided(fail_vehicle, fail_at_s, seed):
    # the 0.5 m formation at 4 m/s; the failed vehicle brakes at the full 2 m/s^2 into Hold in front of a UAV
    # ~1.1 m behind it, with neighbours 0.5 m to each side. Before the fix: seed 2 / vehicle 40 collided with
    # it (the follower's own 0.1 m deviation, used by the common-mode check, cleared it as 'planned'), seed 3 /
    # vehicle 10 too (the escape held each candidate over the whole 2 s horizon and sampled the approach only
    # every 0.1 s: it chose a half-authority sidestep that passed 6 cm from it)
    m = _fly("dense", 81, "mfg", seed, fail_vehicle=fail_vehicle, fail_at_s=fail_at_s)
    assert m["failed_vehicle_collision_pairs"] == 0, m["collided_pairs_list"]
    # (seed 2 / vehicle 40 still has one pair among the others, 0.088 m: the cascade of UAVs escaping around it)
    assert m["collision_pairs"] <= (1 if seed == 2 else 0), m["collided_pairs_list"]
    assert m["arrived_fraction_others"] == 1.0


def test_common_mode_check_does_not_clear_a_braking_vehicle_for_a_uav_on_its_particle():
    # given the dense plan in cruise, one vehicle braking (0.25 m and 1.05 m/s behind its particle, the state 0.5 s
    # after a failure into Hold) and every other UAV on its particle with a small velocity error along the braking
    # vehicle's deviation (0.2 m/s: normal tracking error)
    # (built on the interacting plan, where this case was measured; a single group now flies its rigid translation)
    sc = make_scenario("dense", 81)
    S0 = as_f32(SwarmPlant(sc.initial_pos_m, plant_params_for(DEFAULT), seed=2).states)
    ids = np.arange(sc.n)
    c = make_controller("mfg", dataclasses.replace(DEFAULT, rigid_translation=False), sc.destination_m)
    c.exchange_t0(S0, ids, ids, sc.destination_m)
    k0 = 40
    for _ in range(k0):
        c.plan.advance()
    x = c.plan.states
    v_hat = x[40, 2:4] / np.linalg.norm(x[40, 2:4])
    obs = x.copy()
    obs[:, 2:4] -= 0.2 * v_hat
    obs[40, 0:2] -= 0.25 * v_hat
    obs[40, 2:4] = x[40, 2:4] - 1.05 * v_hat
    sensed = Neighbours.from_pairs(obs, cKDTree(obs[:, :2]).query_pairs(c.sensor_range_m, output_type="ndarray"))
    sn = Neighbours(sensed.states, sensed.owner, sensed.ids)
    assert c._unplanned(sn.states, sn.ids)[sn.ids == 40].all()            # off the plan, as sensed
    c.step(Observation(k0, k0 * DEFAULT.dt_s, obs, None, sensed))
    # then the UAVs right behind it react (before: the shift by their own 0.2 m/s error cleared it)
    behind = [i for i in range(sc.n) if i != 40 and 0.5 < np.dot(obs[i, :2] - obs[40, :2], -v_hat) < 1.5
              and abs(v_hat[0] * (obs[i, 1] - obs[40, 1]) - v_hat[1] * (obs[i, 0] - obs[40, 0])) < 0.3]
    assert behind and c.backstop_active[behind].all(), (behind, c.backstop_active[behind])


def test_escape_checks_the_approach_between_its_samples():
    bp = BackstopParams()
    # given a threat passing at 8 m/s relative, 0.05 m to the side, whose closest approach falls between two
    # 0.1 s samples (t = 0.45 s coasting, 0.48 s braking): at the samples it is >= 0.15 m away, above the trigger
    own = np.array([[0.0, 0.0, 0.0, 0.0]])
    threat = np.array([[3.6, 0.05, -8.0, 0.0]])
    a, act = escape_acc(own, np.zeros((1, 2)), threat, np.array([0]), np.array([True]), np.array([0.12]),
                        np.array([0.3]), bp, 0.5)
    # then the escape acts (the approach is checked along each segment, as the collision metric does) and clears it
    assert act[0]
    assert _min_dist_const_acc(own[0], np.zeros(2), threat[0], dt_s=0.001) < 0.06
    assert _min_dist_const_acc(own[0], a[0], threat[0], dt_s=0.001) > 0.15


def _controller_in_cruise(scenario, n, k0, preset=DEFAULT, seed=0):
    """An MFG controller bank after the t = 0 exchange, its plan flown to step k0 (no vehicle acts)."""
    sc = make_scenario(scenario, n)
    S0 = as_f32(SwarmPlant(sc.initial_pos_m, plant_params_for(preset), seed=seed).states)
    ids = np.arange(sc.n)
    c = make_controller("mfg", preset, sc.destination_m)
    c.exchange_t0(S0, ids, ids, sc.destination_m)
    for _ in range(k0):
        c.plan.advance()
    return c


def test_an_off_plan_vehicle_moving_with_the_flow_gets_the_small_escape_reach_a_stopped_one_the_large():
    # given the crossing plan in cruise (4 m/s, 1.41 m apart) and three off-plan vehicles: one blown 0.7 m sideways
    # and 0.5 m/s off the flow (a gust), one stopped on its particle's place (failed in Hold), one that moves at the
    # flow's speed but 2.5 m/s off its direction
    c = _controller_in_cruise("crossing", 50, 40)
    bp = DEFAULT.backstop
    x = c.plan.states
    v = x[5, 2:4]
    assert np.linalg.norm(v) > 3.5                                      # in cruise (the test is meaningful)
    side = np.array([-v[1], v[0]]) / np.linalg.norm(v)
    blown = np.concatenate([x[5, 0:2] + 0.7 * side, v + 0.5 * side])
    stopped = np.concatenate([x[6, 0:2], [0.0, 0.0]])
    crossing = np.concatenate([x[7, 0:2] + 0.7 * side, v + 2.5 * side])
    q = np.stack([blown, stopped, crossing])
    assert c._unplanned(q).all()
    trig, clear = c._unplanned_reach(q, np.ones(3, dtype=bool), 0.6, 0.8)
    # then the blown one is escaped only when it comes within 0.25 m (it closes at the gust's relative speed), the
    # others at the full 0.6 m with 0.8 m clearance
    np.testing.assert_array_equal(trig, [bp.unplanned_flow_trigger_m, 0.6, 0.6])
    np.testing.assert_array_equal(clear, [bp.unplanned_flow_target_m, 0.8, 0.8])
    # where the plan itself is slow (parked before the start) every off-plan vehicle keeps the large reach
    c0 = _controller_in_cruise("crossing", 50, 0)
    x0 = c0.plan.states
    q0 = np.concatenate([x0[5, 0:2] + [0.7, 0.0], x0[5, 2:4]])[None, :]
    np.testing.assert_array_equal(c0._unplanned_reach(q0, np.ones(1, dtype=bool), 0.6, 0.8)[0], [0.6])
    # and the rule off (unplanned_flow_m_s = 0) gives the large reach to all
    off = dataclasses.replace(DEFAULT, backstop=dataclasses.replace(bp, unplanned_flow_m_s=0.0))
    c_off = _controller_in_cruise("crossing", 50, 40, preset=off)
    np.testing.assert_array_equal(c_off._unplanned_reach(q, np.ones(3, dtype=bool), 0.6, 0.8)[0], [0.6, 0.6, 0.6])


def test_a_vehicle_far_from_its_own_particle_is_unplanned_even_where_another_particle_passes_through_it():
    # given the circle plan in its turn and vehicle 3 sensed exactly in the state of vehicle 20's particle (a failed
    # vehicle that the stream left behind, on the path of vehicle 20): the nearest-particle test alone clears it
    c = _controller_in_cruise("circle", 40, 40)
    x = c.plan.states
    assert np.linalg.norm(x[3, 0:2] - x[20, 0:2]) > DEFAULT.backstop.plan_lost_m        # far from its own particle
    q = x[[20]].copy()
    assert not c._off_plan(q).any()
    # then, known by its id, it is unplanned; a vehicle within plan_lost_m of its own particle is judged as before
    assert c._unplanned(q, np.array([3])).all()
    assert not c._unplanned(q, np.array([20])).any()
    assert not c._unplanned(q).any()                                    # no id: only the nearest-particle test
    off = dataclasses.replace(DEFAULT, backstop=dataclasses.replace(DEFAULT.backstop, plan_lost_m=0.0))
    assert not _controller_in_cruise("circle", 40, 40, preset=off)._unplanned(q, np.array([3])).any()


@pytest.mark.parametrize("n,seed", [(300, 4), (300, 9)])
def test_crossing_half_turn_flies_a_gust_without_collision(n, seed):
    # the half turn takes more of the 2 m/s^2 than a straight flight: UAVs with the strongest gust saturate and drift
    # 1-2 m relative to their neighbours. Before the escape's reach followed the flow, seed 4 had 1 collided pair
    # (escapes from drifting neighbours carried UAVs through the formation); seed 9 was not flown before the change
    # (the paper's plant, as this was measured: with PX4's lag N = 300 seed 4 keeps 0.66 m, not half the spacing 0.71 m; issue 18)
    m = simulate(SimConfig(scenario=make_scenario("crossing", n), mode="mfg", preset=DEFAULT, seed=seed, steps=160,
                           gust=GustParams(), acc_lag_s=0.0), progress=False)[1]
    assert m["collision_pairs"] == 0, m["collided_pairs_list"]
    assert m["arrived_fraction"] == 1.0
    assert m["min_separation_m"] >= 0.5 * m["start_spacing_m"], m["min_separation_m"]


def test_failed_vehicle_on_a_path_into_a_slot_is_avoided_to_the_end_of_the_turn():
    # circle N = 1,000: vehicle 10 fails into Hold at 20 s; 170 s later UAV 548's particle slows through the place
    # where it holds, 0.7 m before 548's slot. Before the lost-to-the-plan rule the hovering vehicle passed as that
    # particle ("on the plan") and 548 tracked into it: 1 collided pair, 0.025 m
    # (measured with the PD Hold, the simulator's default until the twenty-fifth session: with PX4's Hold, the default
    # now, the vehicle holds elsewhere and even the counterfactual below keeps 0.187 m; the default flies both)
    def fly(preset, hold="pd"):
        # (the paper's plant, as this was measured: with PX4's lag the staged pair does not form; issue 18)
        return simulate(SimConfig(scenario=make_scenario("circle", 1000), mode="mfg", preset=preset, seed=6, steps=400,
                                  fail_vehicle=10, fail_at_s=20.0, hold_model=hold, acc_lag_s=0.0), progress=False)[1]
    # (held, as measured: the inner loop, the default, flies the counterfactual below without a pair; both are flown)
    for m in (fly(DEFAULT), fly(HELD), fly(DEFAULT, "px4")):
        assert m["collision_pairs"] == 0, m["collided_pairs_list"]
        assert m["arrived_fraction_others"] == 1.0
    # the case exercises the rule: without it, that pair (with the rules that came after it off as well - the yield,
    # the gap push and the crowded push's flow reach: the flight without the lost rule alone keeps 0.185 m, through
    # what the yields changed before, and with the yield off but the two others on it has no pair either; nor with the
    # eleventh session's trigger by the spacing now and lane side over keep-right, which are off by default; nor the
    # nineteenth session's safety-first escape, which alone keeps it clear; nor the twentieth's barrier filter for
    # crowded rows: with it on and every rule above off, the UAVs settling into the slots around the hovering vehicle
    # collide among themselves instead; and with every off-plan vehicle predicted braking to a stop, as before the
    # twenty-fourth session's measured braking hypothesis)
    off = fly(dataclasses.replace(HELD, backstop=dataclasses.replace(DEFAULT.backstop, plan_lost_m=0.0,
                                                                        escape_brake_hypothesis="threat",
                                                                        escape_yield=False, gap_push=False,
                                                                        push_flow_reach=False,
                                                                        escape_hard_fraction=0.0, crowd_cbf=False),
                                 detour=dataclasses.replace(DEFAULT.detour, enabled=False)))
    assert [10, 548] in off["collided_pairs_list"], off["collided_pairs_list"]


def _lane_mates(x, a):
    """In a plan in cruise: the particles right behind (b) and right ahead of (c) particle a, in its lane."""
    v_hat = x[a, 2:4] / np.linalg.norm(x[a, 2:4])
    dr = x[:, 0:2] - x[a, 0:2]
    along, across = dr @ v_hat, np.abs(dr @ np.array([-v_hat[1], v_hat[0]]))
    lane = np.flatnonzero(across < 0.2)
    behind, ahead = lane[along[lane] < -0.5], lane[along[lane] > 0.5]
    return behind[np.argmax(along[behind])], ahead[np.argmin(along[ahead])]


def _lane_in_cruise(preset, scenario=("crossing", 50, 40)):
    """A plan in flight, by default the crossing plan in cruise (N = 50, step 40): (controller bank, plan states, a, b,
    c, v_hat) for the first UAV a with lane mates behind (b) and ahead (c), v_hat its unit flight direction. The plan
    is the one these lanes were written for (tests/_traced.py): the crossing lanes 1.41 m apart, not spread to 2.1 m."""
    c_ = _controller_in_cruise(*scenario, preset=dataclasses.replace(preset, cruise_spacing_m=TRACED_CRUISE_SPACING_M))
    x = c_.plan.states.copy()
    for a in range(x.shape[0]):
        try:
            b, c = _lane_mates(x, a)
            break
        except ValueError:
            continue
    return c_, x, a, b, c, x[a, 2:4] / np.linalg.norm(x[a, 2:4])


def _act_once(c_, obs):
    """One control step of the bank on the observed states obs (every vehicle sensed within range): (sensed, info)."""
    sensed = Neighbours.from_pairs(obs, cKDTree(obs[:, :2]).query_pairs(c_.sensor_range_m, output_type="ndarray"))
    return sensed, c_.act(Observation(40, 40 * DEFAULT.dt_s, obs, None, sensed))


@pytest.mark.parametrize("scenario,failed", [(("crossing", 50, 40), False), (("dense", 100, 100), True)],
                         ids=["crossing-cruise", "dense-closing-near-a-failed-vehicle"])
def test_two_uavs_off_their_particles_that_close_on_each_other_get_the_gap_push(scenario, failed):
    # given the crossing plan in cruise (a rigid plan, 1.41 m apart), or the dense pad closing into its 0.5 m slots
    # (0.87 m apart at step 100) with a failed vehicle holding behind it, lost to the plan (dense --fail-vehicle
    # N = 10,000 seeds 6 and 7: UAVs escaping the failed vehicle ran into lane mates, neither acting, 0.021 / 0.085 m),
    # a gust that blew every UAV 1 m sideways, and two
    # lane mates a (behind) and c (ahead) of which c was blown 0.35 m further back and 0.1 m further aside and closes
    # on a at 0.65 m/s: each is off the plan the way the other is up to 0.49 m (state metric), so the common-mode check
    # clears it, and each is more than 0.1 m off its own particle, so the planned response is off: neither response
    # covers the pair (the gap; swap4 --gust N = 10,000 seed 8, UAVs 9400 and 9401 closed from 0.55 m to 0.06 m so)
    def step(preset, failed=failed):
        c_, x, a, _, c, v_hat = _lane_in_cruise(preset, scenario)
        side = np.array([-v_hat[1], v_hat[0]])
        obs = x.copy()
        obs[:, 0:2] += 1.0 * side                                           # the gust: everyone 1 m sideways
        obs[c, 0:2] += -0.35 * v_hat + 0.1 * side
        obs[c, 2:4] -= 0.65 * v_hat
        if failed:
            # the failed vehicle q: at rest 1.5 m behind the pad's rear, the vehicle whose particle is farthest from
            # there (> plan_lost_m), within the sensor range of a and c, in nobody's way
            behind = obs[a, 0:2] + (np.min((obs[:, 0:2] - obs[a, 0:2]) @ v_hat) - 1.5) * v_hat
            q = int(np.argmax(np.linalg.norm(x[:, 0:2] - behind, axis=1)))
            obs[q, 0:2], obs[q, 2:4] = behind, 0.0
            assert np.linalg.norm(behind - x[q, 0:2]) > preset.backstop.plan_lost_m
            assert np.linalg.norm(obs[[a, c], 0:2] - behind, axis=1).max() < preset.backstop.sensor_range_m - 1.0
        sensed, info = _act_once(c_, obs)
        return a, c, obs, sensed, c_, np.asarray(info.acc_m_s2)
    off = dataclasses.replace(DEFAULT, backstop=dataclasses.replace(DEFAULT.backstop, gap_push=False))
    a, c, obs, sn, c_off, acc_off = step(off)
    # the gap: to each, the other is near some particle or off the plan the way it is itself (common mode), and
    # without the gap push neither acts
    pair = ((sn.owner == a) & (sn.ids == c)) | ((sn.owner == c) & (sn.ids == a))
    assert not (c_off._unplanned(sn.states[pair], sn.ids[pair])
                & c_off._unplanned(sn.states[pair] - c_off._own_err[sn.owner[pair]])).any()
    assert not c_off.backstop_active[[a, c]].any()
    a_, c2, _, sn2, c_on, acc_on = step(DEFAULT)
    assert (a_, c2) == (a, c)
    # with it, the pair (both ways) and nothing else gets the push, and both act (reciprocal: each takes half of it)
    gp = c_on._gap_pairs(sn2, np.zeros(sn2.states.shape[0], dtype=bool))
    assert gp[pair].all()
    assert c_on.backstop_active[[a, c]].all() and c_on.backstop_active.sum() == 2
    # the commands open the pair at least as fast as the nominal ones (the half-plane keeps a nominal that already
    # separates them: minimal intervention); the separating direction is the pair's closest approach, c - a in 1 s
    rel = obs[c] - obs[a]
    n_hat = (rel[0:2] + 1.0 * rel[2:4]) / np.linalg.norm(rel[0:2] + 1.0 * rel[2:4])
    assert (acc_on[c] - acc_on[a]) @ n_hat >= (acc_off[c] - acc_off[a]) @ n_hat - 1e-9
    # where the particles are closer than gap_push_min_spacing_m, nobody gets it: unless a failed vehicle is in range
    # (in the unspread pad a gust alone must not set off reciprocal pushes: dense --gust N = 144 with cruise_spacing_m
    # = 0, seed 2, 19 collided pairs with them, 1 without)
    cramped = dataclasses.replace(DEFAULT, backstop=dataclasses.replace(DEFAULT.backstop, gap_push_min_spacing_m=1.5))
    assert step(cramped)[4].backstop_active[[a, c]].all() == failed
    if failed:
        assert not step(DEFAULT, failed=False)[4].backstop_active[[a, c]].any()
        alone = dataclasses.replace(DEFAULT, backstop=dataclasses.replace(DEFAULT.backstop, gap_push_near_lost=False))
        assert not step(alone)[4].backstop_active[[a, c]].any()


def test_a_uav_off_its_particle_yields_to_one_on_it_that_it_catches_up_with():
    # given the crossing plan in cruise (a rigid plan, 1.41 m apart) and three UAVs of one lane, c ahead of a ahead of
    # b: c was blown ~2.5 m behind its particle and catches up at 0.5 m/s over the flow, 0.3 m ahead of b's particle
    # (b itself is elsewhere, out of range); a flies its particle 1.1 m ahead of c. The state test takes c for b's
    # particle and a for a planned one: in a rigid plan neither gets a response (the gap; swap4 --gust N = 10,000
    # seeds 5 and 7 collided this way)
    def step(preset):
        c_, x, a, b, c, v_hat = _lane_in_cruise(preset)
        obs = x.copy()
        obs[b, 0:2] += 30.0 * np.array([-v_hat[1], v_hat[0]])                  # out of everyone's range
        obs[c, 0:2] = x[b, 0:2] + 0.3 * v_hat
        obs[c, 2:4] = x[c, 2:4] + 0.5 * v_hat
        sensed, _ = _act_once(c_, obs)                                      # the own deviations; the plan stays at k
        assert not c_._off_plan(obs[[c]]).any() and not c_._unplanned(obs[[c]], np.array([c])).any()   # the gap
        yl = c_._yielding(sensed, np.zeros(sensed.states.shape[0], dtype=bool))
        return a, c, sensed, yl
    a, c, sn, yl = step(DEFAULT)
    # then c (2.5 m off its particle) yields to a (on its particle), and a does not yield to c: one side acts
    assert yl[(sn.owner == c) & (sn.ids == a)].all()
    assert not yl[(sn.owner == a) & (sn.ids == c)].any()
    # nobody yields to c (off its particle), and only c yields (every other UAV flies its particle)
    assert not yl[sn.ids == c].any() and set(sn.owner[yl].tolist()) == {c}
    # where the particles are closer than escape_yield_min_spacing_m (no room to pass between two) nobody yields
    cramped = dataclasses.replace(DEFAULT, backstop=dataclasses.replace(DEFAULT.backstop, escape_yield_min_spacing_m=1.5))
    assert not step(cramped)[3].any()



def test_particles_of_maps_each_exchanged_id_to_its_particle_by_table_or_binary_search():
    # given t = 0 exchanges whose ids are numbered as the simulator does (0..N-1, shuffled: by a table), with gaps and
    # a repeated id (a table), and as a real swarm may (large system ids: by binary search)
    rng = np.random.default_rng(3)
    sc = make_scenario("crossing", 50)
    S0 = as_f32(SwarmPlant(sc.initial_pos_m, plant_params_for(DEFAULT), seed=0).states)
    c = make_controller("mfg", DEFAULT, sc.destination_m)
    probe_extra = np.array([-3, -1, 0, 1, 5, 59, 61, 10**9 + 7, 10**12])
    tables = []
    for ids in (rng.permutation(50), np.r_[np.arange(0, 98, 2), 4], 10**9 + rng.permutation(50)):
        c.exchange_t0(S0, ids, np.arange(50), sc.destination_m)
        tables.append(c._id_table is not None)
        first = {}
        for k, i in enumerate(ids.tolist()):
            first.setdefault(i, k)
        probe = np.r_[ids, probe_extra]
        # then each id gets the particle of its first place in the exchange, every other id -1
        assert c._particles_of(probe).tolist() == [first.get(i, -1) for i in probe.tolist()]
    assert tables == [True, True, False]


def _hover(sensed, unplanned):
    """The controller's hovering threats: unplanned and slower than hover_max_speed_m_s (_DefaultBase._backstop)."""
    v = sensed.states[:, 2:4]
    return unplanned & (v[:, 0] ** 2 + v[:, 1] ** 2 < DEFAULT.backstop.hover_max_speed_m_s ** 2)


def test_the_escape_passes_a_hovering_vehicle_on_the_side_of_its_own_lane():
    # given a UAV flying 4 m/s straight at a vehicle hovering 3 m ahead, 2 cm off its line (a failed vehicle nearly
    # head-on: dense --fail-vehicle N = 5,000 seed 24, UAV 1228 swerved +0.47, -0.84, +1.97, -1.93 m/s^2 across its
    # track on four consecutive steps and passed the failed vehicle at 0.094 m)
    on = dataclasses.replace(DEFAULT, backstop=dataclasses.replace(DEFAULT.backstop, escape_side_commit=1.0))
    bp = on.backstop
    own = np.array([[0.0, 0.0, 4.0, 0.0]])
    sensed = np.array([[3.0, 0.02, 0.0, 0.0]])
    args = (own, np.zeros((1, 2)), sensed, np.array([0]), np.array([True]), np.array([0.6]), np.array([0.8]), bp, 0.5)
    free, act = escape_acc(*args)
    assert act[0] and abs(free[0, 1]) > 0.5                           # it escapes sideways
    # when told the side (its lane's), it passes on that side, whichever it is
    for side in (1.0, -1.0):
        a, act = escape_acc(*args, side_pref=np.array([[0.0, side]]))
        assert act[0] and a[0, 1] * side > 0.5, (side, a)
    # without the preference (escape_side_commit = 0) the side given is ignored
    off = dataclasses.replace(bp, escape_side_commit=0.0)
    a_off, _ = escape_acc(*args[:-2], off, 0.5, side_pref=np.array([[0.0, -np.sign(free[0, 1])]]))
    np.testing.assert_array_equal(a_off, free)
    # the controller takes the side from the plan: in the dense pad in cruise, a vehicle failed in Hold 0.3 m left of
    # the lane of a and 2.5 m ahead of it; a passes it on the right, and every row within range of it on the side its
    # own particle's lane lies on (lanes left of it on the left): the lanes split around it
    c_, x, a, _, c, v_hat = _lane_in_cruise(on, ("dense", 100, 40))
    left = np.array([-v_hat[1], v_hat[0]])
    obs = x.copy()
    obs[c, 0:2] = x[a, 0:2] + 2.5 * v_hat + 0.3 * left
    obs[c, 2:4] = 0.0
    sensed, _ = _act_once(c_, obs)
    unpl = c_._unplanned(sensed.states, sensed.ids)
    assert unpl[(sensed.owner == a) & (sensed.ids == c)].all()
    side = c_._escape_side(obs, sensed, _hover(sensed, unpl))
    np.testing.assert_allclose(side[a], -left, atol=1e-9)
    rows = np.unique(sensed.owner[unpl & (sensed.ids == c)])
    rows = rows[rows != c]
    lane_left = (x[rows, 0:2] - obs[c, 0:2]) @ left > 0                 # every particle flies along v_hat here
    np.testing.assert_allclose(side[rows], np.where(lane_left[:, None], left, -left), atol=1e-9)
    assert lane_left.any() and (~lane_left).any()
    # a row that senses no hovering vehicle gets none
    far = np.flatnonzero(np.linalg.norm(obs[:, 0:2] - obs[c, 0:2], axis=1) > DEFAULT.backstop.sensor_range_m + 0.5)
    assert far.size and not side[far].any()
    # off (escape_side_commit = 0): no side
    off_p = dataclasses.replace(DEFAULT, backstop=dataclasses.replace(DEFAULT.backstop, escape_side_commit=0.0))
    c_off = _lane_in_cruise(off_p, ("dense", 100, 40))[0]
    _act_once(c_off, obs)
    assert c_off._escape_side(obs, sensed, _hover(sensed, unpl)) is None


@pytest.mark.parametrize("memory", [True, False])
def test_the_lane_side_is_kept_while_the_failed_vehicle_drifts_across_the_lane(memory):
    # given the dense pad in cruise and a vehicle failed in Hold 2.5 m ahead of UAV a, 5 cm left of a's lane, that
    # then drifts in the wind to 5 cm right of it (dense --fail-vehicle N = 10,000 seed 9 with the lane side but no
    # memory: a failed vehicle drifting 0.2-0.3 m across lanes, UAV 3733 passed it at 0.092 m)
    bp = dataclasses.replace(DEFAULT.backstop, escape_side_commit=1.0, escape_side_memory=memory)
    pre = dataclasses.replace(DEFAULT, backstop=bp)
    c_, x, a, _, c, v_hat = _lane_in_cruise(pre, ("dense", 100, 40))
    left = np.array([-v_hat[1], v_hat[0]])
    sides = []
    for off in (0.05, -0.05):
        obs = x.copy()
        obs[c, 0:2] = x[a, 0:2] + 2.5 * v_hat + off * left
        obs[c, 2:4] = 0.3 * left                          # drifting, slower than hover_max_speed_m_s: hovering
        sensed = Neighbours.from_pairs(obs, cKDTree(obs[:, :2]).query_pairs(c_.sensor_range_m, output_type="ndarray"))
        unpl = c_._unplanned(sensed.states, sensed.ids)
        assert unpl[(sensed.owner == a) & (sensed.ids == c)].all()
        sides.append(c_._escape_side(obs, sensed, _hover(sensed, unpl))[a])
    # then the side first chosen (right of the vehicle 5 cm left of the lane) is kept with the memory, and flips
    # under the drifting vehicle without it
    np.testing.assert_allclose(sides[0], -left, atol=1e-9)
    np.testing.assert_allclose(sides[1], -left if memory else left, atol=1e-9)
    if memory:
        # a different hovering vehicle is a new meeting: its side is chosen afresh
        obs[c, 2:4] = 0.0
        ids = np.arange(obs.shape[0])
        ids[c] = 10 ** 6
        sensed = Neighbours.from_pairs(obs, cKDTree(obs[:, :2]).query_pairs(c_.sensor_range_m, output_type="ndarray"))
        sensed = Neighbours(sensed.states, sensed.owner, ids[sensed.ids])
        unpl = np.isin(sensed.ids, [10 ** 6])
        np.testing.assert_allclose(c_._escape_side(obs, sensed, _hover(sensed, unpl))[a], left, atol=1e-9)


def test_the_escape_also_acts_when_coasting_would_hit_a_hovering_vehicle():
    # given a UAV at 4 m/s straight at a vehicle hovering 7.5 m ahead, 1 cm off its line, and a nominal command with
    # 0.28 m/s^2 across the track (a momentary tracking correction): held for the 2 s horizon it predicts a 0.5 m
    # miss, coasting a 0.01 m one (dense --fail-vehicle N = 3,000 seed 34: the escape acted only at 3.8 m, one
    # second before the pass, and UAV 455 passed the failed vehicle at 0.091 m)
    own = np.array([[0.0, 0.0, 4.0, 0.0]])
    a_nom = np.array([[0.0, 0.28]])
    sensed = np.array([[7.5, 0.01, 0.0, 0.0]])
    args = (own, a_nom, sensed, np.array([0]), np.array([True]), np.array([0.25]), np.array([0.3]), DEFAULT.backstop, 0.5)
    for hover in (True, False):
        _, act = escape_acc(*args, None, np.array([hover]))
        # then the escape is active where the entry is marked as hovering (the coasting prediction), and not otherwise
        assert act[0] == hover
    assert not escape_acc(*args)[1][0]
    # nor with the rule off (escape_trigger_coast = False)
    off = dataclasses.replace(DEFAULT.backstop, escape_trigger_coast=False)
    assert not escape_acc(*args[:-2], off, 0.5, None, np.array([True]))[1][0]
    # and a vehicle that coasting misses too does not wake it
    far = sensed.copy()
    far[0, 1] = 1.0
    _, act = escape_acc(own, a_nom, far, *args[3:], None, np.array([True]))
    assert not act[0]


def test_a_hovering_vehicle_off_the_plan_is_kept_clear_by_the_spacing_flown_now_and_wakes_the_escape_when_coasting(monkeypatch):
    # given the dense pad in cruise (slots 0.5 m apart, particles ~1.4 m apart now) and two vehicles off the plan
    # ahead of UAV a: one hovering (failed in Hold), one moving across the flow at 3 m/s
    import mfg_autopilot.guidance.controller as ctl
    seen = {}

    def spy(own, a_nom, states, owner, threat, trig, clear, bp, commit_s, side=None, hover=None, own_dist=None,
            brake_hyp=None, **more):
        seen.update(states=states, owner=owner, threat=threat, trig=trig, clear=clear, hover=hover)
        return escape_acc(own, a_nom, states, owner, threat, trig, clear, bp, commit_s, side, hover, own_dist,
                          brake_hyp=brake_hyp, **more)

    monkeypatch.setattr(ctl, "escape_acc", spy)
    for now in (True, False):
        pre = dataclasses.replace(DEFAULT, backstop=dataclasses.replace(DEFAULT.backstop, unplanned_hover_clear_now=now,
                                                                        unplanned_hover_trigger_now=now))
        c_, x, a, _, c, v_hat = _lane_in_cruise(pre, ("dense", 100, 40))
        left = np.array([-v_hat[1], v_hat[0]])
        far = int(np.argmax(np.linalg.norm(x[:, 0:2] - x[a, 0:2], axis=1)))
        obs = x.copy()
        obs[c, 0:2], obs[c, 2:4] = x[a, 0:2] + 3.0 * v_hat + 0.7 * left, 0.0
        obs[far, 0:2], obs[far, 2:4] = x[a, 0:2] + 5.0 * v_hat - 0.7 * left, 3.0 * left
        seen.clear()
        sid = _act_once(c_, obs)[0].ids
        sp, sp_now = c_._spacing_m(), c_._spacing_now_m()
        assert sp_now > 2 * sp
        mine = seen["owner"] == a
        hov, mov = mine & (sid == c), mine & (sid == far)
        assert seen["threat"][hov].all() and seen["threat"][mov].all()
        slot = min(pre.backstop.unplanned_target_m, 0.6 * sp)
        # then the hovering one is kept min(0.8, 0.6 x spacing now) away, the moving one the slot-sized clearance
        want = min(pre.backstop.unplanned_target_m, 0.6 * sp_now) if now else slot
        np.testing.assert_allclose(seen["clear"][hov], want)
        np.testing.assert_allclose(seen["clear"][mov], slot)
        # and its trigger min(0.6, 0.5 x spacing now), the moving one's the slot-sized min(0.6, 0.5 x slot spacing)
        slot_trig = min(pre.backstop.unplanned_trigger_m, 0.5 * sp)
        want = min(pre.backstop.unplanned_trigger_m, 0.5 * sp_now) if now else slot_trig
        np.testing.assert_allclose(seen["trig"][hov], want)
        np.testing.assert_allclose(seen["trig"][mov], slot_trig)
        assert want > slot_trig or not now
        # and only the hovering one is marked as hovering (coasting wakes the escape, the lane side replaces keep-right;
        # a gust-blown vehicle is not: with every unplanned vehicle marked for the coasting trigger, the unspread pad in
        # a gust went from 1 to 4 collided pairs)
        assert seen["hover"][hov].all() and not seen["hover"][mov].any()


@pytest.mark.parametrize("rule", [True, False])
def test_the_lane_side_and_not_keep_right_decides_the_side_a_hovering_vehicle_is_passed_on(rule):
    # given a UAV at 4 m/s straight at a vehicle hovering 5 m ahead on its line, its lane's side on its left (dense
    # --fail-vehicle N = 3,000 seed 31: keep-right's cost 2.0 outweighed the lane side's 1.0, UAV 2682 swerved to the
    # lane side at one step, to the right at the next, back at the third, and passed the failed vehicle at 0.17 m)
    bp = dataclasses.replace(DEFAULT.backstop, escape_side_over_keep_right=rule)
    own = np.array([[0.0, 0.0, 4.0, 0.0]])
    sensed = np.array([[5.0, 0.0, 0.0, 0.0]])
    args = (own, np.zeros((1, 2)), sensed, np.array([0]), np.array([True]), np.array([0.6]), np.array([0.8]), bp, 0.5)
    left, right = np.array([[0.0, 1.0]]), np.array([[0.0, -1.0]])
    a, act = escape_acc(*args, left, np.array([True]))
    # then with the rule it swerves left, to its lane's side; without it keep-right takes it right
    assert act[0] and (a[0, 1] > 0.5 if rule else a[0, 1] < -0.5), a
    # a lane side on the right is kept either way
    a, act = escape_acc(*args, right, np.array([True]))
    assert act[0] and a[0, 1] < -0.5, a
    # and a vehicle not marked as hovering keeps keep-right (two escaping vehicles pick opposite sides by it)
    a, act = escape_acc(*args, left, np.array([False]))
    assert act[0] and a[0, 1] < -0.5, a
