"""MockVehicle's PX4 behaviour without sockets: a fake clock and a list for what it sends."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mavlink_bridge import (
    PX4_HOLD,
    PX4_POSCTL,
    PX4_OFFBOARD,
    CommandAck,
    CommandLong,
    Heartbeat,
    LocalPositionNed,
    MavFrame,
    MavResult,
    ParamSet,
    ParamValue,
    Received,
    SetPositionTargetLocalNed,
    acceleration_setpoint,
)
from mock_vehicle.params import PARAM_SPECS, ParamTable
from mock_vehicle.plant import WindParams
from mock_vehicle.vehicle import MockVehicle, VehicleConfig, check_setpoint


class Clock:
    def __init__(self) -> None:
        self.t = 1000.0

    def __call__(self) -> float:
        return self.t


def make(**cfg):
    clock, sent = Clock(), []
    v = MockVehicle(VehicleConfig(**cfg), lambda msg, port: sent.append(msg), clock=clock)
    return v, clock, sent


def rx(msg, src=(1, 195)) -> Received:
    return Received(msg, *src)


def cmd(command, *params, target=1) -> Received:
    p = tuple(float(x) for x in params) + (0.0,) * (7 - len(params))
    return rx(CommandLong(target, 1, command, p))


def acks(sent):
    return [m for m in sent if isinstance(m, CommandAck)]


def stream(v, clock, seconds, acc=(1.0, 0.0, 0.0), rate_hz=20.0, t_ms=0):
    for _ in range(int(seconds * rate_hz)):
        v.handle(rx(acceleration_setpoint(1, 1, acc, t_ms)))
        clock.t += 1.0 / rate_hz
        v.tick()


@pytest.mark.parametrize(
    "changes, kind",
    [
        (dict(target_system=2), "setpoint wrong target system"),
        (dict(target_component=5), "setpoint wrong target component"),
        (dict(coordinate_frame=MavFrame.GLOBAL), "setpoint unsupported frame"),
        (dict(coordinate_frame=MavFrame.LOCAL_OFFSET_NED), "setpoint unsupported frame"),
        (dict(type_mask=3135 | 512), "setpoint FORCE_SET bit"),
        (dict(type_mask=0x01FF | 0x0C00), "setpoint ignores everything"),
        (dict(afy_m_s2=math.inf), "setpoint non-finite field"),
        (dict(afx_m_s2=math.nan), "setpoint non-finite field"),
    ],
)
def test_px4_setpoint_filter_rejects(changes, kind):
    sp = SetPositionTargetLocalNed(**{**acceleration_setpoint(1, 1, (1.0, 0.0, 0.0), 0).__dict__, **changes})
    assert check_setpoint(sp, 1, 1)[0] == kind


def test_px4_setpoint_filter_accepts_broadcast_body_ned_and_nan_in_ignored_fields():
    base = acceleration_setpoint(0, 0, (1.0, 0.0, 0.0), 0)
    assert check_setpoint(base, 3, 1) is None
    sp = SetPositionTargetLocalNed(**{**base.__dict__, "coordinate_frame": MavFrame.BODY_NED, "x_m": math.nan})
    assert check_setpoint(sp, 3, 1) is None  # x is ignored by mask 3135


def test_offboard_gate_is_px4s_timeout_one_recent_setpoint_is_enough():
    """PX4 (commander/HealthAndArmingChecks/checks/offboardCheck.cpp): OFFBOARD needs an offboard setpoint
    within COM_OF_LOSS_T, not a stream of some duration: MAVSDK's set_acceleration_ned() then start()."""
    v, clock, sent = make()
    v.handle(cmd(400, 1))
    v.handle(cmd(176, 1 | 128, 6))                      # no setpoint yet
    assert acks(sent)[-1].result == MavResult.TEMPORARILY_REJECTED and v.mode == PX4_HOLD
    v.handle(rx(acceleration_setpoint(1, 1, (0.5, 0.0, 0.0), 0)))
    v.handle(cmd(176, 1 | 128, 6))                      # at once
    assert acks(sent)[-1].result == MavResult.ACCEPTED and v.mode == PX4_OFFBOARD
    assert acks(sent)[-1].target_system == 1 and acks(sent)[-1].target_component == 195  # to the sender


def test_offboard_gate_refuses_a_setpoint_older_than_com_of_loss_t():
    v, clock, sent = make(com_of_loss_t_s=1.0)
    v.handle(cmd(400, 1))
    v.handle(rx(acceleration_setpoint(1, 1, (0.5, 0.0, 0.0), 0)))
    clock.t += 1.1
    v.tick()
    v.handle(cmd(176, 1, 6))
    assert acks(sent)[-1].result == MavResult.TEMPORARILY_REJECTED and v.mode == PX4_HOLD
    stream(v, clock, 3.0, rate_hz=1.5)                  # a slow stream is still fresh enough at the moment of the request
    v.handle(cmd(176, 1, 6))
    assert acks(sent)[-1].result == MavResult.ACCEPTED


def test_failsafe_after_com_of_loss_t_and_hold_keeps_position():
    v, clock, sent = make(com_of_loss_t_s=1.0, initial_pos_m=(5.0, 5.0))
    v.handle(cmd(400, 1))
    stream(v, clock, 1.2)
    v.handle(cmd(176, 1, 6))
    stream(v, clock, 2.0)
    assert v.mode == PX4_OFFBOARD and v.state[0] > 5.0
    for _ in range(9):
        clock.t += 0.1
        v.tick()
    assert v.mode == PX4_OFFBOARD  # 0.9 s without setpoints: still fine
    clock.t += 0.2
    v.tick()
    assert v.mode == PX4_HOLD
    hold_at = v.hold_pos_m.copy()
    for _ in range(200):
        clock.t += 0.1
        v.tick()
    assert np.linalg.norm(v.state[0:2] - hold_at) < 3.0 and np.all(np.isfinite(v.state))


def _flying_north_in_offboard(cruise_s: float = 0.0, **cfg):
    """A vehicle flying north at ~4 m/s in OFFBOARD with no wind noise (the along-track motion after a mode change is
    that mode's alone): (vehicle, clock, north position, north velocity). It accelerates at 2 m/s^2 to the end, or
    cruises for its last ``cruise_s`` (acceleration 0). ``cfg``: more VehicleConfig fields. The airframe flies its
    command at once (``acc_lag_s`` 0 unless given): these tests pin PX4's mode logic, not the lag's overshoot (with
    PX4's 0.154 s the Hold's stop is overshot by the lag's ~tau v and flown back to)."""
    cfg.setdefault("acc_lag_s", 0.0)
    calm = WindParams(mean_wind_m_s=(0.0, 0.0), wind_diffusion_m_s=((0.0, 0.0), (0.0, 0.0)))
    v, clock, _ = make(initial_pos_m=(0.0, 0.0), initial_vel_m_s=(0.0, 0.0), wind=calm, **cfg)
    v.handle(cmd(400, 1))
    stream(v, clock, 2.0, acc=(2.0, 0.0, 0.0))
    v.handle(cmd(176, 1, 6))
    stream(v, clock, 2.0, acc=(2.0, 0.0, 0.0))
    stream(v, clock, cruise_s, acc=(0.0, 0.0, 0.0))
    x0, vx0 = float(v.state[0]), float(v.state[2])
    assert v.mode == PX4_OFFBOARD and vx0 > 3.0
    return v, clock, x0, vx0


@pytest.mark.parametrize("model,back_m", [("px4", 0.005), ("pd", 0.001)])
def test_hold_in_flight_targets_px4s_braking_stop_and_never_flies_back(model, back_m):
    # given a vehicle cruising north at ~4 m/s in OFFBOARD, with PX4's Hold (the default) or the PD Hold
    v, clock, x0, vx0 = _flying_north_in_offboard(cruise_s=0.5, hold_model=model)
    # when it is switched to Hold (MAV_CMD_DO_SET_MODE, AUTO.LOITER)
    v.handle(cmd(176, 1, 4, 3))
    assert v.mode == PX4_HOLD
    # then the hold point is PX4's braking stop ahead (Navigator::calculate_breaking_stop with MPC_ACC_HOR = 3 m/s^2,
    # the 0.6 s delay term: |v| (|v| / 6 + 0.6) along the course), not the position where the hold began ...
    assert v.hold_pos_m[0] - x0 == pytest.approx(vx0 * (vx0 / 6.0 + 0.6), rel=1e-6)
    assert abs(v.hold_pos_m[1] - v.state[1]) < 1e-6
    # ... and the vehicle brakes to it without overshooting and flying back against its former course (PX4's position
    # loop settles back by a few millimetres)
    xs = []
    for _ in range(300):
        clock.t += 0.1
        v.tick()
        xs.append(float(v.state[0]))
    assert np.all(np.diff(xs) >= -back_m) and abs(xs[-1] - v.hold_pos_m[0]) < 0.3, (max(xs), xs[-1], v.hold_pos_m)


@pytest.mark.parametrize("cruise_s", [0.5, 0.0])
def test_hold_builds_its_braking_up_at_mpc_jerk_auto_from_the_acceleration_flown_before(cruise_s):
    # given a vehicle with the PD Hold (hold_model "pd": the model before PX4's trajectory was ported, whose acceleration
    # ramps from the one flown before) flying north at ~4 m/s in OFFBOARD, cruising or still accelerating at 2 m/s^2
    v, clock, x0, vx0 = _flying_north_in_offboard(cruise_s=cruise_s, hold_model="pd")
    a_before = float(v.applied_acc_m_s2[0])
    # when it is switched to Hold, and the physics advances sub-step by sub-step (0.1 s)
    v.handle(cmd(176, 1, 4, 3))
    acc = [a_before]
    for _ in range(30):
        clock.t += 0.1
        v.tick()
        acc.append(float(v.applied_acc_m_s2[0]))
    # then the acceleration changes by at most MPC_JERK_AUTO (4 m/s^3) x 0.1 s per sub-step (PX4's PositionSmoothing,
    # reset to the last setpoint's acceleration), so the braking reaches the airframe's 2 m/s^2 only after
    # (a_before + 2) / 4 s, and it does reach it (the braking stop needs it)
    assert v.params["MPC_JERK_AUTO"] == 4.0
    assert np.max(np.abs(np.diff(acc))) <= 0.4 + 1e-9, np.diff(acc)
    ramp = int(round((a_before + 2.0) / 0.4))
    assert acc[ramp - 1] > -2.0 + 1e-9 and min(acc) == pytest.approx(-2.0, abs=1e-9), acc
    # and a Hold entered at cruise loses less speed in its first 0.5 s than braking at the limit would (1 m/s)
    if cruise_s:
        assert 0.4 <= a_before - acc[5] <= 2.0 and np.mean(acc[1:6]) > -1.3, acc


@pytest.mark.parametrize("cruise_s", [0.5, 0.0])
def test_hold_with_px4s_trajectory_stops_at_the_braking_stop_where_the_pd_hold_overshoots(cruise_s):
    """--hold-model px4 (mock_vehicle.smoothing.Px4AutoXY, the default) against the PD Hold: a vehicle at ~4 m/s north, cruising
    or still accelerating at 2 m/s^2, switched to Hold. Measured: the PD Hold overshoots the braking stop by 0 m
    cruising and 1.60 m accelerating (then comes back); PX4's trajectory (which drops the last acceleration at
    activation and plans with MPC_JERK_AUTO, MPC_ACC_HOR) stops within 2 mm of it in both cases."""
    overshoot = {}
    for model in ("pd", "px4"):
        v, clock, x0, vx0 = _flying_north_in_offboard(cruise_s=cruise_s, hold_model=model)
        a_before = float(v.applied_acc_m_s2[0])
        v.handle(cmd(176, 1, 4, 3))
        assert v.mode == PX4_HOLD and v.hold_pos_m[0] - x0 == pytest.approx(vx0 * (vx0 / 6.0 + 0.6), rel=1e-6)
        xs, acc = [], [a_before]
        for _ in range(300):
            clock.t += 0.1
            v.tick()
            xs.append(float(v.state[0]))
            acc.append(float(v.applied_acc_m_s2[0]))
        overshoot[model] = max(xs) - v.hold_pos_m[0]
        assert abs(xs[-1] - v.hold_pos_m[0]) < 0.01 and abs(v.state[2]) < 0.01, (model, xs[-1], v.hold_pos_m)
        if model == "px4":
            # PX4's task is new at the switch: its trajectory drops the acceleration flown before, and the position
            # loop brakes at once (accelerating at 2 m/s^2 before: the first sub-step's is <= 0; cruising: ~0)
            assert acc[1] <= 0.0 if a_before > 1.0 else abs(acc[1]) < 0.01, (a_before, acc[:4])
            assert np.all(np.diff(xs) >= -0.005) and max(xs) - xs[-1] < 0.005   # settles back by < 5 mm at most
    if cruise_s:
        assert overshoot["pd"] == pytest.approx(0.0, abs=0.01) and abs(overshoot["px4"]) < 0.002, overshoot
    else:
        assert overshoot["pd"] == pytest.approx(1.60, abs=0.03) and abs(overshoot["px4"]) < 0.002, overshoot


def test_hold_model_is_checked():
    with pytest.raises(ValueError, match="hold_model"):
        VehicleConfig(hold_model="lqr")


def test_position_mode_in_flight_locks_where_px4s_braking_setpoint_stops():
    # given a vehicle flying north at ~4 m/s in OFFBOARD (no wind noise)
    v, clock, x0, vx0 = _flying_north_in_offboard()
    # when it is switched to Position mode (MAV_CMD_DO_SET_MODE, POSCTL) with no stick input
    v.handle(cmd(176, 1, 3))
    assert v.mode == PX4_POSCTL
    # then it brakes along PX4's velocity setpoint (drag 2 MPC_ACC_HOR / MPC_VEL_MANUAL = 0.6/s, boosted up to
    # sqrt(10) by a 0.8 s filter) and locks where it is when that setpoint reaches zero: the setpoint alone stops
    # between (v0 - 1) / k + 2 / (3 k) for k = 0.6 sqrt(10) (full boost) and k = 0.6 (none); the airframe's 2 m/s^2
    # cannot follow the boosted drag, so the vehicle is still moving when the position locks and comes back to it
    stop = lambda k: (vx0 - 1.0) / k + 2.0 / (3.0 * k)      # noqa: E731
    path_end = float(v.hold_pos_m[0] - x0)
    assert stop(0.6 * 10.0 ** 0.5) < path_end < stop(0.6), (path_end, stop(0.6 * 10.0 ** 0.5), stop(0.6))
    xs, vxs = [], []
    for _ in range(300):
        clock.t += 0.1
        v.tick()
        xs.append(float(v.state[0]))
        vxs.append(float(v.state[2]))
    lock = float(v.hold_pos_m[0])
    assert v.mode == PX4_POSCTL and v.posctl_path is None                  # locked
    # ahead, not where the mode began: past the setpoint's stop (the vehicle brakes at most at 2 m/s^2), about where
    # braking at the limit ends
    assert x0 + path_end <= lock <= x0 + vx0 ** 2 / (2.0 * 2.0) + 0.5, (lock, x0, path_end)
    assert abs(v.hold_pos_m[1] - v.state[1]) < 1e-6
    assert np.all(np.diff(vxs[:10]) <= 1e-9)                                # it brakes at once
    assert abs(xs[-1] - lock) < 0.05 and abs(vxs[-1]) < 0.05                # and holds the lock


def test_frozen_until_first_offboard():
    v, clock, sent = make(initial_pos_m=(150.0, 100.0))
    v.handle(cmd(400, 1))
    for _ in range(50):
        clock.t += 0.1
        v.tick()
    assert tuple(v.state[0:2]) == (150.0, 100.0)
    lp = [m for m in sent if isinstance(m, LocalPositionNed)]
    assert lp and lp[-1].x_m == 150.0


def test_unknown_command_is_unsupported_and_other_targets_are_ignored():
    v, clock, sent = make()
    v.handle(cmd(31000))
    assert acks(sent)[-1].result == MavResult.UNSUPPORTED
    n = len(acks(sent))
    v.handle(cmd(400, 1, target=7))
    assert len(acks(sent)) == n and not v.armed


def test_lockstep_step_and_stale_setpoint():
    v, clock, sent = make(lockstep=True, dt_s=0.5, seed=3)
    v.handle(cmd(400, 1))
    stream(v, clock, 1.2, t_ms=999)
    v.handle(cmd(176, 1, 6))
    assert v.mode == PX4_OFFBOARD and v.time_boot_ms() == 0
    sent.clear()
    v.handle(rx(acceleration_setpoint(1, 1, (1.0, 0.0, 0.0), 0)))
    assert v.time_boot_ms() == 500
    lp = [m for m in sent if isinstance(m, LocalPositionNed)]
    assert lp[-1].time_boot_ms == 500
    sent.clear()
    v.handle(rx(acceleration_setpoint(1, 1, (2.0, 0.0, 0.0), 0)))  # stale
    assert v.time_boot_ms() == 500 and sent == [lp[-1]]
    clock.t += 100.0
    v.tick()
    assert v.mode == PX4_OFFBOARD  # frozen world: no failsafe


def test_param_set_bounds_and_effect():
    v, clock, sent = make()
    v.handle(rx(ParamSet(1, 1, "MPC_ACC_HOR_MAX", 1.0)))
    assert v.plant.params.acc_limit_m_s2 == 1.0
    v.handle(rx(ParamSet(1, 1, "MPC_ACC_HOR_MAX", math.nan)))
    v.handle(rx(ParamSet(1, 1, "NO_SUCH_PARAM", 1.0)))
    pv = [m for m in sent if isinstance(m, ParamValue)]
    assert [p.value for p in pv] == [1.0, 1.0] and pv[0].param_count == len(PARAM_SPECS)
    assert v.rejects.counts == {"PARAM_SET refused": 2}
    with pytest.raises(ValueError, match="outside"):
        ParamTable({"COM_OF_LOSS_T": -1.0})


def test_heartbeat_reports_px4_modes():
    v, clock, sent = make()
    hb = v._heartbeat()
    assert hb.px4_mode == PX4_HOLD and not hb.armed
    v.handle(cmd(400, 1))
    assert [m for m in sent if isinstance(m, Heartbeat)][-1].armed


def test_lockstep_loop_sleeps_until_its_next_event_and_resends_only_when_idle():
    """Given a lockstep vehicle stepping in OFFBOARD, its next deadline is never in the past
    (the I/O loop blocks instead of spinning) and a step's telemetry is not followed by
    wall-clock copies; an idle vehicle re-sends its position at lockstep_resend_hz."""
    v, clock, sent = make(lockstep=True, dt_s=0.5, seed=3, lockstep_resend_hz=5.0)
    v.handle(cmd(400, 1))
    stream(v, clock, 1.2, t_ms=999)
    v.handle(cmd(176, 1, 6))
    assert v.mode == PX4_OFFBOARD
    for k in range(20):                                # a controller stepping every 50 ms
        v.handle(rx(acceleration_setpoint(1, 1, (1.0, 0.0, 0.0), k * 500)))
        assert v.next_deadline() > clock.t, "a deadline in the past makes the loop spin"
        clock.t += 0.05
        v.tick()
    lp = [m.time_boot_ms for m in sent if isinstance(m, LocalPositionNed)]
    assert lp[-20:] == [500 * (k + 1) for k in range(20)]            # one per step, no wall-clock copies
    assert lp.count(10_000) == 1
    sent.clear()
    idle_from = clock.t
    while True:                                        # idle for 1 s: re-sent at 5 Hz
        clock.t = max(clock.t, v.next_deadline())
        if clock.t > idle_from + 1.0:
            break
        v.tick()
    resent = [m.time_boot_ms for m in sent if isinstance(m, LocalPositionNed)]
    assert 4 <= len(resent) <= 6 and set(resent) == {10_000}


def test_lockstep_idle_traffic_resend_backs_off():
    """An idle lockstep vehicle with a proximity sensor re-sends its current traffic set at
    traffic_rate_hz at first, then ever more slowly (at most every 2 s)."""
    from mavlink_bridge import NamedValueInt

    v, clock, sent = make(lockstep=True, dt_s=0.5, traffic_rate_hz=5.0)
    v.attach_world(lambda t, s: None)
    v.on_world_answer(0, np.array([1]), np.array([[1.0, 2.0, 0.0, 0.0]]))
    sent.clear()
    start = clock.t
    while clock.t < start + 30.0:
        clock.t = max(clock.t + 1e-3, v.next_deadline())
        v.tick()
    markers = [m for m in sent if isinstance(m, NamedValueInt)]
    assert 12 <= len(markers) <= 20                    # 5 Hz would be 150
    assert all(m.time_boot_ms == 0 and m.value == 1 for m in markers)


def test_realtime_next_deadline_includes_the_offboard_loss_failsafe():
    v, clock, sent = make(com_of_loss_t_s=1.0, rates_hz={k: 0.0 for k in VehicleConfig().rates_hz}, physics_dt_s=5.0)
    v.handle(cmd(400, 1))
    stream(v, clock, 1.2)
    v.handle(cmd(176, 1, 6))                            # OFFBOARD entry restarts the loss timer
    assert v.mode == PX4_OFFBOARD
    entered = clock.t
    d = v.next_deadline()
    assert entered + 1.0 < d <= entered + 1.0 + 1e-3    # COM_OF_LOSS_T after it, not a polling period later
    clock.t = d
    v.tick()
    assert v.mode == PX4_HOLD


def test_world_datagrams_are_the_documented_struct_layout():
    """Given answers of 0..40 random float64 states, pack_answer gives exactly the bytes of the
    documented layout packed entry by entry with struct ("<4sBBHIH" then "<H4f": float32
    rounding included), and unpack gives them back; malformed datagrams raise ValueError."""
    import struct

    from mock_vehicle.world import KIND_ANSWER, MAGIC, Answer, pack_answer, pack_report, unpack

    rng = np.random.default_rng(4)
    for m in (0, 1, 2, 24, 40):
        ids = np.sort(rng.choice(1000, size=m, replace=False)).astype(np.int64)
        states = rng.normal(size=(m, 4)) * 10.0 ** rng.integers(-3, 4, size=(m, 4))
        data = pack_answer(Answer(7, 123456, ids, states))
        ref = struct.pack("<4sBBHIH", MAGIC, 1, KIND_ANSWER, 7, 123456, m) + b"".join(
            struct.pack("<H4f", int(i), *(float(v) for v in s)) for i, s in zip(ids, states))
        assert data == ref
        kind, vid, t_ms, ids2, st2 = unpack(data)
        assert (kind, vid, t_ms) == (KIND_ANSWER, 7, 123456)
        assert np.array_equal(ids2, ids) and np.array_equal(st2, states.astype(np.float32).astype(np.float64))
    kind, vid, t_ms, ids, st = unpack(pack_report(3, 500, np.array([1.5, -2.0, 0.25, 0.0])))
    assert (kind, vid, t_ms, ids.tolist(), st.tolist()) == (1, 3, 500, [3], [[1.5, -2.0, 0.25, 0.0]])
    good = pack_answer(Answer(1, 0, np.array([2]), np.zeros((1, 4))))
    with pytest.raises(ValueError, match="does not hold"):
        unpack(good[:-1])
    with pytest.raises(ValueError, match="non-finite"):
        unpack(pack_answer(Answer(1, 0, np.array([2, 3]), np.array([[0.0, math.inf, 0, 0], [0, 0, 0, 0]]))))
