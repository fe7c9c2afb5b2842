"""The mock as a real-field stand-in (issue 19): ground start, takeoff, the altitude loop, land and
auto-disarm, the offboard-loss action, PX4's two setpoint gates, its own EKF origin. A fake clock, no
sockets (tests/test_mock_unit.py's helpers). docs/mavlink.md cites the PX4 source of every rule."""

from __future__ import annotations

import math

import numpy as np
import pymap3d
import pytest
from test_mock_unit import acks, cmd, make, rx

from mavlink_bridge import (
    PX4_HOLD,
    PX4_LAND,
    PX4_OFFBOARD,
    PX4_TAKEOFF,
    GpsGlobalOrigin,
    HomePosition,
    MavFrame,
    MavLandedState,
    MavResult,
    ParamSet,
    SetPositionTargetLocalNed,
    StatusText,
    acceleration_setpoint,
    altitude_hold_setpoint,
)
from mock_vehicle.lifecycle import vertical_step
from mock_vehicle.setpoint import CONTROLLER_KINDS, RECEIVER_KINDS, classify_setpoint
from mock_vehicle.vehicle import check_setpoint

HOME = (47.397742, 8.545594, 488.0)
NAN7 = (math.nan, 0, 0, math.nan, math.nan, math.nan, math.nan)     # MAV_CMD_NAV_TAKEOFF, no altitude


def run(v, clock, seconds, dt=0.05, setpoint=None):
    for _ in range(int(round(seconds / dt))):
        if setpoint is not None:
            v.handle(rx(setpoint))
        clock.t += dt
        v.tick()


def landed_state(v) -> int:
    return v._telemetry("extended_sys_state").landed_state


def airborne(z_m=-2.5, **cfg):
    """A ground-start vehicle armed, taken off and holding at ``-z_m`` (MIS_TAKEOFF_ALT unless given)."""
    v, clock, sent = make(start_on_ground=True, **cfg)
    v.handle(cmd(400, 1))
    v.handle(cmd(22, *NAN7[:6], HOME[2] - z_m))
    run(v, clock, 8.0)
    assert v.mode == PX4_HOLD and v.z_m == pytest.approx(z_m, abs=0.05)
    return v, clock, sent


def texts(sent) -> list[str]:
    return [m.text for m in sent if isinstance(m, StatusText)]


# ------------------------------------------------------------------ the ground and takeoff
def test_given_a_ground_start_then_the_vehicle_sits_on_the_ground_disarmed_and_the_wind_does_not_move_it():
    v, clock, sent = make(start_on_ground=True, initial_pos_m=(3.0, 4.0))
    run(v, clock, 10.0)
    assert not v.armed and v.landed and v.z_m == 0.0
    assert tuple(v.state) == (3.0, 4.0, 0.0, 0.0)
    assert landed_state(v) == MavLandedState.ON_GROUND


def test_takeoff_while_disarmed_is_a_mode_change_and_arming_then_starts_the_climb():
    """PX4's Commander only changes the mode (AUTO.TAKEOFF) and accepts it; its own `commander takeoff`
    sends NAV_TAKEOFF first and arms after the ACK."""
    v, clock, sent = make(start_on_ground=True)
    v.handle(cmd(22, *NAN7))
    assert acks(sent)[-1].result == MavResult.ACCEPTED and v.mode == PX4_TAKEOFF
    run(v, clock, 3.0)
    assert v.landed and not v.armed and v.z_m == 0.0 and landed_state(v) == MavLandedState.ON_GROUND
    v.handle(cmd(400, 1))
    run(v, clock, 1.0)
    assert not v.landed and v.z_m < -0.5 and landed_state(v) == MavLandedState.TAKEOFF


def test_given_armed_on_the_ground_when_takeoff_then_it_climbs_at_mpc_tko_speed_and_loiters_at_mis_takeoff_alt():
    v, clock, sent = make(start_on_ground=True)
    v.handle(cmd(400, 1))
    v.handle(cmd(22, *NAN7))
    assert acks(sent)[-1].result == MavResult.ACCEPTED and v.mode == PX4_TAKEOFF
    assert "Using default takeoff altitude: 2.5 m" in texts(sent)
    run(v, clock, 1.0)
    assert landed_state(v) == MavLandedState.TAKEOFF
    assert v.vz_m_s == pytest.approx(-1.5, abs=0.05)                     # MPC_TKO_SPEED, after the velocity loop's lag
    run(v, clock, 0.7)
    assert v.mode == PX4_HOLD and landed_state(v) == MavLandedState.IN_AIR  # AUTO.LOITER within NAV_MC_ALT_RAD (0.8 m)
    run(v, clock, 4.0)
    assert v.z_m == pytest.approx(-2.5, abs=0.03)                       # and the loiter holds the takeoff's altitude


def test_takeoff_altitude_comes_from_param_7_or_the_parameter_mavsdk_sets_and_never_goes_down():
    v, clock, sent = make(start_on_ground=True)
    v.handle(rx(ParamSet(1, 1, "MIS_TAKEOFF_ALT", 6.0)))
    v.handle(cmd(400, 1))
    v.handle(cmd(22, *NAN7))
    run(v, clock, 9.0)
    assert v.z_m == pytest.approx(-6.0, abs=0.05)
    w, clock, sent = airborne(z_m=-4.0)                                  # param 7: AMSL
    w.handle(cmd(22, *NAN7[:6], HOME[2] + 1.0))                          # below where it is: it stays
    assert acks(sent)[-1].result == MavResult.ACCEPTED and "Already higher than takeoff altitude" in texts(sent)
    run(w, clock, 3.0)
    assert w.mode == PX4_HOLD and w.z_m == pytest.approx(-4.0, abs=0.05)


# ------------------------------------------------------------------ the altitude loop
def test_vertical_step_is_px4s_altitude_loop():
    """Given z far below its setpoint, then vz follows MPC_Z_VEL_P_ACC's first-order lag to
    -MPC_Z_VEL_MAX_UP (3 m/s); a descent is limited by MPC_Z_VEL_MAX_DN (1.5 m/s); one long step is the
    same sub-steps as many short ones, bit for bit; without a z or vz term only az moves vz."""
    z, vz = vertical_step(0.0, 0.0, 0.25, z_sp_m=-100.0)
    assert vz == pytest.approx(-3.0 * (1 - math.exp(-1.0)), abs=0.15)
    z, vz = vertical_step(z, vz, 3.0, z_sp_m=-100.0)
    assert vz == pytest.approx(-3.0, abs=1e-3)
    assert vertical_step(0.0, 0.0, 5.0, z_sp_m=100.0)[1] == pytest.approx(1.5, abs=1e-3)
    long_step = vertical_step(-3.0, 0.5, 1.0, z_sp_m=-10.0, az_ff_m_s2=0.1)
    z, vz = -3.0, 0.5
    for _ in range(10):
        z, vz = vertical_step(z, vz, 0.1, z_sp_m=-10.0, az_ff_m_s2=0.1)
    assert (z, vz) == long_step
    assert vertical_step(-7.0, 0.0, 2.0) == (-7.0, 0.0)                 # hover: the mock's optimistic acc-only z
    assert vertical_step(-7.0, 0.0, 1.0, az_ff_m_s2=-0.5)[1] == pytest.approx(-0.5)


def test_altitude_hold_setpoint_3387_tracks_z_within_px4s_speed_limits_while_x_y_take_the_acceleration():
    v, clock, sent = airborne()
    sp = altitude_hold_setpoint(1, 1, (0.5, 0.0), -20.0, 0)
    assert classify_setpoint(sp, 1, 1) is None                           # both of PX4's gates accept 3387
    v.handle(rx(sp))
    v.handle(cmd(176, 1, 6))
    assert v.mode == PX4_OFFBOARD
    run(v, clock, 2.0, setpoint=sp)
    assert v.vz_m_s == pytest.approx(-3.0, abs=0.05)                     # MPC_Z_VEL_MAX_UP
    run(v, clock, 15.0, setpoint=sp)
    assert v.z_m == pytest.approx(-20.0, abs=0.05) and v.state[2] > 3.0  # held at 20 m; accelerating north
    down = altitude_hold_setpoint(1, 1, (0.0, 0.0), -5.0, 0)
    run(v, clock, 3.0, setpoint=down)
    assert v.vz_m_s == pytest.approx(1.5, abs=0.05)                      # MPC_Z_VEL_MAX_DN
    run(v, clock, 15.0, setpoint=down)
    assert v.z_m == pytest.approx(-5.0, abs=0.05)
    acc = acceleration_setpoint(1, 1, (0.0, 0.0, 0.0), 0)                # 3135: no altitude feedback, z kept (optimistic)
    run(v, clock, 5.0, setpoint=acc)
    assert v.z_m == pytest.approx(-5.0, abs=0.05)


def test_offboard_from_the_ground_lifts_off_only_when_the_setpoint_asks_to_climb():
    v, clock, sent = make(start_on_ground=True)
    v.handle(cmd(400, 1))
    acc = acceleration_setpoint(1, 1, (1.0, 0.0, 0.0), 0)
    v.handle(rx(acc))
    v.handle(cmd(176, 1, 6))
    assert v.mode == PX4_OFFBOARD
    run(v, clock, 2.0, setpoint=acc)
    assert v.landed and v.z_m == 0.0 and v.state[0] == 0.0             # idle on the ground (az = 0)
    climb = altitude_hold_setpoint(1, 1, (0.0, 0.0), -5.0, 0)
    run(v, clock, 6.0, setpoint=climb)
    assert not v.landed and v.z_m == pytest.approx(-5.0, abs=0.1)
    w, clock, sent = make(start_on_ground=True)
    w.handle(cmd(400, 1))
    up = acceleration_setpoint(1, 1, (0.0, 0.0, -0.5), 0)               # az < 0 asks to climb too
    w.handle(rx(up))
    w.handle(cmd(176, 1, 6))
    run(w, clock, 1.0, setpoint=up)
    assert not w.landed and w.z_m < -0.1


# ------------------------------------------------------------------ land and disarm
def test_land_descends_at_mpc_land_speed_touches_down_and_disarms_com_disarm_land_later():
    v, clock, sent = airborne()
    v.handle(cmd(21))
    assert v.mode == PX4_LAND and landed_state(v) == MavLandedState.LANDING
    run(v, clock, 2.0)
    assert v.vz_m_s == pytest.approx(0.7, abs=0.02)                      # MPC_LAND_SPEED
    run(v, clock, 2.5)
    assert v.landed and v.armed and landed_state(v) == MavLandedState.ON_GROUND   # touched down, not yet disarmed
    run(v, clock, 2.1)
    assert not v.armed and "Disarmed by auto disarm on land" in texts(sent)       # COM_DISARM_LAND = 2 s


def test_disarming_in_the_air_is_refused_unless_forced():
    v, clock, sent = airborne()
    v.handle(cmd(400, 0))
    assert acks(sent)[-1].result == MavResult.TEMPORARILY_REJECTED and v.armed
    assert "Disarming denied: not landed" in texts(sent)
    v.handle(cmd(400, 0, 21196))                                         # forced: the motors stop, it falls
    assert acks(sent)[-1].result == MavResult.ACCEPTED and not v.armed and v.landed and v.z_m == 0.0


def test_armed_on_the_ground_without_a_takeoff_disarms_after_com_disarm_prflt():
    v, clock, sent = make(start_on_ground=True)
    v.handle(cmd(400, 1))
    run(v, clock, 9.5)
    assert v.armed
    run(v, clock, 0.6)
    assert not v.armed and "Disarmed by auto preflight disarming" in texts(sent)
    w, clock, sent = make(start_on_ground=True)
    w.handle(rx(ParamSet(1, 1, "COM_DISARM_PRFLT", -1.0)))
    w.handle(rx(ParamSet(1, 1, "COM_DISARM_LAND", 0.0)))                # <= 0 disables either
    w.handle(cmd(400, 1))
    run(w, clock, 15.0)
    assert w.armed


def test_the_air_start_keeps_its_old_rules():
    v, clock, sent = make(initial_pos_m=(150.0, 100.0))
    lp = v._local_position()
    assert (lp.x_m, lp.y_m, lp.z_m) == (150.0, 100.0, -10.0)
    assert v._message_by_id(49) == GpsGlobalOrigin(HOME[0], HOME[1], HOME[2], 0)
    assert not v.landed and landed_state(v) == MavLandedState.ON_GROUND           # disarmed: "on the ground"
    v.handle(cmd(400, 1))
    run(v, clock, 30.0)
    assert v.armed and v.z_m == -10.0                                   # frozen at its slot, no auto-disarm
    v.handle(cmd(400, 0))
    assert acks(sent)[-1].result == MavResult.ACCEPTED and not v.armed  # disarming is always accepted


# ------------------------------------------------------------------ offboard: entry, loss, PX4's setpoint gates
def test_offboard_loss_flies_com_obl_rc_act_hold_by_default_or_land():
    for act, mode in ((0.0, PX4_HOLD), (5.0, PX4_HOLD), (4.0, PX4_LAND)):
        v, clock, sent = airborne()
        v.handle(rx(ParamSet(1, 1, "COM_OBL_RC_ACT", act)))
        sp = altitude_hold_setpoint(1, 1, (0.0, 0.0), -2.5, 0)
        run(v, clock, 0.5, setpoint=sp)
        v.handle(cmd(176, 1, 6))
        run(v, clock, 0.5, setpoint=sp)
        assert v.mode == PX4_OFFBOARD
        run(v, clock, 1.2)
        assert v.mode == mode, act


RECEIVER_REFUSES = [
    (dict(target_system=2), "setpoint wrong target system"),
    (dict(coordinate_frame=MavFrame.LOCAL_OFFSET_NED), "setpoint unsupported frame"),
    (dict(type_mask=3387 | 512), "setpoint FORCE_SET bit"),
    (dict(type_mask=0x0DFF), "setpoint ignores everything"),
    (dict(afx_m_s2=math.nan, afy_m_s2=math.nan, z_m=math.nan), "setpoint ignores everything"),   # NaN is an ignored field
    (dict(coordinate_frame=MavFrame.BODY_NED), "setpoint ignores everything"),   # BODY_NED: no position, and az ignored drops ax, ay
]
CONTROLLER_REFUSES = [
    (dict(type_mask=3387 | 4), "setpoint axis without a term"),          # z ignored too: nothing on z
    (dict(type_mask=3387 | 128), "setpoint axis without a term"),        # ay ignored: nothing on y
    (dict(type_mask=3387 & ~1), "setpoint x/y not in pairs"),            # a position on x, none on y
    (dict(afx_m_s2=math.nan), "setpoint non-finite field"),
]


@pytest.mark.parametrize("changes, kind", RECEIVER_REFUSES + CONTROLLER_REFUSES)
def test_the_setpoint_gates_refuse_what_px4_refuses(changes, kind):
    sp = SetPositionTargetLocalNed(**{**altitude_hold_setpoint(1, 1, (1.0, 0.0), -2.5, 0).__dict__, **changes})
    verdict = classify_setpoint(sp, 1, 1)
    assert verdict.kind == kind and check_setpoint(sp, 1, 1) == (verdict.kind, verdict.detail)
    assert verdict.keeps_offboard == (kind in CONTROLLER_KINDS) and (kind in RECEIVER_KINDS) != verdict.keeps_offboard


def test_the_setpoint_gates_accept_what_px4_accepts():
    base = altitude_hold_setpoint(0, 0, (1.0, 0.0), -2.5, 0)              # broadcast target
    for changes in (dict(), dict(type_mask=3135), dict(type_mask=3135, coordinate_frame=MavFrame.BODY_NED, x_m=math.nan),
                    dict(type_mask=0x0DC7 | 512),                          # velocity only with FORCE: no acceleration, accepted
                    dict(type_mask=0x0DF8)):                               # position only
        sp = SetPositionTargetLocalNed(**{**base.__dict__, **changes})
        assert classify_setpoint(sp, 3, 1) is None, changes


@pytest.mark.parametrize("changes, kind", RECEIVER_REFUSES)
def test_a_setpoint_px4s_receiver_refuses_is_no_offboard_heartbeat_and_changes_nothing(changes, kind):
    v, clock, sent = airborne()
    bad = SetPositionTargetLocalNed(**{**altitude_hold_setpoint(1, 1, (1.0, 0.0), -2.5, 0).__dict__, **changes})
    run(v, clock, 0.5, setpoint=bad)
    v.handle(cmd(176, 1, 6))
    assert acks(sent)[-1].result == MavResult.TEMPORARILY_REJECTED and v.mode == PX4_HOLD
    assert v.rejects.counts[kind] > 0


@pytest.mark.parametrize("changes, kind", CONTROLLER_REFUSES)
def test_a_setpoint_px4s_position_controller_refuses_keeps_offboard_and_stops_the_vehicle(changes, kind):
    v, clock, sent = airborne()
    go = altitude_hold_setpoint(1, 1, (1.0, 0.0), -2.5, 0)
    run(v, clock, 0.2, setpoint=go)
    v.handle(cmd(176, 1, 6))
    run(v, clock, 3.0, setpoint=go)
    assert v.mode == PX4_OFFBOARD and v.state[2] > 2.0
    bad = SetPositionTargetLocalNed(**{**go.__dict__, **changes})
    run(v, clock, 6.0, setpoint=bad)
    assert v.mode == PX4_OFFBOARD and v.rejects.counts[kind] > 0         # still an offboard heartbeat: no failsafe
    assert np.hypot(*v.state[2:4]) < 0.3 and abs(v.vz_m_s) < 0.05      # "stop and wait": velocity 0 (up to the wind)


# ------------------------------------------------------------------ frames
def test_given_its_own_ekf_origin_the_vehicle_reports_local_positions_relative_to_it_and_consistent_wgs84():
    o_lat, o_lon, _ = pymap3d.ned2geodetic(2000.0, 0.0, 0.0, HOME[0], HOME[1], 0.0)
    v, clock, sent = make(start_on_ground=True, initial_pos_m=(10.0, -5.0), origin=(float(o_lat), float(o_lon), HOME[2] + 3.0))
    run(v, clock, 0.5)
    origins = [m for m in sent if isinstance(m, GpsGlobalOrigin)]
    assert len(origins) == 1 and origins[0].lat_deg == pytest.approx(o_lat, abs=1e-12)   # announced once, at boot
    lp = v._local_position()
    assert lp.x_m == pytest.approx(10.0 - 2000.0, abs=0.01) and lp.y_m == pytest.approx(-5.0, abs=0.01)
    assert lp.z_m == pytest.approx(3.0)                                   # the field lies 3 m below the origin's altitude
    gp = v._global_position()
    lat, lon, _ = pymap3d.ned2geodetic(10.0, -5.0, 0.0, HOME[0], HOME[1], 0.0)
    assert (gp.lat_deg, gp.lon_deg) == pytest.approx((lat, lon), abs=1e-9) and gp.alt_amsl_m == HOME[2]
    # and the same point from the origin (PX4's convention: horizontal on the ellipsoid, z an AMSL difference):
    # LOCAL_POSITION_NED and GLOBAL_POSITION_INT agree
    n, e, _ = pymap3d.geodetic2ned(gp.lat_deg, gp.lon_deg, 0.0, o_lat, o_lon, 0.0)
    assert (n, e) == pytest.approx((lp.x_m, lp.y_m), abs=0.01) and HOME[2] + 3.0 - gp.alt_amsl_m == pytest.approx(lp.z_m, abs=0.01)
    # the origin on request (MAV_CMD_REQUEST_MESSAGE 49), and home with its local coordinates
    n_sent = len(sent)
    v.handle(cmd(512, 49))
    assert acks(sent)[-1].result == MavResult.ACCEPTED and isinstance(sent[-1], GpsGlobalOrigin) and len(sent) == n_sent + 2
    home = v._telemetry("home_position")
    assert isinstance(home, HomePosition) and home.x_m == pytest.approx(lp.x_m) and home.lat_deg == pytest.approx(lat, abs=1e-9)
    # an acceleration setpoint in the local axes moves the vehicle the same way in the world
    v.handle(cmd(400, 1))
    v.handle(cmd(22, *NAN7))
    run(v, clock, 5.0)
    sp = altitude_hold_setpoint(1, 1, (1.0, 0.0), lp.z_m - 2.5, 0)
    v.handle(rx(sp))
    v.handle(cmd(176, 1, 6))
    x0 = v._local_position().x_m
    run(v, clock, 3.0, setpoint=sp)
    assert v._local_position().x_m - x0 > 2.0 and abs(v._local_position().y_m + 5.0) < 1.5      # (the mean wind blows east -1 m/s)
    assert v._local_position().z_m == pytest.approx(lp.z_m - 2.5, abs=0.05)                    # z relative to the origin too


# ------------------------------------------------------------------ the command line
def test_cli_defaults_keep_the_air_start_and_the_new_flags_select_the_field():
    from mock_vehicle.cli import build_parser, config_from_args

    cfg, _ = config_from_args(build_parser().parse_args([]))
    assert (cfg.start_on_ground, cfg.origin, cfg.params) == (False, None, ())
    cfg, _ = config_from_args(build_parser().parse_args(["--start", "ground", "--origin=47.4,8.55,490.5", "--initial-pos-m=-3,4",
                                                         "--param", "COM_OBL_RC_ACT=4", "--param", "MIS_TAKEOFF_ALT=7.5"]))
    assert cfg.start_on_ground and cfg.origin == (47.4, 8.55, 490.5) and cfg.initial_pos_m == (-3.0, 4.0)
    v, clock, sent = make(**{k: getattr(cfg, k) for k in ("start_on_ground", "origin", "params", "initial_pos_m")})
    assert (v.params["COM_OBL_RC_ACT"], v.params["MIS_TAKEOFF_ALT"], v.landed) == (4.0, 7.5, True)
    for bad, match in ((["--param", "NOPE=1"], "unknown parameter"), (["--param", "COM_OBL_RC_ACT"], "NAME=VALUE"),
                       (["--param", "COM_OBL_RC_ACT=9"], "outside"), (["--origin=95,8,400"], "--origin")):
        with pytest.raises(ValueError, match=match):
            config_from_args(build_parser().parse_args(bad))


def test_in_lockstep_the_auto_modes_climb_on_the_wall_clock_and_offboard_steps_the_altitude_loop():
    v, clock, sent = make(start_on_ground=True, lockstep=True, dt_s=0.5)
    v.handle(cmd(400, 1))
    v.handle(cmd(22, *NAN7))
    run(v, clock, 10.0)                                                  # no steps: time_boot_ms stays 0
    assert v.time_boot_ms() == 0 and v.mode == PX4_HOLD and v.z_m == pytest.approx(-2.5, abs=0.01)
    assert not v._auto_vertical_pending()                                # settled: no more wake-ups for it
    sp = altitude_hold_setpoint(1, 1, (0.0, 0.0), -10.0, 0)
    v.handle(rx(sp))
    v.handle(cmd(176, 1, 6))
    assert v.mode == PX4_OFFBOARD
    for k in range(20):                                                  # 20 steps of 0.5 s, each stamped with the vehicle's time
        v.handle(rx(altitude_hold_setpoint(1, 1, (0.0, 0.0), -10.0, v.time_boot_ms())))
    assert v.time_boot_ms() == 10_000 and v.z_m == pytest.approx(-10.0, abs=0.05)
