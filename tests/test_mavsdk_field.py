"""MAVSDK-Python drives a ground-start mock with its own EKF origin through the standard field flow
(issue 19): set_takeoff_altitude, arm, takeoff, set_acceleration_ned + start (at once: PX4's
offboard check is a timeout), position() in WGS84, land, auto-disarm. A real process over loopback."""

from __future__ import annotations

import json
import subprocess

import pymap3d
import pytest

from _net import PYTHON, running_mock_vehicle
from mavlink_bridge import GpsGlobalOrigin, VehicleLink

pytestmark = pytest.mark.e2e

HOME = (47.397742, 8.545594, 488.0)

# MAVSDK-Python 4.x in its own process (a hang cannot take pytest with it); every wait bounded.
CLIENT = r"""
import json, sys, time
from mavsdk import Mavsdk, Configuration, ComponentType
from mavsdk.plugins.action import Action
from mavsdk.plugins.offboard import Offboard, AccelerationNed
from mavsdk.plugins.telemetry import Telemetry

def out(**kw):
    print(json.dumps(kw), flush=True)

def until(pred, timeout_s, what):
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if pred():
            return True
        time.sleep(0.1)
    out(event="timeout", what=what); sys.exit(4)

m = Mavsdk(Configuration.create_with_component_type(ComponentType.COMPANION_COMPUTER))
m.add_any_connection(f"udpin://127.0.0.1:{int(sys.argv[1])}")
system = m.first_autopilot(10.0)
if system is None:
    out(event="error", what="no autopilot"); sys.exit(3)
action, offboard, telemetry = Action(system), Offboard(system), Telemetry(system)
time.sleep(0.5)
out(event="discovered", in_air=telemetry.in_air(), armed=telemetry.armed())
action.set_takeoff_altitude(5.0)
action.arm()
out(event="armed", armed=telemetry.armed())
action.takeoff()
until(lambda: telemetry.position().relative_altitude_m > 4.8, 15.0, "takeoff to 5 m")
p = telemetry.position()
out(event="airborne", in_air=telemetry.in_air(), rel_alt=p.relative_altitude_m)
offboard.set_acceleration_ned(AccelerationNed(1.0, 0.0, 0.0))
offboard.start()
out(event="offboard", mode=telemetry.flight_mode().name)
time.sleep(2.0)
p = telemetry.position()
out(event="position", lat=p.latitude_deg, lon=p.longitude_deg, abs_alt=p.absolute_altitude_m, t=time.monotonic())
action.land()
until(lambda: not telemetry.armed(), 20.0, "land and disarm")
out(event="landed", in_air=telemetry.in_air(), armed=telemetry.armed())
"""


def test_mavsdk_standard_field_flow_on_a_ground_start_mock_with_its_own_origin(tmp_path):
    o_lat, o_lon, _ = pymap3d.ned2geodetic(-1500.0, 800.0, 0.0, HOME[0], HOME[1], 0.0)   # origin 1.7 km from the world's home
    with running_mock_vehicle("--start", "ground", "--origin", f"{o_lat},{o_lon},{HOME[2]}", "--initial-pos-m=-1500,800",
                              "--wind-diffusion", "0", gcs=True) as mock:
        with VehicleLink.open(mock.gcs_url, target_system=1) as gcs:
            gcs.wait_heartbeat(timeout_s=10.0)
            origin = gcs.wait_origin(timeout_s=5.0)
            assert isinstance(origin, GpsGlobalOrigin) and origin.lat_deg == pytest.approx(o_lat, abs=1e-7)
            client = subprocess.Popen([PYTHON, "-c", CLIENT, str(mock.onboard_port)], stdout=subprocess.PIPE,
                                      stderr=subprocess.DEVNULL, text=True, start_new_session=True)
            try:
                out, _ = client.communicate(timeout=90.0)
            finally:
                if client.poll() is None:
                    client.kill()
                    client.wait(5)
            events = {e["event"]: e for e in map(json.loads, out.splitlines())}
            assert client.returncode == 0, out
            assert events["discovered"] == {"event": "discovered", "in_air": False, "armed": False}
            assert events["armed"]["armed"] and events["airborne"]["in_air"]
            assert events["offboard"]["mode"] == "OFFBOARD"
            assert events["landed"] == {"event": "landed", "in_air": False, "armed": False}
            # MAVSDK's lat/lon is where the vehicle is: its local position from its own origin, through WGS84
            pos = events["position"]
            lp = gcs.latest_local_position()
            assert lp is not None and abs(lp.x_m) < 50.0 and lp.z_m == pytest.approx(0.0, abs=0.05)   # back on the ground
            n, e, _ = pymap3d.geodetic2ned(pos["lat"], pos["lon"], 0.0, origin.lat_deg, origin.lon_deg, 0.0)
            assert abs(n) < 40.0 and abs(e) < 40.0                    # a few metres of flight from its own origin, not 1.7 km
            assert n > 1.0                                            # it accelerated north at 1 m/s^2 for 2 s
            assert pos["abs_alt"] == pytest.approx(HOME[2] + 5.0, abs=0.3)
