"""PX4's auto-mode trajectory (``mock_vehicle.smoothing``: VelocitySmoothing, PositionSmoothing, FlightTaskAuto,
PositionControl, XY): PX4's own unit tests ported (src/lib/motion_planning/VelocitySmoothingTest.cpp at 1bbd1168,
PositionSmoothingTest.cpp at 1f8c8534, their numbers; XY only, so their Z axis is left out), the limits, and the Hold
a vehicle flies with it against the PD-with-jerk-limit Hold (``plant.hold_acc_m_s2`` + ``jerk_limited_m_s2``)."""

import math

import numpy as np
import pytest

from mock_vehicle.plant import WindParams, braking_stop_m, hold_acc_m_s2, jerk_limited_m_s2, saturate_norm
from mock_vehicle.smoothing import (
    AutoParams,
    PositionSmoothing,
    Px4AutoXY,
    VelocitySmoothing,
    compute_braking_distance_from_velocity,
    compute_max_speed_from_distance,
)


# ------------------------------------------------------------------ VelocitySmoothingTest.cpp
def _trajectories(j_max, a_max, v_max, a0, v0, x0):
    trajs = [VelocitySmoothing() for _ in range(3)]
    for i, t in enumerate(trajs):
        t.setMaxJerk(j_max); t.setMaxAccel(a_max); t.setMaxVel(v_max)
        t.setCurrentAcceleration(a0[i]); t.setCurrentVelocity(v0[i]); t.setCurrentPosition(x0[i])
    return trajs


def _update_trajectories(trajs, dt, vel_sp, n_sync=2):
    """VelocitySmoothingTest::updateTrajectories: integrate, check the limits, plan, synchronise the first n_sync."""
    for t in trajs:
        t.updateTraj(dt)
        assert abs(t.getCurrentJerk()) <= t.getMaxJerk()
        assert abs(t.getCurrentAcceleration()) <= t.getMaxAccel() + 1e-9
        assert abs(t.getCurrentVelocity()) <= t.getMaxVel() + 1e-9
    for t, v in zip(trajs, vel_sp):
        t.updateDurations(v)
    VelocitySmoothing.timeSynchronization(trajs[:n_sync])


def test_velocity_smoothing_time_synchronization():
    # PX4 testTimeSynchronization: j 55.2, a 6, v 6; a0 (0.22, 0, 0.22), v0 (2.47, -5.59e-6, 2.47); setpoints (-3, 1, 0)
    trajs = _trajectories(55.2, 6.0, 6.0, (0.22, 0.0, 0.22), (2.47, -5.59e-6, 2.47), (0.0, 0.0, 0.0))
    _update_trajectories(trajs, 0.0, (-3.0, 1.0, 0.0))
    assert abs(trajs[0].getTotalTime() - trajs[1].getTotalTime()) <= 1e-4
    assert trajs[0].getTotalTime() > 0.1                      # there is something to synchronise


def test_velocity_smoothing_time_synchronization_same_delta():
    # PX4 testTimeSynchronizationSameDelta: no constraints set (0), v0 (0.5, -0.2, 0), both XY +0.3 m/s
    trajs = [VelocitySmoothing() for _ in range(3)]
    for t, v in zip(trajs, (0.5, -0.2, 0.0)):
        t.setCurrentVelocity(v)
    for t, v in zip(trajs, (0.8, 0.1, 0.0)):
        t.updateDurations(v)
    VelocitySmoothing.timeSynchronization(trajs)
    assert trajs[0].getTotalTime() == pytest.approx(trajs[1].getTotalTime())
    for get in ("getT1", "getT2", "getT3"):
        assert getattr(trajs[0], get)() == pytest.approx(getattr(trajs[1], get)())
    assert trajs[2].getTotalTime() == pytest.approx(trajs[0].getTotalTime())
    assert trajs[2].getT1() == 0.0 and trajs[2].getT3() == 0.0
    assert trajs[2].getT2() == pytest.approx(trajs[0].getTotalTime())


def test_velocity_smoothing_constant_setpoint():
    # PX4 testConstantSetpoint: j 55.2, a 6, v 6 from rest to (-3, 0, -1) in ceil(T123 / 0.01) steps of 0.01 s
    trajs = _trajectories(55.2, 6.0, 6.0, (0.0,) * 3, (0.0,) * 3, (0.0,) * 3)
    sp = (-3.0, 0.0, -1.0)
    _update_trajectories(trajs, 0.0, sp)
    for _ in range(math.ceil(trajs[0].getTotalTime() / 0.01)):
        _update_trajectories(trajs, 0.01, sp)
    for t, v in zip(trajs, sp):
        assert abs(t.getCurrentVelocity() - v) <= 0.01
        assert abs(t.getCurrentAcceleration()) <= 1e-4


def test_velocity_smoothing_zero_setpoint():
    # PX4 testZeroSetpoint: from rest with zero setpoints (and no constraints set), 60 steps of 0.01 s: all stays 0
    trajs = [VelocitySmoothing() for _ in range(3)]
    for _ in range(60):
        _update_trajectories(trajs, 0.01, (0.0, 0.0, 0.0))
    for t in trajs:
        assert (t.getCurrentJerk(), t.getCurrentAcceleration(), t.getCurrentVelocity(), t.getCurrentPosition()) == (0,) * 4


def test_a_new_trajectory_drops_the_acceleration_it_was_reset_to_on_its_first_update():
    # PX4: reset() sets the state only; a new object's T1 = T2 = T3 = 0, so updateTraj(dt > 0) ends in the
    # zero-acceleration phase. With dt = 0 the acceleration stays.
    t = VelocitySmoothing(2.0, 4.0, 0.0)
    t.setMaxJerk(4.0); t.setMaxAccel(3.0); t.setMaxVel(12.0)
    t.updateTraj(1e-6)
    assert t.getCurrentAcceleration() == 0.0 and t.getCurrentVelocity() == 4.0
    u = VelocitySmoothing(2.0, 4.0, 0.0)
    u.updateTraj(0.0)
    assert u.getCurrentAcceleration() == 2.0


# ------------------------------------------------------------------ PositionSmoothingTest.cpp
MAX_JERK, MAX_ACCELERATION, MAX_ALLOWED_HOR_ERR, CRUISE_SPEED = 4.0, 3.0, 2.0, 5.0
MAX_VELOCITY, HORIZONTAL_TRAJECTORY_GAIN, TARGET_ACCEPTANCE_RADIUS = CRUISE_SPEED, 0.5, 0.5


def _position_smoothing() -> PositionSmoothing:
    ps = PositionSmoothing()
    ps.setMaxJerkXY(MAX_JERK); ps.setMaxAccelerationXY(MAX_ACCELERATION); ps.setMaxVelocityXY(MAX_VELOCITY)
    ps.setMaxAllowedHorizontalError(MAX_ALLOWED_HOR_ERR); ps.setCruiseSpeed(CRUISE_SPEED)
    ps.setHorizontalTrajectoryGain(HORIZONTAL_TRAJECTORY_GAIN); ps.setTargetAcceptanceRadius(TARGET_ACCEPTANCE_RADIUS)
    ps.reset(np.zeros(2), np.zeros(2), np.zeros(2))
    return ps


def _expect_limits(out):
    assert np.all(np.abs(out["velocity"]) <= MAX_VELOCITY + 1e-9)
    assert np.all(np.abs(out["acceleration"]) <= MAX_ACCELERATION + 1e-9)
    assert np.all(np.abs(out["jerk"]) <= MAX_JERK)


def test_position_smoothing_all_zero_case():
    out = PositionSmoothing().generateSetpoints(np.zeros(2), np.zeros((3, 2)), np.zeros(2), 0.0)
    for k in ("jerk", "acceleration", "velocity", "position", "unsmoothed_velocity"):
        np.testing.assert_array_equal(out[k], np.zeros(2))


@pytest.mark.parametrize("integrate_velocity", [False, True])
def test_position_smoothing_reaches_target(integrate_velocity):
    # PX4 reachesTargetPositionSetpoint / reachesTargetVelocityIntegration: from rest at 0 to (12, 17) at 50 Hz, the
    # drone at the trajectory's position (or integrating its velocity), within 2000 iterations (matrix ==: 1e-4)
    ps, target = _position_smoothing(), np.array([12.0, 17.0])
    wps, position = np.stack([np.zeros(2), target, target]), np.zeros(2)
    for it in range(2000):
        out = ps.generateSetpoints(position, wps, np.zeros(2), 0.02)
        position = position + out["velocity"] * 0.02 if integrate_velocity else out["position"]
        _expect_limits(out)
        if np.all(np.abs(position - target) <= 1e-4):
            break
    assert it < 1999 and np.all(np.abs(position - target) <= 1e-4), (it, position)


def test_position_smoothing_reaches_target_with_initial_feedforward_velocity():
    # PX4 reachesTargetInitialVelocity: ff velocity (1, 0.1) on the first call, within XY_ACC_RAD = 10 m in < 20000
    ps, target = _position_smoothing(), np.array([12.0, 17.0])
    wps, position, ff = np.stack([np.zeros(2), target, target]), np.zeros(2), np.array([1.0, 0.1])
    for it in range(20000):
        out = ps.generateSetpoints(position, wps, ff, 0.02)
        position, ff = out["position"], np.zeros(2)
        _expect_limits(out)
        if np.linalg.norm(position - target) < 10.0:
            break
    assert np.linalg.norm(position - target) < 10.0 and it < 19999


def test_the_velocity_setpoint_is_the_speed_the_trajectory_can_still_stop_from():
    # TrajMath: computeMaxSpeedFromDistance(j 4, a 3, d, 0) = (-9 + sqrt(81 + 24 d)) / 2; 5.07 m -> 2.62 m/s
    assert compute_max_speed_from_distance(4.0, 3.0, 5.0, 0.0) == pytest.approx((-9 + math.sqrt(81 + 120)) / 2)
    assert compute_max_speed_from_distance(4.0, 3.0, 0.0, 1.5) == 1.5          # at least the final speed
    assert compute_braking_distance_from_velocity(4.0, 4.0, 3.0, 0.6 * 4.0) == pytest.approx(4.0 * (4.0 / 6.0 + 0.6))
    ps = _position_smoothing()
    out = ps.generateSetpoints(np.zeros(2), np.array([[0.0, 0.0], [5.0, 0.0], [5.0, 0.0]]), np.full(2, np.nan), 0.02)
    np.testing.assert_allclose(out["unsmoothed_velocity"], [compute_max_speed_from_distance(4.0, 3.0, 5.0, 0.0), 0.0])
    far = ps.generateSetpoints(np.zeros(2), np.array([[0.0, 0.0], [500.0, 0.0], [500.0, 0.0]]), np.full(2, np.nan), 0.02)
    assert far["unsmoothed_velocity"][0] == CRUISE_SPEED                        # capped at the cruise speed


def test_the_trajectory_waits_for_a_vehicle_that_lags_behind():
    # _generateTrajectory's time stretch: 1 - error / MPC_XY_ERR_MAX while the drone is behind; 0 from 2 m on
    ps = _position_smoothing()
    wps = np.array([[0.0, 0.0], [50.0, 0.0], [50.0, 0.0]])
    for _ in range(100):
        out = ps.generateSetpoints(out["position"] if _ else np.zeros(2), wps, np.full(2, np.nan), 0.02)
    x = out["position"][0]
    stuck = ps.generateSetpoints(np.array([x - 2.5, 0.0]), wps, np.full(2, np.nan), 0.02)
    assert stuck["position"][0] == x                                            # frozen: 2.5 m behind
    half = ps.generateSetpoints(np.array([x - 1.0, 0.0]), wps, np.full(2, np.nan), 0.02)
    assert 0.0 < half["position"][0] - x < out["velocity"][0] * 0.02           # slowed


# ------------------------------------------------------------------ the Hold (FlightTaskAuto + PositionControl)
def _fly_hold(model: str, v0_m_s: float, a0_m_s2: float, params: AutoParams | None = None, c0_per_s: float = 0.1,
              acc_limit_m_s2: float = 2.0, seconds: float = 20.0, h: float = 0.1, rng=None, wind_sigma: float = 0.0):
    """A vehicle flying north at v0 (accelerating at a0) enters Hold at x = 0: eq. 9 with calm mean wind (drag c0 v),
    optional wind noise. Returns (Hold point x, along-track positions, accelerations, jerk-limited trajectory info)."""
    s = np.array([0.0, 0.0, v0_m_s, 0.0])
    hold = braking_stop_m(s[None])[0]
    a_prev = np.array([a0_m_s2, 0.0])
    m = None
    if model == "px4":
        m = Px4AutoXY(params)
        m.activate(s, hold, a_prev)
    xs, accs, sps = [s.copy()], [a_prev.copy()], []
    for _ in range(int(round(seconds / h))):
        if model == "pd":
            a = jerk_limited_m_s2(a_prev, hold_acc_m_s2(s[None], hold[None], acc_limit_m_s2)[0], 4.0, h)
        else:
            a = m.acc_m_s2(s, h, acc_limit_m_s2)
            sps.append({k: v.copy() for k, v in m.last_setpoints.items()})
        a = saturate_norm(a, acc_limit_m_s2)
        dw = rng.standard_normal(2) * wind_sigma * math.sqrt(h) if rng is not None else np.zeros(2)
        s = np.array([s[0] + s[2] * h, s[1] + s[3] * h, s[2] + (a[0] - c0_per_s * s[2]) * h + dw[0],
                      s[3] + (a[1] - c0_per_s * s[3]) * h + dw[1]])
        a_prev = a
        xs.append(s.copy()); accs.append(a.copy())
    return hold, np.array(xs), np.array(accs), sps


@pytest.mark.parametrize("a0", [0.0, 2.0])
def test_the_hold_trajectory_respects_px4s_limits_and_the_vehicle_reaches_and_holds_the_point(a0):
    hold, xs, accs, sps = _fly_hold("px4", 4.0, a0)
    acc_sp = np.array([sp["acceleration"] for sp in sps])
    vel_sp = np.array([sp["velocity"] for sp in sps])
    jerk_sp = np.array([sp["jerk"] for sp in sps])
    assert np.all(np.abs(jerk_sp) <= 4.0) and np.all(np.abs(acc_sp) <= 3.0 + 1e-9)      # MPC_JERK_AUTO, MPC_ACC_HOR
    assert np.all(np.abs(vel_sp) <= 5.0 + 1e-9)                                         # MPC_XY_CRUISE
    # the trajectory's acceleration changes at most MPC_JERK_AUTO x 0.1 s per sub-step (after its first update,
    # which drops the acceleration it was reset to: PX4's)
    assert acc_sp[0, 0] == 0.0
    assert np.max(np.abs(np.diff(acc_sp[:, 0]))) <= 0.4 + 1e-9
    # the vehicle stops at the Hold point and stays there
    assert np.linalg.norm(xs[-1, 0:2] - hold) < 0.01 and np.linalg.norm(xs[-1, 2:4]) < 0.01
    assert np.all(np.linalg.norm(xs[100:, 0:2] - hold, axis=1) < 0.05)                  # from 10 s on


def _overshoot_m(hold, xs):
    return float(xs[:, 0].max() - hold[0])


def test_entering_hold_at_cruise_and_while_accelerating_overshoots_as_measured():
    """The case of docs/default_controller.md ("Hold builds its braking up at MPC_JERK_AUTO"): 4 m/s north, in calm
    air with the mock's drag (c0 = 0.1 /s), airframe limit 2 m/s^2. Measured with PX4's trajectory and position loop
    (1 cycle per 0.1 s sub-step): the vehicle stops 1 mm short of the Hold point at cruise and when accelerating at
    2 m/s^2 (PX4 drops the last acceleration: the task is new); the old Hold overshoots by 0 and 1.74 m."""
    pd0 = _overshoot_m(*_fly_hold("pd", 4.0, 0.0)[:2])
    pd2 = _overshoot_m(*_fly_hold("pd", 4.0, 2.0)[:2])
    px0 = _overshoot_m(*_fly_hold("px4", 4.0, 0.0)[:2])
    px2 = _overshoot_m(*_fly_hold("px4", 4.0, 2.0)[:2])
    assert pd0 == pytest.approx(0.0, abs=1e-3) and pd2 == pytest.approx(1.738, abs=0.01), (pd0, pd2)
    assert px0 == pytest.approx(-0.001, abs=0.002) and px2 == pytest.approx(-0.001, abs=0.002), (px0, px2)
    # without the mock's drag (c0 -> 0) the airframe's 2 m/s^2 cannot follow PX4's 3 m/s^2 (MPC_ACC_HOR) braking:
    # 0.37 m (0.34 accelerating) past the point; the old Hold: 0.13 / 2.97 m
    assert _overshoot_m(*_fly_hold("px4", 4.0, 0.0, c0_per_s=0.0)[:2]) == pytest.approx(0.368, abs=0.01)
    assert _overshoot_m(*_fly_hold("px4", 4.0, 2.0, c0_per_s=0.0)[:2]) == pytest.approx(0.344, abs=0.01)
    assert _overshoot_m(*_fly_hold("pd", 4.0, 2.0, c0_per_s=0.0)[:2]) == pytest.approx(2.973, abs=0.01)


def test_keeping_the_reset_acceleration_would_overshoot_so_px4_drops_it():
    # first_update_dt_s = 0: the trajectory keeps the +2 m/s^2 it was reset to and overshoots ~3 m (measured 2.97)
    keep = _overshoot_m(*_fly_hold("px4", 4.0, 2.0, AutoParams(first_update_dt_s=0.0))[:2])
    assert keep > 2.5, keep


def test_a_finer_trajectory_step_changes_little():
    # PX4 runs the trajectory at ~50 Hz; the mock's controller acts per 0.1 s sub-step. 5 trajectory cycles per
    # sub-step move the stop by ~1 cm (measured -0.001 -> +0.008 m past the point)
    coarse = _overshoot_m(*_fly_hold("px4", 4.0, 2.0)[:2])
    fine = _overshoot_m(*_fly_hold("px4", 4.0, 2.0, AutoParams(internal_dt_s=0.02))[:2])
    assert abs(fine - coarse) < 0.02 and fine == pytest.approx(0.008, abs=0.003), (coarse, fine)


def test_the_velocity_integrator_holds_the_point_against_a_steady_wind():
    # eq. 9's drag towards a mean wind of (1, -1) m/s is a steady force: a P-only loop would sit off the point;
    # PX4's velocity integrator (MPC_XY_VEL_I_ACC) brings the vehicle back to it. Wind noise from a seeded Generator.
    rng = np.random.Generator(np.random.PCG64(7))
    s = np.array([0.0, 0.0, 0.0, 0.0])
    m = Px4AutoXY()
    m.activate(s, np.zeros(2), np.zeros(2))
    wind = WindParams()
    for k in range(600):
        a = saturate_norm(m.acc_m_s2(s, 0.1, 2.0), 2.0)
        dw = rng.standard_normal(2) * math.sqrt(0.1) @ wind.V_o.T
        s = np.concatenate([s[0:2] + s[2:4] * 0.1, s[2:4] + (a - wind.c0_per_s * (s[2:4] - wind.v_o)) * 0.1 + dw])
        if k == 599:
            assert np.linalg.norm(s[0:2]) < 0.3, s
    m_no_i = Px4AutoXY(AutoParams(mpc_xy_vel_i_acc_per_s2=0.0))
    s = np.zeros(4)
    m_no_i.activate(s, np.zeros(2), np.zeros(2))
    for _ in range(600):
        a = saturate_norm(m_no_i.acc_m_s2(s, 0.1, 2.0), 2.0)
        s = np.concatenate([s[0:2] + s[2:4] * 0.1, s[2:4] + (a - wind.c0_per_s * (s[2:4] - wind.v_o)) * 0.1])
    # steady state without I: 0.1 (v - v_o) = P_v (P_p e - v) with v = 0 -> e = 0.1 v_o / (1.8 x 0.95) = 0.058 m
    np.testing.assert_allclose(s[0:2], wind.v_o * 0.1 / (1.8 * 0.95), atol=1e-3)


def test_params_are_checked():
    with pytest.raises(ValueError, match="mpc_jerk_auto_m_s3"):
        AutoParams(mpc_jerk_auto_m_s3=0.0)
    with pytest.raises(ValueError, match="internal_dt_s"):
        AutoParams(internal_dt_s=0.0)
    with pytest.raises(RuntimeError, match="before activate"):
        Px4AutoXY().acc_m_s2(np.zeros(4), 0.1, 2.0)
