"""`mfg-autopilot` as a real process against a real mock-vehicle process (issue 4)."""

import json
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
from _net import PYTHON, VENV_BIN, free_tcp_ports, free_udp_port, free_udp_ports, spawn, wait_until

from mavlink_bridge import LocalPositionNed, SetPositionTargetLocalNed, read_tlog
from mfg_autopilot.presets import preset_by_name
from mfg_swarm.scenarios import make_scenario
from mfg_swarm.sim import SimConfig, simulate

pytestmark = pytest.mark.e2e


def _free_tcp_port() -> int:
    return free_tcp_ports(1)[0]      # below the ephemeral range (tests/_net.py)


def _autopilot(url, *extra, n=1, instance=0):
    return [PYTHON, "-m", "mfg_autopilot.runtime.cli", "--instance", str(instance), "--connect", url, "--n", str(n),
            "--zenoh-listen", f"tcp/127.0.0.1:{_free_tcp_port()}", *extra]


def _records(path):
    return [json.loads(line) for line in path.read_text().splitlines()]


def test_no_vehicle_is_a_clear_timeout_error(tmp_path):
    port = free_udp_port()
    p = subprocess.run(_autopilot(f"udpin:127.0.0.1:{port}", "--vehicle-timeout-s", "1.5", "--log", str(tmp_path / "c.jsonl")),
                       capture_output=True, text=True, timeout=60)
    assert p.returncode == 1
    assert "HeartbeatTimeout" in p.stderr and "system 1" in p.stderr
    assert any(r.get("what") == "error" for r in _records(tmp_path / "c.jsonl"))


def test_arm_denied_is_a_clear_error(tmp_path):
    port = free_udp_port()
    mock = [PYTHON, "-m", "mock_vehicle.cli", "--onboard-url", f"udpout:127.0.0.1:{port}", "--gcs-url", "none", "--deny-arming"]
    with spawn(mock, log_dir=tmp_path, name="mock"):
        p = subprocess.run(_autopilot(f"udpin:127.0.0.1:{port}", "--vehicle-timeout-s", "20"), capture_output=True, text=True, timeout=90)
    assert p.returncode == 1
    assert "CommandDenied" in p.stderr and "COMPONENT_ARM_DISARM" in p.stderr and "DENIED" in p.stderr


def test_bad_configuration_is_refused_before_anything_starts():
    p = subprocess.run(_autopilot("udpin:127.0.0.1:1", "--mode", "hjb"), capture_output=True, text=True, timeout=60)
    assert p.returncode == 2 and "radio range" in p.stderr
    p = subprocess.run(_autopilot("udpin:127.0.0.1:1", instance=3, n=2), capture_output=True, text=True, timeout=60)
    assert p.returncode == 2 and "not a vehicle of a swarm of 2" in p.stderr


def test_same_controller_through_a_mavproxy_router_flies_the_same_lockstep_flight(tmp_path):
    """Only the connection string changes: mock -> MAVProxy -> controller, and back."""
    p_master, p_out = free_udp_ports(2)
    steps, seed = 15, 4
    start = [float(v) for v in make_scenario("paper", 1).initial_pos_m[0]]
    mavproxy = [str(VENV_BIN / "mavproxy.py"), f"--master=udpin:127.0.0.1:{p_master}", f"--out=udpout:127.0.0.1:{p_out}",
                "--daemon", "--no-state", "--default-modules=", "--nowait"]
    mock = [PYTHON, "-m", "mock_vehicle.cli", "--onboard-url", f"udpout:127.0.0.1:{p_master}", "--gcs-url", "none",
            "--initial-pos-m", f"{start[0]!r},{start[1]!r}", "--seed", str(seed), "--lockstep", "--tlog", str(tmp_path / "v.tlog"),
            "--acc-lag-s", "0"]     # the paper's plant, as the paper's preset flies in the simulator
    with spawn(mavproxy, log_dir=tmp_path, name="mavproxy", stop_timeout_s=3.0):
        with spawn(mock, log_dir=tmp_path, name="mock"):
            p = subprocess.run(_autopilot(f"udpin:127.0.0.1:{p_out}", "--lockstep", "--steps", str(steps), "--preset", "paper",
                                          "--log", str(tmp_path / "c.jsonl")), capture_output=True, text=True, timeout=120)
            assert p.returncode == 0, p.stderr[-2000:]
            time.sleep(0.5)
    pos = {r.msg.time_boot_ms: (r.msg.x_m, r.msg.y_m) for _, r in read_tlog(tmp_path / "v.tlog") if isinstance(r.msg, LocalPositionNed)}
    flown = np.array([pos[k * 1000] for k in range(steps + 1)])
    traj, _ = simulate(SimConfig(make_scenario("paper", 1), "mfg", preset_by_name("paper"), seed=seed, steps=steps), progress=False)
    assert np.max(np.abs(flown - traj.pos_m[:, 0])) < 1e-3
    sps = [r.msg for _, r in read_tlog(tmp_path / "v.tlog") if isinstance(r.msg, SetPositionTargetLocalNed)]
    assert sps and {m.target_system for m in sps} == {1}, "setpoints only ever target the controller's own vehicle"
    assert any(r.get("what") == "hold" for r in _records(tmp_path / "c.jsonl"))


def test_stale_telemetry_stops_setpoints_and_resumes_when_it_returns(tmp_path):
    """The link (a MAVProxy router) freezes for 3 s: the controller sees telemetry go stale and
    stops commanding; the vehicle's own offboard-loss failsafe puts it in HOLD; when the link
    comes back the controller says so, re-enters OFFBOARD and flies on."""
    p_master, p_out = free_udp_ports(2)
    mavproxy = [str(VENV_BIN / "mavproxy.py"), f"--master=udpin:127.0.0.1:{p_master}", f"--out=udpout:127.0.0.1:{p_out}",
                "--daemon", "--no-state", "--default-modules=", "--nowait"]
    mock = [PYTHON, "-m", "mock_vehicle.cli", "--onboard-url", f"udpout:127.0.0.1:{p_master}", "--gcs-url", "none",
            "--initial-pos-m", "150,100"]
    log = tmp_path / "c.jsonl"
    with spawn(mavproxy, log_dir=tmp_path, name="mavproxy", stop_timeout_s=3.0) as mp, spawn(mock, log_dir=tmp_path, name="mock") as mv:
        with spawn(_autopilot(f"udpin:127.0.0.1:{p_out}", "--steps", "19", "--preset", "paper", "--log", str(log),
                              "--vehicle-lost-s", "30"), log_dir=tmp_path, name="ap", stop_signal=signal.SIGINT) as ap:
            wait_until(lambda: log.exists() and sum('"type":"step"' in l for l in log.read_text().splitlines()) >= 3, 60, "3 control steps")
            mp.popen.send_signal(signal.SIGSTOP)              # the link falls silent both ways
            try:
                wait_until(lambda: '"telemetry_stale"' in log.read_text(), 10, "telemetry_stale event")
                time.sleep(2.5)                               # > COM_OF_LOSS_T: the vehicle's own failsafe acts
            finally:
                mp.popen.send_signal(signal.SIGCONT)
            wait_until(lambda: '"telemetry_back"' in log.read_text(), 15, "telemetry_back event")
            wait_until(lambda: ap.popen.poll() is not None, 60, "controller to finish")
            assert ap.popen.returncode == 0
        assert "failsafe" in mv.log_path.read_text().lower()
    recs = _records(log)
    whats = [r.get("what") for r in recs if r["type"] == "event"]
    assert whats.index("telemetry_stale") < whats.index("telemetry_back")
    # after the vehicle's failsafe put it in HOLD, the controller re-entered OFFBOARD and flew on
    assert whats.count("offboard") >= 2
    assert sum(r["type"] == "step" for r in recs) >= 10


def test_vehicle_restart_is_seen_and_the_handshake_is_redone(tmp_path):
    """The vehicle process dies and comes back on the same port: the controller sees the
    heartbeat vanish, stops commanding, waits, and redoes arm + OFFBOARD."""
    port = free_udp_port()
    mock = [PYTHON, "-m", "mock_vehicle.cli", "--onboard-url", f"udpout:127.0.0.1:{port}", "--gcs-url", "none", "--initial-pos-m", "150,100"]
    log = tmp_path / "c.jsonl"
    with spawn(_autopilot(f"udpin:127.0.0.1:{port}", "--steps", "14", "--preset", "paper", "--log", str(log), "--vehicle-lost-s", "2"),
               log_dir=tmp_path, name="ap", stop_signal=signal.SIGINT) as ap:
        with spawn(mock, log_dir=tmp_path, name="mock1") as first:
            wait_until(lambda: log.exists() and log.read_text().count('"type":"step"') >= 2, 60, "2 control steps")
            first.popen.kill()
        wait_until(lambda: '"vehicle_lost"' in log.read_text(), 10, "vehicle_lost event")
        with spawn(mock, log_dir=tmp_path, name="mock2"):
            wait_until(lambda: '"vehicle_back"' in log.read_text(), 20, "vehicle_back event")
            wait_until(lambda: ap.popen.poll() is not None, 60, "controller to finish")
    assert ap.popen.returncode == 0
    whats = [r.get("what") for r in _records(log) if r["type"] == "event"]
    i = whats.index("vehicle_lost")
    assert whats[i:].index("vehicle_back") < whats[i:].index("armed") < whats[i:].index("offboard")
    assert [r for r in _records(log) if r["type"] == "end"][0]["reason"] == "mission_time"


def test_one_controller_flies_one_mock_from_the_source_to_its_destination(tmp_path):
    """Default preset, lockstep, 70 simulated s: from the paper's source (150, 100) m into its
    slot (the destination site itself for a swarm of one), as the vehicle's own tlog shows."""
    port = free_udp_port()
    mock = [PYTHON, "-m", "mock_vehicle.cli", "--onboard-url", f"udpout:127.0.0.1:{port}", "--gcs-url", "none",
            "--initial-pos-m", "150,100", "--lockstep", "--dt-s", "0.5", "--tlog", str(tmp_path / "v.tlog")]
    with spawn(mock, log_dir=tmp_path, name="mock"):
        p = subprocess.run(_autopilot(f"udpin:127.0.0.1:{port}", "--lockstep", "--steps", "140", "--preset", "default",
                                      "--log", str(tmp_path / "c.jsonl")), capture_output=True, text=True, timeout=180)
        assert p.returncode == 0, p.stderr[-2000:]
    pos = [(r.msg.time_boot_ms, r.msg.x_m, r.msg.y_m) for _, r in read_tlog(tmp_path / "v.tlog") if isinstance(r.msg, LocalPositionNed)]
    t_end, x, y = max(pos)
    assert t_end == 140 * 500 and np.hypot(x, y) < 1.0, (t_end, x, y)
    end = [r for r in _records(tmp_path / "c.jsonl") if r["type"] == "end"][0]
    assert end["reason"] == "mission_time" and end["destination_m"] == [0.0, 0.0]
