"""The swarm frame: geodetic <-> NED through pymap3d, each vehicle's own EKF origin (SPEC 4b)."""

from __future__ import annotations

import numpy as np
import pytest
from pymap3d.vincenty import vdist, vreckon

from mfg_autopilot.mission.frames import GeodeticPoint, SwarmFrame

DATUM = GeodeticPoint(47.397742, 8.545594, 488.0)
FRAME = SwarmFrame(DATUM)


def test_given_points_km_away_when_converted_to_ned_and_back_then_they_round_trip_to_a_millimetre():
    rng = np.random.default_rng(7)
    ned = rng.uniform(-3000, 3000, size=(200, 3)) * np.array([1, 1, 0.01])
    lat, lon, alt = FRAME.ned_to_geodetic(ned)
    back = FRAME.geodetic_to_ned(lat, lon, alt)
    assert np.max(np.abs(back - ned)) < 1e-3


def test_given_a_point_one_km_north_by_the_geodesic_then_the_frame_puts_it_1000_m_north():
    lat, lon = vreckon(DATUM.lat_deg, DATUM.lon_deg, 1000.0, 0.0)
    ned = FRAME.geodetic_to_ned(lat, lon, DATUM.alt_amsl_m)
    assert ned[0] == pytest.approx(1000.0, abs=0.001) and abs(ned[1]) < 1e-6
    assert ned[2] == 0.0                                                  # same altitude: down is an altitude difference (PX4)
    assert FRAME.geodetic_to_ned(lat, lon, DATUM.alt_amsl_m + 20.0)[2] == pytest.approx(-20.0)


def test_given_two_vehicles_with_origins_2_km_apart_when_each_reports_local_positions_then_the_swarm_frame_agrees():
    # vehicle a's origin at the datum, vehicle b's 2 km north-east; both stand at the same geodetic point
    lat_b, lon_b = vreckon(DATUM.lat_deg, DATUM.lon_deg, 2000.0, 45.0)
    a = FRAME.vehicle(DATUM)
    b = FRAME.vehicle(GeodeticPoint(float(lat_b), float(lon_b), DATUM.alt_amsl_m))
    target = np.array([1414.0, 1414.0, -20.0])                          # swarm frame: 20 m up, near b
    local_a, local_b = a.swarm_to_local(target), b.swarm_to_local(target)
    assert np.linalg.norm(local_a[:2] - local_b[:2]) > 1900                # the local numbers differ by the origins' offset
    # (the horizontal map is taken on the ellipsoid's surface, the altitude apart: a round trip is exact to 0.2 mm)
    assert np.max(np.abs(a.local_to_swarm(local_a) - target)) < 2e-4
    assert np.max(np.abs(b.local_to_swarm(local_b) - target)) < 2e-4
    # b's origin offset d_b is where the geodesic says
    assert np.hypot(*b.origin_ned_m[:2]) == pytest.approx(2000.0, abs=0.05)


def test_velocities_turn_by_the_tangent_planes_angle_and_keep_their_length():
    lat_b, lon_b = vreckon(DATUM.lat_deg, DATUM.lon_deg, 2000.0, 90.0)
    b = FRAME.vehicle(GeodeticPoint(float(lat_b), float(lon_b), DATUM.alt_amsl_m))
    assert np.allclose(b.rotation @ b.rotation.T, np.eye(3), atol=1e-8)
    v = np.array([8.0, 0.0, 0.0])
    vs = b.vector_to_swarm(v)
    assert np.linalg.norm(vs) == pytest.approx(8.0, abs=1e-6)
    assert 0 < np.linalg.norm(vs - v) < 0.01                               # ~3e-4 rad at 2 km: 2.5 mm/s at 8 m/s
    state = b.state_local_to_swarm(np.array([10.0, -5.0, 8.0, 0.0]), down_m=-20.0)
    assert state[0:2] == pytest.approx(b.local_to_swarm([10.0, -5.0, -20.0])[0:2], abs=1e-9)
    assert np.allclose(b.acc_swarm_to_local(b.vector_to_swarm(np.array([1.0, 2.0, 0.0]))[0:2]), [1.0, 2.0], atol=1e-6)


def test_px4s_azimuthal_equidistant_local_frame_is_within_5_mm_of_the_tangent_plane_over_2_km():
    """PX4's MapProjection is an azimuthal-equidistant projection: (north, east) = s (cos az, sin az) with
    s the distance along the surface. The tangent plane (pymap3d) differs by less than 5 mm within 2 km."""
    worst = 0.0
    for az in range(0, 360, 15):
        lat, lon = vreckon(DATUM.lat_deg, DATUM.lon_deg, 2000.0, float(az))
        s, a = vdist(DATUM.lat_deg, DATUM.lon_deg, lat, lon)
        ae = np.array([s * np.cos(np.radians(a)), s * np.sin(np.radians(a))])
        n, e, _ = FRAME.geodetic_to_ned(lat, lon, DATUM.alt_amsl_m)
        worst = max(worst, float(np.hypot(n - ae[0], e - ae[1])))
    assert worst < 0.005


@pytest.mark.parametrize("bad", [dict(lat_deg=91.0, lon_deg=0.0, alt_amsl_m=0.0), dict(lat_deg=0.0, lon_deg=-181.0, alt_amsl_m=0.0),
                                 dict(lat_deg=float("nan"), lon_deg=0.0, alt_amsl_m=0.0)])
def test_bad_coordinates_are_refused(bad):
    with pytest.raises(ValueError, match="latitude|longitude"):
        GeodeticPoint(**bad)
