"""A controller killed mid-flight (kill -9): its vehicle's own failsafe holds it, a restarted
controller resumes from its checkpoint without a new swarm exchange, and the other vehicle
flies on undisturbed (issue 10)."""

import json
import signal
import time

import pytest
from _net import PYTHON, free_tcp_ports, free_udp_ports, spawn, wait_until

from mavlink_bridge import SetPositionTargetLocalNed, StatusText, read_tlog

pytestmark = pytest.mark.e2e

COM_OF_LOSS_T_S = 1.0
TELEMETRY_PERIOD_S = 1.0 / 30


def _tcp_ports(n):
    return free_tcp_ports(n)      # below the ephemeral range (tests/_net.py)


def _recs(path):
    out = []
    for line in path.read_text().splitlines():
        try:
            out.append(json.loads(line))
        except json.JSONDecodeError:
            pass           # the line a killed process was writing
    return out


def test_controller_crash_hold_then_resume_without_new_exchange(tmp_path):
    mav = free_udp_ports(2)
    zp = _tcp_ports(2)
    steps = 22                    # paper preset: dt = 1 s of real time per step

    def mock(i):
        return [PYTHON, "-m", "mock_vehicle.cli", "--instance", str(i), "--onboard-url", f"udpout:127.0.0.1:{mav[i]}",
                "--gcs-url", "none", "--initial-pos-m", f"150,{100 + 3 * i}", "--tlog", str(tmp_path / f"v{i}.tlog")]

    def ctrl(i, log):
        argv = [PYTHON, "-m", "mfg_autopilot.runtime.cli", "--instance", str(i), "--n", "2", "--connect", f"udpin:127.0.0.1:{mav[i]}",
                "--mode", "mfg", "--preset", "paper", "--steps", str(steps), "--log", str(log), "--state-dir", str(tmp_path / f"state{i}"),
                "--zenoh-listen", f"tcp/127.0.0.1:{zp[i]}", "--swarm", "crash", "--hold-on-arrival", "off"]
        return argv + (["--zenoh-connect", f"tcp/127.0.0.1:{zp[0]}"] if i else [])

    log0, log0b, log1 = tmp_path / "c0.jsonl", tmp_path / "c0b.jsonl", tmp_path / "c1.jsonl"
    with spawn(mock(0), log_dir=tmp_path, name="m0"), spawn(mock(1), log_dir=tmp_path, name="m1"):
        with spawn(ctrl(1, log1), log_dir=tmp_path, name="c1", stop_signal=signal.SIGINT) as c1:
            with spawn(ctrl(0, log0), log_dir=tmp_path, name="c0") as c0:
                wait_until(lambda: log0.exists() and log0.read_text().count('"type":"step"') >= 5, 60, "5 steps of controller 0")
                c0.popen.send_signal(signal.SIGKILL)
                c0.popen.wait(5)
                killed_at = time.time()
            time.sleep(3.0)                                   # the vehicle is on its own meanwhile
            with spawn(ctrl(0, log0b), log_dir=tmp_path, name="c0b", stop_signal=signal.SIGINT) as c0b:
                wait_until(lambda: c0b.popen.poll() is not None and c1.popen.poll() is not None, 120, "both controllers to finish")
                assert c0b.popen.returncode == 0, c0b.log_path.read_text()[-2000:]
                assert c1.popen.returncode == 0, c1.log_path.read_text()[-2000:]
        time.sleep(0.5)

    # 1. the vehicle held by itself within COM_OF_LOSS_T + one telemetry period of the last setpoint
    pk = [(t, r.msg) for t, r in read_tlog(tmp_path / "v0.tlog")]
    last_sp = max(t for t, m in pk if isinstance(m, SetPositionTargetLocalNed) and t < killed_at)
    failsafe = min(t for t, m in pk if isinstance(m, StatusText) and "failsafe" in m.text.lower() and t > last_sp)
    assert failsafe - last_sp <= COM_OF_LOSS_T_S + TELEMETRY_PERIOD_S + 0.05, failsafe - last_sp
    # 2. the restarted controller resumed: no new exchange, back in OFFBOARD, mission completed
    r0b = _recs(log0b)
    whats = [r.get("what") for r in r0b if r["type"] == "event"]
    assert "resumed" in whats and "t0_exchange" not in whats and "offboard" in whats
    end = [r for r in r0b if r["type"] == "end"][0]
    assert end["reason"] == "mission_time" and end["states_received_t0"] == 1
    steps0 = [r["step"] for r in r0b if r["type"] == "step"]
    assert steps0 and steps0[-1] == steps - 1 and steps0[0] > 5, "resumed on the mission clock, not from step 0"
    # 3. the other vehicle was not affected: every step, no error, no outage
    r1 = _recs(log1)
    assert [r["step"] for r in r1 if r["type"] == "step"] == list(range(steps))
    assert not [r for r in r1 if r.get("what") in ("error", "telemetry_stale", "vehicle_lost", "left_offboard")]
