"""The simulator's failed vehicle flies PX4's Hold: towards the braking stop, its braking built up at MPC_JERK_AUTO
(mfg_swarm.sim._step_with_hold, mock_vehicle.plant.jerk_limited_m_s2), as the mock vehicle flies it."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mfg_autopilot.guidance import controller as ctl
from mfg_autopilot.presets import preset_by_name
from mfg_swarm import sim
from mfg_swarm.scenarios import make_scenario
from mock_vehicle.plant import SwarmPlant, braking_stop_m, jerk_limited_m_s2, saturate_norm


def test_jerk_limit_moves_towards_the_target_by_at_most_jerk_times_dt():
    prev = np.array([[0.4, 0.0], [0.0, 0.0], [1.0, 1.0]])
    target = np.array([[-2.0, 0.0], [0.1, -0.1], [1.0, 1.0]])
    got = jerk_limited_m_s2(prev, target, 4.0, 0.1)
    np.testing.assert_allclose(got[0], [0.0, 0.0], atol=1e-12)        # 0.4 m/s^2 per 0.1 s
    np.testing.assert_array_equal(got[1:], target[1:])                  # within reach: the target
    np.testing.assert_array_equal(jerk_limited_m_s2(prev, target, 0.0, 0.1), target)      # 0: no limit
    np.testing.assert_array_equal(jerk_limited_m_s2(prev, target, float("inf"), 0.1), target)


_acc = st.tuples(st.floats(-5.0, 5.0), st.floats(-5.0, 5.0))


@settings(max_examples=300, deadline=None)
@given(prev=_acc, target=_acc, jerk=st.floats(0.5, 80.0), dt=st.floats(0.001, 0.5))
def test_jerk_limit_property(prev, target, jerk, dt):
    # the result is on the segment from the previous acceleration to the target, at most jerk x dt from the previous,
    # and the target itself when that is within reach
    p, t = np.array(prev), np.array(target)
    got = jerk_limited_m_s2(p, t, jerk, dt)
    step, gap = np.linalg.norm(got - p), np.linalg.norm(t - p)
    assert step <= jerk * dt * (1 + 1e-12) + 1e-12
    d, g = got - p, t - p
    assert abs(d[0] * g[1] - d[1] * g[0]) <= 1e-9 * max(1.0, gap) and np.dot(d, g) >= -1e-12
    if gap <= jerk * dt:
        np.testing.assert_allclose(got, t, atol=1e-12)
    else:
        assert step == pytest.approx(jerk * dt, rel=1e-9)


def _twin_plants(seed: int, acc_seed: int):
    """Two identical plants of 30 `paper` vehicles, their parameters and one random command (30, 2)."""
    sc = make_scenario("paper", 30)
    params = sim.plant_params_for(preset_by_name("default"))
    a, b = SwarmPlant(sc.initial_pos_m, params, seed=seed), SwarmPlant(sc.initial_pos_m, params, seed=seed)
    return a, b, params, np.random.default_rng(acc_seed).uniform(-1.5, 1.5, (30, 2))


def test_the_other_vehicles_move_bit_for_bit_as_in_one_plant_step():
    # given two identical plants of 30 vehicles and one command
    a, b, params, acc = _twin_plants(5, 0)
    K = 7
    hold = braking_stop_m(a.states[K:K + 1])
    # when one steps with vehicle K in Hold (sub-step by sub-step) and the other with one plant.step
    applied, last, _ = sim._step_with_hold(a, acc, 0.5, K, hold, np.zeros(2), 4.0)
    b.step(acc, 0.5)
    # then every other vehicle is where one plant.step puts it, bit for bit, and K is not
    others = np.arange(30) != K
    np.testing.assert_array_equal(a.states[others], b.states[others])
    np.testing.assert_array_equal(applied[others], saturate_norm(acc, params.acc_limit_m_s2)[others])
    assert not np.array_equal(a.states[K], b.states[K])
    # K's acceleration moved from 0 by at most 4 m/s^3 x 0.5 s, and the mean over the sub-steps is logged
    assert np.linalg.norm(last) <= 2.0 + 1e-12
    assert np.linalg.norm(applied[K]) <= 4.0 * 0.1 * 3 + 1e-12       # mean of 0.4, 0.8, ..., 2.0 at most


@pytest.mark.parametrize("jerk", [4.0, 0.0])
def test_the_failed_vehicle_builds_its_braking_up_at_the_jerk_limit(jerk):
    # given paper N = 25 with vehicle 7 failing at 10 s into the PD Hold (hold_model "pd": a saturated PD whose
    # acceleration ramps at PX4's jerk limit, 4 m/s^3, or does not; PX4's own trajectory, the default, is checked in
    # tests/test_position_smoothing.py and below)
    cfg = sim.SimConfig(scenario=make_scenario("paper", 25), mode="mfg", preset=preset_by_name("default"), seed=1,
                        steps=30, fail_vehicle=7, fail_at_s=10.0, hold_jerk_m_s3=jerk, hold_model="pd")
    traj, metrics = sim.simulate(cfg, progress=False)
    kf = 20
    a = traj.acc_m_s2[:, 7]
    change = np.linalg.norm(a[kf] - a[kf - 1])
    if jerk:
        # then the first Hold step's mean acceleration is at most the ramp's (0.4 + ... + 2.0) / 5 = 1.2 m/s^2 away
        # from the last command, and the next step brakes near the airframe's limit
        assert change <= 1.2 + 1e-9 and np.linalg.norm(a[kf + 1]) > 1.5, (a[kf - 1], a[kf], a[kf + 1])
    else:
        # without the limit it brakes at the airframe's 2 m/s^2 from the first instant
        assert np.linalg.norm(a[kf]) == pytest.approx(2.0, abs=1e-6) and change > 1.5
    assert metrics["hold_jerk_m_s3"] == jerk
    # and it stops where PX4's navigator put the loiter point (its braking stop), whichever way it braked
    speed = np.linalg.norm(traj.vel_m_s[-1, 7])
    assert speed < 0.3


def test_a_negative_or_non_finite_jerk_is_refused():
    for bad in (-1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="hold_jerk_m_s3"):
            sim.SimConfig(scenario=make_scenario("paper", 4), mode="mfg", preset=preset_by_name("default"),
                          fail_vehicle=1, hold_jerk_m_s3=bad)


def test_several_failed_vehicles_are_checked_before_the_flight():
    sc, p = make_scenario("paper", 9), preset_by_name("default")
    for bad, match in (((1, 1), "twice"), ((1, 9), r"\[0, 8\]"), ((), r"\[0, 8\]"), ((1.5,), r"\[0, 8\]")):
        with pytest.raises(ValueError, match=match):
            sim.SimConfig(scenario=sc, mode="mfg", preset=p, fail_vehicle=bad)
    with pytest.raises(ValueError, match="one time for all"):
        sim.SimConfig(scenario=sc, mode="mfg", preset=p, fail_vehicle=(1, 2), fail_at_s=(1.0, 2.0, 3.0))
    with pytest.raises(ValueError, match=">= 0"):
        sim.SimConfig(scenario=sc, mode="mfg", preset=p, fail_vehicle=(1, 2), fail_at_s=(1.0, -2.0))
    cfg = sim.SimConfig(scenario=sc, mode="mfg", preset=p, fail_vehicle=(3, 1), fail_at_s=5.0)
    assert cfg.failures == ((3, 5.0), (1, 5.0))


def test_one_failed_vehicle_given_as_a_list_of_one_flies_bit_for_bit_as_given_alone():
    kw = dict(scenario=make_scenario("paper", 25), mode="mfg", preset=preset_by_name("default"), seed=2, steps=40)
    a, ma = sim.simulate(sim.SimConfig(fail_vehicle=7, fail_at_s=10.0, **kw), progress=False)
    b, mb = sim.simulate(sim.SimConfig(fail_vehicle=(7,), fail_at_s=(10.0,), **kw), progress=False)
    np.testing.assert_array_equal(a.pos_m, b.pos_m)
    assert ma["fail_vehicle"] == mb["fail_vehicle"] == 7 and ma["fail_at_s"] == mb["fail_at_s"] == 10.0


def test_a_failed_vehicles_row_is_no_safety_intervention(monkeypatch):
    # the bank still computes the failed vehicle's row (its commands are not flown: it holds), and that row's flags follow
    # the Hold's acceleration through the disturbance observer; safety_interventions counts only rows whose command flies
    seen = []
    act = ctl.DefaultMFGController.act

    def spy(self, obs):
        info = act(self, obs)
        seen.append((obs.step, bool(self.backstop_active[3])))
        return info

    monkeypatch.setattr(ctl.DefaultMFGController, "act", spy)
    cfg = sim.SimConfig(scenario=make_scenario("crossing", 16), mode="mfg", preset=preset_by_name("default"), seed=2,
                        steps=80, gust=sim.GustParams(), fail_vehicle=3, fail_at_s=10.0)
    traj, m = sim.simulate(cfg, progress=False)
    active = traj.extra["backstop_active"]
    assert any(flag for k, flag in seen if k * 0.5 >= 10.0)         # the row was flagged after the failure ...
    assert not active[20:, 3].any()                                 # ... and is not counted from its failure on
    assert m["safety_interventions"] == int(active.sum())


def test_two_vehicles_failing_at_their_own_times_each_hold_and_the_others_arrive():
    """paper and crossing N = 100, seed 3 (not a seed the controller was tuned on; two failures were never part of its
    tuning): vehicles 10 and 50 fail into PX4's Hold at 20 s and 25 s. Each flies its last command until its own
    failure, then stops near its own braking stop; no pair collides (0.1 m) and every other vehicle arrives."""
    for scenario in ("paper", "crossing"):
        cfg = sim.SimConfig(scenario=make_scenario(scenario, 100), mode="mfg", preset=preset_by_name("default"),
                            seed=3, steps=300, fail_vehicle=(10, 50), fail_at_s=(20.0, 25.0))
        traj, m = sim.simulate(cfg, progress=False)
        assert m["fail_vehicle"] == [10, 50] and m["fail_at_s"] == [20.0, 25.0]
        assert m["collision_pairs"] == 0 and m["failed_vehicle_collision_pairs"] == 0, (scenario, m["closest_pair"])
        assert m["arrived_fraction_others"] == 1.0, scenario
        for K, k_fail in ((10, 40), (50, 50)):
            stop = braking_stop_m(np.concatenate([traj.pos_m[k_fail, K], traj.vel_m_s[k_fail, K]])[None])[0]
            assert np.linalg.norm(traj.vel_m_s[-1, K]) < 0.3, (scenario, K)
            assert np.linalg.norm(traj.pos_m[-1, K] - stop) < 1.0, (scenario, K, traj.pos_m[-1, K], stop)
        # each holds from its own failure on: at 22.5 s vehicle 10 has nearly stopped while 50 still cruises with
        # the stream (measured ~0.2 against 3.5-4.2 m/s), and by 27.5 s 50 has stopped too
        speed = np.linalg.norm(traj.vel_m_s, axis=2)
        assert speed[45, 10] < 0.5 and speed[45, 50] > 3.0 and speed[55, 50] < 0.5, (scenario, speed[[45, 55]][:, [10, 50]])


def test_a_failure_inside_a_control_step_begins_at_its_physics_sub_step():
    # given two identical plants of 30 vehicles and one command, vehicle K failing 0.2 s into a 0.5 s step
    a, b, params, acc = _twin_plants(4, 1)
    K = 7
    # when one steps with K entering Hold at sub-step 2 (its Hold point unknown until then: a dummy is replaced) ...
    applied, last, hold = sim._step_with_hold(a, acc, 0.5, K, np.full((1, 2), np.nan), np.zeros(2), 4.0,
                                              first_sub=np.array([2]))
    # ... and the other flies two plain 0.1 s sub-steps, then Hold from there over the remaining 0.3 s
    cmd = b.step(acc, 0.1)
    b.step(acc, 0.1)
    hold_b = braking_stop_m(b.states[K:K + 1])
    _, last_b, _ = sim._step_with_hold(b, acc, 0.3, K, hold_b, cmd[K], 4.0)
    # then both end alike (to rounding: 0.3 / 3 is not 0.1 to the last bit): K flew its command until its failure,
    # its Hold point is the braking stop ahead of its state at the failure, its smoothing starts from that command
    np.testing.assert_allclose(a.states, b.states, rtol=0, atol=1e-9)
    np.testing.assert_allclose(hold, hold_b, rtol=0, atol=1e-9)
    np.testing.assert_allclose(last, last_b, rtol=0, atol=1e-9)
    assert np.linalg.norm(hold - braking_stop_m(a.states[K:K + 1])) > 0.1      # not where it is at the step's end
    # and the logged mean is two sub-steps of the command and three of the ramp away from it
    ramp = np.linalg.norm(applied[K] - saturate_norm(acc, params.acc_limit_m_s2)[K])
    assert 0.0 < ramp <= (0.4 + 0.8 + 1.2) / 5 + 1e-12


def test_a_vehicle_failing_between_two_samples_flies_its_command_until_then():
    """paper N = 25, vehicle 7 failing at 10.2 s (between the control instants 10.0 and 10.5): up to 10.0 s the flight
    is the one without a failure, bit for bit; from 10.2 s vehicle 7 holds, so at 10.5 s it is off the flight that has
    no failure but also off the one that fails at 10.0 s (it flew its command 0.2 s longer); the other vehicles see it
    only at 10.5 s and move as without the failure until then."""
    kw = dict(scenario=make_scenario("paper", 25), mode="mfg", preset=preset_by_name("default"), seed=1, steps=30)
    free, _ = sim.simulate(sim.SimConfig(**kw), progress=False)
    mid, m = sim.simulate(sim.SimConfig(fail_vehicle=7, fail_at_s=10.2, **kw), progress=False)
    grid, _ = sim.simulate(sim.SimConfig(fail_vehicle=7, fail_at_s=10.0, **kw), progress=False)
    assert m["fail_at_s"] == 10.2
    np.testing.assert_array_equal(mid.pos_m[:21], free.pos_m[:21])
    others = np.arange(25) != 7
    np.testing.assert_array_equal(mid.pos_m[21, others], free.pos_m[21, others])
    for other in (free, grid):
        assert np.linalg.norm(mid.pos_m[21, 7] - other.pos_m[21, 7]) > 1e-3
    # it brakes: slower than without the failure, faster than when it failed 0.2 s earlier
    speed = [np.linalg.norm(t.vel_m_s[21, 7]) for t in (free, mid, grid)]
    assert speed[0] > speed[1] > speed[2], speed
    # and it stops near the braking stop ahead of where it was when it failed
    assert np.linalg.norm(mid.vel_m_s[-1, 7]) < 0.3


def test_a_failure_off_the_control_grid_needs_the_jerk_limited_hold():
    sc, p = make_scenario("paper", 9), preset_by_name("default")
    with pytest.raises(ValueError, match="not on the control grid"):
        sim.SimConfig(scenario=sc, mode="mfg", preset=p, fail_vehicle=1, fail_at_s=10.2, hold_jerk_m_s3=0.0,
                      hold_model="pd")
    sim.SimConfig(scenario=sc, mode="mfg", preset=p, fail_vehicle=1, fail_at_s=10.5, hold_jerk_m_s3=0.0,
                  hold_model="pd")   # on it
    # the abrupt Hold is the PD's: with the default Hold (PX4's trajectory) the error says so
    with pytest.raises(ValueError, match="hold_model='pd'"):
        sim.SimConfig(scenario=sc, mode="mfg", preset=p, fail_vehicle=1, fail_at_s=10.5, hold_jerk_m_s3=0.0)
    for bad in (float("nan"), float("inf")):
        with pytest.raises(ValueError, match="finite and >= 0"):
            sim.SimConfig(scenario=sc, mode="mfg", preset=p, fail_vehicle=1, fail_at_s=bad)


def test_the_mock_and_the_simulator_fly_px4s_hold_bit_for_bit_alike():
    """--hold-model px4: a mock vehicle switched to Hold while flying (wind noise on) and the simulator's failed vehicle
    (``_step_with_hold`` with a ``Px4AutoXY``) started from the same state, noise stream position, Hold point and last
    acceleration move bit for bit alike, sub-step by sub-step (the mock: 0.1 s physics ticks; the simulator: 0.5 s
    control steps of 5 sub-steps)."""
    import copy

    from mavlink_bridge import PX4_HOLD, CommandLong, Received, acceleration_setpoint
    from mock_vehicle.smoothing import AutoParams, Px4AutoXY
    from mock_vehicle.vehicle import MockVehicle, VehicleConfig

    class Clock:
        t = 1000.0

        def __call__(self):
            return self.t

    clock = Clock()
    v = MockVehicle(VehicleConfig(initial_pos_m=(3.0, -2.0), seed=11, hold_model="px4"), lambda m, p: None, clock=clock)
    v.handle(Received(CommandLong(1, 1, 400, (1.0,) + (0.0,) * 6), 1, 195))
    for _ in range(60):                                     # 3 s of offboard at (1.5, 0.8) m/s^2, 20 Hz
        v.handle(Received(acceleration_setpoint(1, 1, (1.5, 0.8, 0.0), 0), 1, 195))
        if _ == 1:
            v.handle(Received(CommandLong(1, 1, 176, (1.0, 6.0) + (0.0,) * 5), 1, 195))
        clock.t += 0.05
        v.tick()
    # the simulator's twin: the mock's plant as it is now (state, noise stream position), its last acceleration
    plant = copy.deepcopy(v.plant)
    a_prev = v.applied_acc_m_s2.copy()
    v.handle(Received(CommandLong(1, 1, 176, (1.0, 4.0, 3.0) + (0.0,) * 4), 1, 195))
    assert v.mode == PX4_HOLD and np.linalg.norm(v.state[2:4]) > 2.0
    hold = braking_stop_m(plant.states)
    np.testing.assert_array_equal(hold[0], v.hold_pos_m)
    model = Px4AutoXY(AutoParams(mpc_jerk_auto_m_s3=4.0))
    for step in range(20):                                  # 10 s: 20 control steps of 0.5 s
        _, a_prev, _ = sim._step_with_hold(plant, np.zeros((1, 2)), 0.5, 0, hold, a_prev, 4.0, models=[model])
        for _ in range(5):
            clock.t += 0.1
            v.tick()
        np.testing.assert_array_equal(plant.states[0], v.state, err_msg=f"step {step}")
    # and it stopped at the Hold point (within the wind noise)
    assert np.linalg.norm(v.state[0:2] - hold[0]) < 0.3 and np.linalg.norm(v.state[2:4]) < 0.3


def test_a_px4_hold_flight_stops_its_failed_vehicle_near_the_braking_stop():
    # paper N = 25, vehicle 7 failing at 10.2 s (inside a control step) into PX4's Hold (the default): it stops near the
    # braking stop ahead of its state at the failure, the other vehicles fly as without the failure until the next sample
    kw = dict(scenario=make_scenario("paper", 25), mode="mfg", preset=preset_by_name("default"), seed=1, steps=40)
    free, _ = sim.simulate(sim.SimConfig(**kw), progress=False)
    assert sim.SimConfig(**kw).hold_model == "px4"
    px4, m = sim.simulate(sim.SimConfig(fail_vehicle=7, fail_at_s=10.2, **kw), progress=False)
    pd, mp = sim.simulate(sim.SimConfig(fail_vehicle=7, fail_at_s=10.2, hold_model="pd", **kw), progress=False)
    assert m["hold_model"] == "px4" and mp["hold_model"] == "pd"
    others = np.arange(25) != 7
    np.testing.assert_array_equal(px4.pos_m[:21], free.pos_m[:21])
    np.testing.assert_array_equal(px4.pos_m[21, others], free.pos_m[21, others])
    assert not np.array_equal(px4.pos_m[21:, 7], pd.pos_m[21:, 7])          # a different Hold
    assert np.linalg.norm(px4.vel_m_s[-1, 7]) < 0.3
    with pytest.raises(ValueError, match="hold_model"):
        sim.SimConfig(fail_vehicle=7, hold_model="lqr", **kw)
    with pytest.raises(ValueError, match="MPC_JERK_AUTO"):
        sim.SimConfig(fail_vehicle=7, hold_model="px4", hold_jerk_m_s3=0.0, **kw)
