"""The mock as a real-field stand-in (issue 19): ground start, takeoff, altitude hold, land and
auto-disarm, its own EKF origin. A fake clock, no sockets (tests/test_mock_unit.py's helpers)."""

from __future__ import annotations

import math

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
    MavLandedState,
    MavResult,
    ParamSet,
    acceleration_setpoint,
    altitude_hold_setpoint,
)
from mock_vehicle.vehicle import check_setpoint

HOME = (47.397742, 8.545594, 488.0)


def run(v, clock, seconds, dt=0.05, setpoint=None):
    for _ in range(int(round(seconds / dt))):
        if setpoint is not None:
            v.handle(rx(setpoint))
        clock.t += dt
        v.tick()


def landed_state(v) -> int:
    return v._telemetry("extended_sys_state").landed_state


def test_given_a_ground_start_then_the_vehicle_sits_on_the_ground_disarmed_and_the_wind_does_not_move_it():
    v, clock, sent = make(start_on_ground=True, initial_pos_m=(3.0, 4.0))
    run(v, clock, 10.0)
    assert not v.armed and v.landed and v.z_m == 0.0
    assert tuple(v.state) == (3.0, 4.0, 0.0, 0.0)
    assert landed_state(v) == MavLandedState.ON_GROUND


def test_takeoff_is_denied_while_disarmed():
    v, clock, sent = make(start_on_ground=True)
    v.handle(cmd(22, math.nan, 0, 0, math.nan, math.nan, math.nan, math.nan))
    assert acks(sent)[-1].result == MavResult.DENIED and v.landed


def test_given_armed_on_the_ground_when_takeoff_then_it_climbs_at_mpc_tko_speed_to_mis_takeoff_alt_and_holds():
    v, clock, sent = make(start_on_ground=True)
    v.handle(cmd(400, 1))
    v.handle(cmd(22, math.nan, 0, 0, math.nan, math.nan, math.nan, math.nan))
    assert acks(sent)[-1].result == MavResult.ACCEPTED and v.mode == PX4_TAKEOFF
    assert landed_state(v) == MavLandedState.TAKEOFF
    run(v, clock, 1.0)
    assert v.z_m == pytest.approx(-1.5, abs=0.2)                       # MPC_TKO_SPEED 1.5 m/s (0.1-s physics steps)
    run(v, clock, 2.0)
    assert v.mode == PX4_HOLD and v.z_m == pytest.approx(-2.5, abs=0.06)  # MIS_TAKEOFF_ALT 2.5 m, then AUTO.LOITER
    assert landed_state(v) == MavLandedState.IN_AIR


def test_takeoff_altitude_comes_from_the_command_or_the_parameter_mavsdk_sets():
    v, clock, sent = make(start_on_ground=True)
    v.handle(rx(ParamSet(1, 1, "MIS_TAKEOFF_ALT", 6.0)))
    v.handle(cmd(400, 1))
    v.handle(cmd(22, math.nan, 0, 0, math.nan, math.nan, math.nan, math.nan))
    run(v, clock, 6.0)
    assert v.z_m == pytest.approx(-6.0, abs=0.06)
    w, clock, sent = make(start_on_ground=True)
    w.handle(cmd(400, 1))
    w.handle(cmd(22, math.nan, 0, 0, math.nan, math.nan, math.nan, HOME[2] + 4.0))   # param 7: AMSL
    run(w, clock, 5.0)
    assert w.z_m == pytest.approx(-4.0, abs=0.06)


def test_altitude_hold_setpoint_3387_tracks_z_with_px4s_speed_limits_while_x_y_take_the_acceleration():
    v, clock, sent = make(start_on_ground=True)
    v.handle(cmd(400, 1))
    v.handle(cmd(22, math.nan, 0, 0, math.nan, math.nan, math.nan, math.nan))
    run(v, clock, 3.0)
    sp = altitude_hold_setpoint(1, 1, (0.5, 0.0), -20.0, 0)
    assert check_setpoint(sp, 1, 1) is None                            # PX4's filter accepts 3387
    v.handle(rx(sp))
    v.handle(cmd(176, 1, 6))
    assert v.mode == PX4_OFFBOARD
    z0 = v.z_m
    run(v, clock, 1.0, setpoint=sp)
    assert z0 - v.z_m == pytest.approx(3.0, abs=0.2)                   # climbs at MPC_Z_VEL_MAX_UP = 3 m/s
    run(v, clock, 15.0, setpoint=sp)
    assert v.z_m == pytest.approx(-20.0, abs=0.05) and v.state[2] > 3.0   # held at 20 m; accelerating north
    # acceleration-only (3135): the altitude stays where it is
    acc = acceleration_setpoint(1, 1, (0.0, 0.0, 0.0), 0)
    run(v, clock, 5.0, setpoint=acc)
    assert v.z_m == pytest.approx(-20.0, abs=0.05)


def test_offboard_from_the_ground_lifts_off_only_when_the_setpoint_asks_to_climb():
    v, clock, sent = make(start_on_ground=True)
    v.handle(cmd(400, 1))
    acc = acceleration_setpoint(1, 1, (1.0, 0.0, 0.0), 0)
    v.handle(rx(acc))
    v.handle(cmd(176, 1, 6))
    assert v.mode == PX4_OFFBOARD
    run(v, clock, 2.0, setpoint=acc)
    assert v.landed and v.z_m == 0.0 and v.state[0] == 0.0             # idle on the ground
    climb = altitude_hold_setpoint(1, 1, (0.0, 0.0), -5.0, 0)
    run(v, clock, 4.0, setpoint=climb)
    assert not v.landed and v.z_m == pytest.approx(-5.0, abs=0.1)


def test_land_descends_at_mpc_land_speed_touches_down_and_disarms_com_disarm_land_later():
    v, clock, sent = make(start_on_ground=True)
    v.handle(cmd(400, 1))
    v.handle(cmd(22, math.nan, 0, 0, math.nan, math.nan, math.nan, math.nan))
    run(v, clock, 3.0)
    v.handle(cmd(21))
    assert v.mode == PX4_LAND and landed_state(v) == MavLandedState.LANDING
    run(v, clock, 2.0)
    assert v.z_m == pytest.approx(-2.5 + 1.4, abs=0.1)                 # 0.7 m/s
    run(v, clock, 2.0)
    assert v.landed and v.armed                                         # touched down, not yet disarmed
    assert landed_state(v) == MavLandedState.ON_GROUND
    run(v, clock, 2.1)
    assert not v.armed                                                  # COM_DISARM_LAND = 2 s


def test_given_its_own_ekf_origin_the_vehicle_reports_local_positions_relative_to_it_and_consistent_wgs84():
    o_lat, o_lon, _ = pymap3d.ned2geodetic(2000.0, 0.0, 0.0, HOME[0], HOME[1], 0.0)
    v, clock, sent = make(start_on_ground=True, initial_pos_m=(10.0, -5.0), origin=(float(o_lat), float(o_lon), HOME[2]))
    run(v, clock, 0.5)
    origins = [m for m in sent if isinstance(m, GpsGlobalOrigin)]
    assert origins and origins[0].lat_deg == pytest.approx(o_lat, abs=1e-12)       # announced at boot
    lp = v._local_position()
    assert lp.x_m == pytest.approx(10.0 - 2000.0, abs=0.01) and lp.y_m == pytest.approx(-5.0, abs=0.01) and lp.z_m == 0.0
    gp = v._global_position()
    lat, lon, _ = pymap3d.ned2geodetic(10.0, -5.0, 0.0, HOME[0], HOME[1], 0.0)
    assert (gp.lat_deg, gp.lon_deg) == pytest.approx((lat, lon), abs=1e-9) and gp.alt_amsl_m == HOME[2]
    # the origin on request (MAV_CMD_REQUEST_MESSAGE 49), and home with its local coordinates
    n = len(sent)
    v.handle(cmd(512, 49))
    assert acks(sent)[-1].result == MavResult.ACCEPTED and isinstance(sent[-1], GpsGlobalOrigin) and len(sent) == n + 2
    home = v._telemetry("home_position")
    assert isinstance(home, HomePosition) and home.x_m == pytest.approx(lp.x_m) and home.lat_deg == pytest.approx(lat, abs=1e-9)
    # an acceleration setpoint in the local axes moves the vehicle the same way in the world
    v.handle(cmd(400, 1))
    v.handle(cmd(22, math.nan, 0, 0, math.nan, math.nan, math.nan, math.nan))
    run(v, clock, 3.0)
    sp = altitude_hold_setpoint(1, 1, (1.0, 0.0), -2.5, 0)
    v.handle(rx(sp))
    v.handle(cmd(176, 1, 6))
    x0 = v._local_position().x_m
    run(v, clock, 3.0, setpoint=sp)
    assert v._local_position().x_m - x0 > 2.0 and abs(v._local_position().y_m + 5.0) < 1.5      # (the mean wind blows east -1 m/s)


def test_without_an_origin_the_local_frame_is_the_world_frame_as_before():
    v, clock, sent = make(initial_pos_m=(150.0, 100.0))
    lp = v._local_position()
    assert (lp.x_m, lp.y_m, lp.z_m) == (150.0, 100.0, -10.0)
    assert v._message_by_id(49) == GpsGlobalOrigin(HOME[0], HOME[1], HOME[2], 0)
    assert not v.landed and landed_state(v) == MavLandedState.ON_GROUND       # the legacy air start, disarmed
