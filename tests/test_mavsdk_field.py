"""MAVSDK-Python drives a ground-start mock with its own EKF origin through the standard field flow
(issue 19): set_takeoff_altitude, arm, takeoff, set_acceleration_ned + start (at once: PX4's offboard
check is a timeout), position() in WGS84, land, auto-disarm. A real process over loopback; MAVSDK runs in
a child process of its own (a hang cannot take pytest with it) and every wait is bounded."""

from __future__ import annotations

import json
import subprocess
import threading

import numpy as np
import pymap3d
import pytest

from _net import PYTHON, running_mock_vehicle
from mavlink_bridge import GpsGlobalOrigin, TelemetryTimeout, VehicleLink

pytestmark = pytest.mark.e2e

HOME = (47.397742, 8.545594, 488.0)
TAKEOFF_ALT_M = 5.0

# MAVSDK-Python 4.x (SPEC 4): Mavsdk, add_any_connection, first_autopilot; plugins on the system.
# Each event line carries time.monotonic() (one clock for every process on this machine).
CLIENT = r"""
import json, sys, time
from mavsdk import Mavsdk, Configuration, ComponentType
from mavsdk.plugins.action import Action
from mavsdk.plugins.offboard import Offboard, AccelerationNed
from mavsdk.plugins.telemetry import Telemetry

def out(**kw):
    print(json.dumps(dict(kw, t=time.monotonic())), flush=True)

def until(pred, timeout_s, what):
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if pred():
            return True
        time.sleep(0.1)
    out(event="timeout", what=what); sys.exit(4)

def position(event):
    p = telemetry.position()
    out(event=event, lat=p.latitude_deg, lon=p.longitude_deg, abs_alt=p.absolute_altitude_m, rel_alt=p.relative_altitude_m)

m = Mavsdk(Configuration.create_with_component_type(ComponentType.COMPANION_COMPUTER))
m.add_any_connection(f"udpin://127.0.0.1:{int(sys.argv[1])}")
system = m.first_autopilot(10.0)
if system is None:
    out(event="error", what="no autopilot"); sys.exit(3)
action, offboard, telemetry = Action(system), Offboard(system), Telemetry(system)
time.sleep(0.5)
out(event="discovered", in_air=telemetry.in_air(), armed=telemetry.armed())
action.set_takeoff_altitude(float(sys.argv[2]))
action.arm()
out(event="armed", armed=telemetry.armed())
action.takeoff()
until(lambda: telemetry.position().relative_altitude_m > float(sys.argv[2]) - 0.2, 20.0, "takeoff")
out(event="airborne", in_air=telemetry.in_air(), mode=telemetry.flight_mode().name)
offboard.set_acceleration_ned(AccelerationNed(1.0, 0.0, 0.0))
offboard.start()
out(event="offboard", mode=telemetry.flight_mode().name)
for k in range(8):
    time.sleep(0.25)
    position("position")
action.land()
until(lambda: not telemetry.armed(), 30.0, "land and disarm")
time.sleep(0.5)
out(event="landed", in_air=telemetry.in_air(), armed=telemetry.armed())
position("landed_position")
"""


class _LocalTrack:
    """LOCAL_POSITION_NED as the GCS link receives it, with time.monotonic() (a thread; bounded waits)."""

    def __init__(self, link: VehicleLink) -> None:
        self.samples: list[tuple[float, float, float, float]] = []    # (t, x, y, z)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, args=(link,), daemon=True)
        self._thread.start()

    def _run(self, link: VehicleLink) -> None:
        last = None
        while not self._stop.is_set():
            try:
                p = link.wait_local_position(last, timeout_s=0.5)
            except TelemetryTimeout:
                continue
            last = p.time_boot_ms
            self.samples.append((p.received_monotonic_s, p.x_m, p.y_m, p.z_m))

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(2.0)

    def nearest_m(self, t: float, ned: tuple[float, float, float], window_s: float = 0.6) -> float:
        """The smallest distance from ``ned`` to the local positions received in [t - window_s, t]
        (MAVSDK's position() is the latest GLOBAL_POSITION_INT, 5 Hz: up to ~0.3 s old)."""
        pts = np.array([s[1:] for s in self.samples if t - window_s <= s[0] <= t + 0.05])
        assert len(pts), f"no local position near t = {t}"
        return float(np.min(np.linalg.norm(pts - np.asarray(ned), axis=1)))


def test_mavsdk_standard_field_flow_on_a_ground_start_mock_with_its_own_origin():
    o_lat, o_lon = (float(v) for v in pymap3d.ned2geodetic(-1500.0, 800.0, 0.0, HOME[0], HOME[1], 0.0)[:2])   # 1.7 km from home
    o_alt = HOME[2] + 2.0                                                               # and 2 m above the field
    with running_mock_vehicle("--start", "ground", f"--origin={o_lat!r},{o_lon!r},{o_alt!r}", "--initial-pos-m=-1490,805",
                              "--wind-diffusion", "0", gcs=True) as mock:
        with VehicleLink.open(mock.gcs_url, target_system=1) as gcs:
            gcs.wait_heartbeat(timeout_s=10.0)
            origin = gcs.wait_origin(timeout_s=5.0)
            assert isinstance(origin, GpsGlobalOrigin) and origin.lat_deg == pytest.approx(o_lat, abs=1e-7)
            track = _LocalTrack(gcs)
            client = subprocess.Popen([PYTHON, "-c", CLIENT, str(mock.onboard_port), str(TAKEOFF_ALT_M)], stdout=subprocess.PIPE,
                                      stderr=subprocess.DEVNULL, text=True, start_new_session=True)
            try:
                out, _ = client.communicate(timeout=120.0)
            finally:
                if client.poll() is None:
                    client.kill()
                    client.wait(5)
                track.stop()
        events = [json.loads(line) for line in out.splitlines()]
        by = {e["event"]: e for e in events}
        assert client.returncode == 0, out
        assert (by["discovered"]["in_air"], by["discovered"]["armed"]) == (False, False)
        assert by["armed"]["armed"] and by["airborne"]["in_air"] and by["airborne"]["mode"] == "HOLD"
        assert by["offboard"]["mode"] == "OFFBOARD"
        assert (by["landed"]["in_air"], by["landed"]["armed"]) == (False, False)    # landed and auto-disarmed

        def local_of(e) -> tuple[float, float, float]:
            """MAVSDK's WGS84 position in the vehicle's LOCAL_NED: horizontally on the ellipsoid from the
            origin, z an AMSL difference (PX4's convention)."""
            n, e_, _ = pymap3d.geodetic2ned(e["lat"], e["lon"], 0.0, origin.lat_deg, origin.lon_deg, 0.0)
            return float(n), float(e_), origin.alt_amsl_m - e["abs_alt"]

        flight = [e for e in events if e["event"] == "position"]
        assert len(flight) == 8
        for e in flight:                        # what MAVSDK reads is where the mock flies, within a metre
            assert track.nearest_m(e["t"], local_of(e)) < 1.0, e
        n0, e0, z0 = local_of(flight[0])
        n1, _, z1 = local_of(flight[-1])
        assert abs(n0 - 10.0) < 20.0 and abs(e0 - 5.0) < 20.0           # near its launch point, 10 m N, 5 m E of its origin
        assert n1 - n0 > 1.0                                            # it accelerated north at 1 m/s^2
        assert z0 == pytest.approx(2.0 - TAKEOFF_ALT_M, abs=0.3) and z1 == pytest.approx(z0, abs=0.1)   # 5 m above the field
        landed = local_of(by["landed_position"])
        assert track.nearest_m(by["landed_position"]["t"], landed, window_s=2.0) < 0.5
        assert landed[2] == pytest.approx(2.0, abs=0.05)               # on the field, 2 m below the origin
        assert mock.proc.alive()
