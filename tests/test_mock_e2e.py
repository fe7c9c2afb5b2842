"""mock-vehicle as a real process over loopback UDP (issue 3 "Must show"): real
third-party clients (MAVSDK-Python, MAVProxy), PX4 rules, bad input, lockstep
reproducibility, tlog on SIGINT/SIGTERM, parameters."""

from __future__ import annotations

import json
import math
import signal
import subprocess
import time

import numpy as np
import pytest

from _net import PYTHON, VENV_BIN, free_udp_ports, running_mock_vehicle, spawn, wait_until
from mavlink_bridge import (
    PX4_HOLD,
    PX4_OFFBOARD,
    AutopilotVersion,
    CommandDenied,
    CommandLong,
    GlobalPositionInt,
    Heartbeat,
    HomePosition,
    MavFrame,
    MavlinkPort,
    MavResult,
    PositionTargetTypeMask,
    SetPositionTargetLocalNed,
    StatusText,
    VehicleLink,
    acceleration_setpoint,
    read_tlog,
)
from mock_vehicle.plant import PlantParams, SwarmPlant

pytestmark = pytest.mark.e2e

# MAVSDK-Python 4.x (native binding, no mavsdk_server), run in its own process so that a
# hang cannot take pytest with it. PX4 (and the mock) need the setpoint stream for > 1 s
# before OFFBOARD, so the client waits 1.5 s between set_acceleration_ned and start().
MAVSDK_CLIENT = r"""
import json, sys, time
from mavsdk import Mavsdk, Configuration, ComponentType
from mavsdk.plugins.action import Action
from mavsdk.plugins.offboard import Offboard, AccelerationNed
from mavsdk.plugins.telemetry import Telemetry

def out(**kw):
    print(json.dumps(kw), flush=True)

port, acc_n, fly_s = int(sys.argv[1]), float(sys.argv[2]), float(sys.argv[3])
m = Mavsdk(Configuration.create_with_component_type(ComponentType.COMPANION_COMPUTER))
out(event="connect", result=str(m.add_any_connection(f"udpin://127.0.0.1:{port}")))
system = m.first_autopilot(10.0)
if system is None:
    out(event="error", what="no autopilot"); sys.exit(3)
action, offboard, telemetry = Action(system), Offboard(system), Telemetry(system)
def pos():
    pv = telemetry.position_velocity_ned()
    return [pv.position.north_m, pv.position.east_m, pv.velocity.north_m_s, pv.velocity.east_m_s]
time.sleep(0.5)
out(event="discovered", sysid=system.get_system_id(), pos=pos())
action.arm()
out(event="armed", armed=telemetry.armed())
offboard.set_acceleration_ned(AccelerationNed(acc_n, 0.0, 0.0))
time.sleep(1.5)
offboard.start()
out(event="offboard", mode=telemetry.flight_mode().name, pos=pos())
time.sleep(fly_s)
out(event="flown", mode=telemetry.flight_mode().name, pos=pos())
offboard.stop()
time.sleep(0.5)
out(event="stopped", mode=telemetry.flight_mode().name)
"""


def _ou_prediction(x1, v1, a, c0, v_o, tau):
    """Exact solution of eq. 1 without noise: dv = (a - c0 (v - v_o)) dt, dr = v dt."""
    v_inf = v_o + a / c0
    e = math.exp(-c0 * tau)
    v = v_inf + (v1 - v_inf) * e
    x = x1 + v_inf * tau + (v1 - v_inf) * (1 - e) / c0
    return x, v


def test_mavsdk_arms_flies_offboard_acceleration_and_stops_into_hold(tmp_path):
    """Given a noise-free mock (V_o = 0, v(0) = 0), MAVSDK arms, streams a = (1, 0) m/s^2,
    starts OFFBOARD; the position seen on the GCS link follows eq. 1 within 0.5 m / 0.2 m/s
    (the physics ticks every 0.1 s of wall time); stop() leaves the vehicle in HOLD."""
    with running_mock_vehicle(
        "--initial-pos-m", "150,100", "--initial-vel-m-s", "0,0", "--wind-diffusion", "0", "--tlog", str(tmp_path / "m.tlog"), gcs=True
    ) as mock:
        with VehicleLink.open(mock.gcs_url, target_system=1) as gcs:
            gcs.wait_heartbeat(timeout_s=10.0)
            client = subprocess.Popen(
                [PYTHON, "-c", MAVSDK_CLIENT, str(mock.onboard_port), "1.0", "3.0"],
                stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True, start_new_session=True,
            )  # fmt: skip
            try:
                hb = gcs.wait_for(Heartbeat, lambda h: h.is_offboard and h.armed, timeout_s=15.0)
                assert hb is not None, "MAVSDK never got the vehicle into OFFBOARD"
                time.sleep(0.5)
                s1 = gcs.wait_local_position(None, timeout_s=1.0)
                time.sleep(2.0)
                s2 = gcs.wait_local_position(s1.time_boot_ms + 1900, timeout_s=1.0)
                assert gcs.latest_heartbeat().is_offboard
                out, _ = client.communicate(timeout=20.0)
            finally:
                if client.poll() is None:
                    client.kill()
                    client.wait(5)
            assert client.returncode == 0, out
            events = {e["event"]: e for e in map(json.loads, out.splitlines())}
            assert events["discovered"]["sysid"] == 1 and events["armed"]["armed"]
            assert events["offboard"]["mode"] == "OFFBOARD" and events["flown"]["mode"] == "OFFBOARD"
            assert events["stopped"]["mode"] == "HOLD"
            assert events["flown"]["pos"][0] - events["offboard"]["pos"][0] > 2.0  # MAVSDK sees it move north
            assert gcs.wait_for(Heartbeat, lambda h: h.px4_mode == PX4_HOLD, timeout_s=2.0) is not None
        tau = (s2.time_boot_ms - s1.time_boot_ms) / 1000.0
        v_o = np.array([1.0, -1.0])
        x, v = _ou_prediction(np.array([s1.x_m, s1.y_m]), np.array([s1.vx_m_s, s1.vy_m_s]), np.array([1.0, 0.0]), 0.1, v_o, tau)
        np.testing.assert_allclose([s2.x_m, s2.y_m], x, atol=0.5)
        np.testing.assert_allclose([s2.vx_m_s, s2.vy_m_s], v, atol=0.2)
    # MAVSDK's setpoints came from sys 1 comp 195 (a companion), targeted at 1/1 with mask 3135
    sps = [r for _, r in read_tlog(tmp_path / "m.tlog") if isinstance(r.msg, SetPositionTargetLocalNed)]
    assert sps and {(r.msg.target_system, r.msg.type_mask) for r in sps} == {(1, 3135)}


def test_mavproxy_routes_between_mock_and_pymavlink_client():
    """Mock -> MAVProxy (headless, --master udpin) -> --out udpout -> VehicleLink, and back."""
    p_master, p_out = free_udp_ports(2)
    mavproxy = [
        str(VENV_BIN / "mavproxy.py"), f"--master=udpin:127.0.0.1:{p_master}", f"--out=udpout:127.0.0.1:{p_out}",
        "--daemon", "--no-state", "--default-modules=", "--nowait",
    ]  # fmt: skip
    with spawn(mavproxy, name="mavproxy", stop_timeout_s=3.0) as mp:
        with spawn([PYTHON, "-m", "mock_vehicle.cli", "--onboard-url", f"udpout:127.0.0.1:{p_master}", "--gcs-url", "none"], name="mock"):
            with VehicleLink.open(f"udpin:127.0.0.1:{p_out}", target_system=1) as link:
                try:
                    link.wait_heartbeat(timeout_s=20.0)
                except Exception:
                    print(mp.log_text())
                    raise
                assert link.arm(timeout_s=5.0).armed
                link.start_setpoint_stream(rate_hz=20, acc_ned_m_s2=(0.5, 0.0, 0.0))
                time.sleep(1.3)
                assert link.start_offboard(timeout_s=5.0).is_offboard
                p = link.wait_local_position(None, timeout_s=2.0)
                assert link.get_param("COM_OF_LOSS_T", timeout_s=3.0) == 1.0
                assert link.hold(timeout_s=5.0).px4_mode == PX4_HOLD
                assert p.z_m == -10.0


def test_offboard_loss_failsafe_goes_to_hold_after_com_of_loss_t():
    with running_mock_vehicle("--initial-pos-m", "0,0") as mock:
        with VehicleLink.open(mock.onboard_url, target_system=1) as link:
            link.wait_heartbeat(timeout_s=10.0)
            link.arm(timeout_s=3.0)
            link.start_setpoint_stream(rate_hz=20, acc_ned_m_s2=(0.0, 2.0, 0.0))
            time.sleep(1.2)
            link.start_offboard(timeout_s=3.0)
            time.sleep(1.0)
            link.stop_setpoint_stream()
            t_stop = time.monotonic()
            hb = link.wait_for(Heartbeat, lambda h: h.px4_mode == PX4_HOLD, timeout_s=3.0)
            assert hb is not None, "no failsafe"
            assert 0.9 <= hb.received_monotonic_s - t_stop <= 1.6  # COM_OF_LOSS_T = 1.0 s
            assert hb.armed
            sample_hold = link.wait_local_position(None, timeout_s=1.0)
            time.sleep(3.0)
            later = link.wait_local_position(sample_hold.time_boot_ms, timeout_s=1.0)
            # Hold brakes: the speed falls and the vehicle stays near where the hold began
            assert math.hypot(later.vx_m_s, later.vy_m_s) < 0.5 * math.hypot(sample_hold.vx_m_s, sample_hold.vy_m_s)
            assert math.hypot(later.x_m - sample_hold.x_m, later.y_m - sample_hold.y_m) < 5.0
        assert "failsafe to HOLD" in mock.log_text()


BAD_SETPOINTS = {
    "setpoint wrong target system": dict(target_system=5),
    "setpoint wrong target component": dict(target_component=7),
    "setpoint unsupported frame": dict(coordinate_frame=MavFrame.LOCAL_ENU),
    "setpoint FORCE_SET bit": dict(type_mask=3135 | PositionTargetTypeMask.FORCE_SET),
    "setpoint ignores everything": dict(type_mask=0x0FFF & ~PositionTargetTypeMask.FORCE_SET),
    "setpoint out of range": dict(afx_m_s2=1e6),
}
"""What PX4's MAVLink receiver drops (plus the mock's own range guard): none of it is an offboard heartbeat."""


def test_bad_input_is_ignored_logged_and_survived():
    """Wrong target, wrong frame, FORCE bit, all-ignored mask, out of range, garbage: each is
    rejected with one log line, none counts as a setpoint stream, the process lives on. A NaN in a
    used field is what PX4's position controller refuses, not its receiver: in OFFBOARD it keeps the
    vehicle in OFFBOARD ("stop and wait"), and NaN never reaches the state."""
    with running_mock_vehicle("--initial-pos-m", "10,20", gcs=True) as mock:
        with VehicleLink.open(mock.onboard_url, target_system=1) as link:
            link.wait_heartbeat(timeout_s=10.0)
            link.arm(timeout_s=3.0)
            raw = MavlinkPort.open(mock.gcs_url, 1, 190)  # a second sender on the GCS link
            try:
                wait_until(lambda: raw.recv(0.2), 5.0, "first packet on the GCS link")  # learn the peer
                t_end = time.monotonic() + 1.4
                rng = np.random.default_rng(1)
                while time.monotonic() < t_end:
                    for bad in BAD_SETPOINTS.values():
                        raw.send(SetPositionTargetLocalNed(**{**acceleration_setpoint(1, 1, (1.0, 0.0, 0.0), 0).__dict__, **bad}))
                    raw.send_raw(rng.integers(0, 256, 64, dtype=np.uint8).tobytes())
                    raw.send_raw(b"\xfd\x20\x00\x00\x01\x01\x01\x54")  # truncated MAVLink 2 header
                    time.sleep(0.05)
                # none of that was a setpoint stream
                with pytest.raises(CommandDenied, match="TEMPORARILY_REJECTED"):
                    link.start_offboard(timeout_s=2.0)
                # with a valid stream it flies, while NaN setpoints keep arriving on the side
                link.start_setpoint_stream(rate_hz=20, acc_ned_m_s2=(0.5, 0.5, 0.0))
                time.sleep(1.2)
                assert link.start_offboard(timeout_s=3.0).is_offboard
                for _ in range(20):
                    raw.send(SetPositionTargetLocalNed(**{**acceleration_setpoint(1, 1, (0.0, 0.0, 0.0), 0).__dict__, "afx_m_s2": math.nan}))
                    time.sleep(0.02)
                t_ask = time.monotonic()
                assert link.wait_heartbeat(timeout_s=2.0, newer_than_monotonic_s=t_ask).is_offboard  # still alive
                p = link.wait_local_position(None, timeout_s=1.0)
                assert all(math.isfinite(v) for v in (p.x_m, p.y_m, p.vx_m_s, p.vy_m_s))
                assert (p.x_m, p.y_m) != (10.0, 20.0)
            finally:
                raw.close()
        assert mock.proc.alive()
    log = mock.log_text()
    for kind in [*BAD_SETPOINTS, "bad packet", "setpoint non-finite field"]:
        assert f"rejected {kind}:" in log, kind
    # rate-limited: one line with the detail, then counted (summary at exit)
    assert log.count("WARNING rejected setpoint wrong target system:") == 1
    assert "rejected setpoint wrong target system: " in log.split("signal")[-1] and "in total" in log
    assert "Traceback" not in log


def _drive_lockstep(seed: int, n_steps: int, tmp_path, tag: str, *extra: str):
    """Fly a lockstep mock through ``n_steps`` fixed setpoints; returns the telemetry."""
    dt_ms = 500
    accs = [(1.5 * math.cos(0.4 * k), 1.5 * math.sin(0.4 * k), 0.0) for k in range(n_steps)]
    with running_mock_vehicle(
        "--lockstep", "--dt-s", "0.5", "--seed", str(seed), "--initial-pos-m", "150,100", "--tlog", str(tmp_path / f"{tag}.tlog"),
        *extra,
    ) as mock:
        with VehicleLink.open(mock.onboard_url, target_system=1) as link:
            link.wait_heartbeat(timeout_s=10.0)
            start = link.wait_local_position(None, timeout_s=2.0)
            assert start.time_boot_ms == 0  # simulated time has not started
            link.arm(timeout_s=3.0)
            link.start_setpoint_stream(rate_hz=20)
            time.sleep(1.2)  # the offboard gate runs on the wall clock
            link.start_offboard(timeout_s=3.0)
            link.stop_setpoint_stream()
            samples = [start]
            for k, acc in enumerate(accs):
                samples.append(link.step_lockstep(acc, k * dt_ms, timeout_s=5.0))
                assert samples[-1].time_boot_ms == (k + 1) * dt_ms
                if k == 3:  # a stale setpoint: no step, just the latest telemetry again
                    link.send_acc_setpoint((2.0, 2.0, 0.0), time_boot_ms=0)
                    time.sleep(0.2)
                    assert link.latest_local_position() == samples[-1]
            time.sleep(1.5)  # frozen world: no failsafe while waiting for the controller
            assert link.latest_heartbeat().px4_mode == PX4_OFFBOARD
            assert link.latest_local_position() == samples[-1]
    return samples, accs


def _plant_states(accs, params: PlantParams) -> np.ndarray:
    """The in-process plant (seed 7, vehicle 0, at 150, 100) flown through the setpoints as the wire carries them
    (float32), as float32 telemetry reports it: (len(accs) + 1, 4)."""
    plant = SwarmPlant(np.array([[150.0, 100.0]]), params, seed=7, vehicle_ids=np.array([0]))
    expected = [plant.states[0].copy()]
    for acc in accs:
        plant.step(np.array([[np.float32(acc[0]), np.float32(acc[1])]], dtype=np.float64), 0.5)
        expected.append(plant.states[0].copy())
    return np.array(expected).astype(np.float32).astype(np.float64)


def _telemetry_states(samples) -> np.ndarray:
    return np.array([[s.x_m, s.y_m, s.vx_m_s, s.vy_m_s] for s in samples])


def test_lockstep_is_bit_for_bit_reproducible_and_matches_the_plant(tmp_path):
    # (the mock's default airframe flies PX4's lag: the next test; here the paper's plant, --acc-lag-s 0)
    a, accs = _drive_lockstep(7, 12, tmp_path, "a", "--acc-lag-s", "0")
    b, _ = _drive_lockstep(7, 12, tmp_path, "b", "--acc-lag-s", "0")
    assert a == b  # identical telemetry (receive times are not part of equality)
    # ... and equal to the in-process plant with the same seed and vehicle id (float32 wire)
    np.testing.assert_array_equal(_telemetry_states(a), _plant_states(accs, PlantParams()))
    c, _ = _drive_lockstep(8, 3, tmp_path, "c", "--acc-lag-s", "0")
    assert c[1:] != a[1:4]  # another seed, another wind


def test_lockstep_with_an_acceleration_lag_matches_the_plant_with_it(tmp_path):
    # the mock process flies its default lag (PX4's, SIM_ACC_TAU) as the simulator's plant does (PlantParams.acc_lag_s),
    # bit for bit
    a, accs = _drive_lockstep(7, 12, tmp_path, "lag")
    lagged = _plant_states(accs, PlantParams(acc_lag_s=0.154))
    np.testing.assert_array_equal(_telemetry_states(a), lagged)
    assert np.abs(_plant_states(accs, PlantParams())[-1, 2:] - lagged[-1, 2:]).max() > 0.05   # the lag is flown, not ignored


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_signal_leaves_a_complete_readable_tlog(tmp_path, signum):
    tlog = tmp_path / "v.tlog"
    with running_mock_vehicle("--tlog", str(tlog), stop_signal=signum) as mock:
        with VehicleLink.open(mock.onboard_url, target_system=1) as link:
            link.wait_heartbeat(timeout_s=10.0)
            link.arm(timeout_s=3.0)
            link.wait_local_position(None, timeout_s=1.0)
        rc = mock.proc.stop(signum, timeout_s=5.0)
    assert rc == 0
    records = read_tlog(tlog)
    n_logged = int(mock.log_text().split("records)")[0].rsplit("(", 1)[1].split()[0])
    assert len(records) == n_logged  # every record whole and readable by pymavlink
    names = {type(r.msg).__name__ for _, r in records}
    assert {"Heartbeat", "LocalPositionNed", "CommandLong", "CommandAck"} <= names
    assert all(t2 >= t1 for (t1, _), (t2, _) in zip(records, records[1:]))


def test_sigkill_loses_at_most_about_a_second_of_tlog(tmp_path):
    tlog = tmp_path / "k.tlog"
    with running_mock_vehicle("--tlog", str(tlog)) as mock:
        time.sleep(2.5)
        t_kill = time.time()
        mock.proc.kill()
    records = read_tlog(tlog)
    assert records and t_kill - records[-1][0] < 1.5


def test_params_commands_and_map_telemetry():
    with running_mock_vehicle("--initial-pos-m", "100,50", "--home-lat", "47.0", "--home-lon", "8.0", "--altitude-m", "20") as mock:
        with VehicleLink.open(mock.onboard_url, target_system=1) as link:
            link.wait_heartbeat(timeout_s=10.0)
            params = link.list_params(timeout_s=3.0)
            assert params["COM_OF_LOSS_T"] == 1.0 and params["MPC_ACC_HOR_MAX"] == 2.0 and len(params) >= 8
            assert link.set_param("COM_OF_LOSS_T", 2.5, timeout_s=2.0) == 2.5
            assert link.get_param("COM_OF_LOSS_T", timeout_s=2.0) == 2.5
            assert link.set_param("COM_OF_LOSS_T", -3.0, timeout_s=2.0) == 2.5  # out of bounds: kept
            assert link.set_param("SIM_ARM_DENY", 1.0, timeout_s=2.0) == 1.0
            with pytest.raises(CommandDenied, match="DENIED"):
                link.arm(timeout_s=2.0)
            assert link.wait_for(StatusText, lambda s: "Preflight" in s.text, timeout_s=1.0) is not None
            # REQUEST_MESSAGE and SET_MESSAGE_INTERVAL; UNSUPPORTED for the rest
            assert link.request_message(148, timeout_s=2.0).result == MavResult.ACCEPTED
            assert link.wait_for(AutopilotVersion, lambda m: m.capabilities & 8192, timeout_s=1.0) is not None
            assert link.set_message_interval(32, 0.1, timeout_s=2.0).result == MavResult.ACCEPTED
            with pytest.raises(CommandDenied, match="UNSUPPORTED"):
                link.command_long(31000, (), timeout_s=2.0)
            # map telemetry: flat-earth from home
            g = link.wait_for(GlobalPositionInt, lambda m: True, timeout_s=2.0)
            h = link.wait_for(HomePosition, lambda m: True, timeout_s=3.0)
            assert h.lat_deg == pytest.approx(47.0) and h.lon_deg == pytest.approx(8.0)
            assert g.lat_deg == pytest.approx(47.0 + math.degrees(100 / 6378137.0), abs=2e-7)
            assert g.lon_deg == pytest.approx(8.0 + math.degrees(50 / (6378137.0 * math.cos(math.radians(47.0)))), abs=2e-7)
            assert g.relative_alt_m == pytest.approx(20.0)
        assert mock.proc.alive()


def test_commands_for_other_systems_get_no_answer():
    with running_mock_vehicle() as mock:
        with VehicleLink.open(mock.onboard_url, target_system=1) as link:
            link.wait_heartbeat(timeout_s=10.0)
            link.port.send(CommandLong(9, 1, 400, (1.0, 0, 0, 0, 0, 0, 0)))
            time.sleep(0.5)
            assert not link.latest_heartbeat().armed
        assert "rejected command for another system:" in mock.log_text()
