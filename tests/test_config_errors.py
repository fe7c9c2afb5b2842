"""Bad configuration gets a clear error that names the problem and the fix (issue 10)."""

import socket
import subprocess
import sys

import pytest
from _net import free_udp_port

pytestmark = pytest.mark.e2e


def _swarm(*args, timeout=60):
    return subprocess.run([sys.executable, "-m", "mfg_swarm.cli", *args], capture_output=True, text=True, timeout=timeout)


def _autopilot(*args, timeout=60):
    return subprocess.run([sys.executable, "-m", "mfg_autopilot.runtime.cli", "--instance", "0", "--n", "1", *args],
                          capture_output=True, text=True, timeout=timeout)


def test_impossible_swarm_sizes(tmp_path):
    p = _swarm("run", "--n", "300", "--out", str(tmp_path / "a"), "--no-plot")
    assert p.returncode == 2 and "N = 300 is impossible" in p.stderr and "1..253" in p.stderr
    p = _swarm("run", "--n", "0", "--out", str(tmp_path / "b"), "--no-plot")
    assert p.returncode == 2 and "n must be >= 1" in p.stderr


def test_port_in_use_is_named(tmp_path):
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
        p = _swarm("run", "--n", "2", "--mavlink-base-port", str(port), "--out", str(tmp_path / "c"), "--no-plot")
    assert p.returncode == 2 and f"port {port}" in p.stderr and "in use" in p.stderr and "another base port" in p.stderr


def test_unreachable_zenoh_router_is_named():
    p = _autopilot("--connect", f"udpin:127.0.0.1:{free_udp_port()}", "--zenoh-mode", "client",
                   "--zenoh-connect", "tcp/127.0.0.1:1", "--vehicle-timeout-s", "1")
    assert p.returncode == 1 and "cannot open zenoh session" in p.stderr and "tcp/127.0.0.1:1" in p.stderr


def test_bad_connection_string_lists_the_accepted_forms():
    p = _autopilot("--connect", "bogus:xyz")
    assert p.returncode == 1 and "unknown connection string 'bogus:xyz'" in p.stderr and "udpin:" in p.stderr


def test_missing_and_loose_key_files(tmp_path):
    p = _autopilot("--connect", f"udpin:127.0.0.1:{free_udp_port()}", "--mavlink-key", str(tmp_path / "none.key"))
    assert p.returncode == 1 and "does not exist" in p.stderr and "--generate" in p.stderr
    p = _swarm("run", "--n", "2", "--mavlink-key", str(tmp_path / "none.key"), "--out", str(tmp_path / "d"), "--no-plot")
    assert p.returncode == 2 and "does not exist" in p.stderr


def test_missing_mission_file_and_bad_preset(tmp_path):
    p = _autopilot("--connect", "udpin:127.0.0.1:1", "--mission", str(tmp_path / "nope.json"))
    assert p.returncode == 2 and "mission file" in p.stderr and "not found" in p.stderr
    p = _swarm("sim", "--preset", "nonesuch", "--out", str(tmp_path / "e"))
    assert p.returncode == 2 and "unknown preset 'nonesuch'" in p.stderr


def test_rt_priority_out_of_range_is_refused_before_anything_starts():
    p = _autopilot("--connect", "udpin:127.0.0.1:1", "--rt-priority", "0")
    assert p.returncode == 2 and "--rt-priority must be 1..99, got 0" in p.stderr


def test_rt_priority_is_applied_to_every_thread_or_refused_with_a_log_line():
    # given a process with a few threads (as a controller has: MAVLink receive, setpoint stream, Zenoh)
    code = r"""
import logging, os, sys, threading, json
logging.basicConfig(level=logging.INFO, stream=sys.stderr)
from mfg_autopilot.runtime.autopilot import set_realtime_priority
stop = threading.Event()
ts = [threading.Thread(target=stop.wait, daemon=True) for _ in range(3)]
for t in ts: t.start()
ok = set_realtime_priority(20)
tids = [int(t) for t in os.listdir("/proc/self/task")]
pol = {tid: os.sched_getscheduler(tid) for tid in tids}
stop.set()
print(json.dumps({"ok": ok, "fifo": [p == os.SCHED_FIFO for p in pol.values()]}))
"""
    # when it asks for SCHED_FIFO 20 (a child process: the test runner keeps its own scheduling)
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert p.returncode == 0, p.stderr
    import json
    r = json.loads(p.stdout.strip().splitlines()[-1])
    # then either every thread runs SCHED_FIFO, or none does and the refusal is logged (no CAP_SYS_NICE)
    if r["ok"]:
        assert len(r["fifo"]) >= 4 and all(r["fifo"])
    else:
        assert not any(r["fifo"]) and "refused" in p.stderr and "normal scheduling" in p.stderr


def test_swarm_rt_priority_out_of_range_is_refused_before_any_process_starts(tmp_path):
    p = _swarm("run", "--n", "2", "--rt-priority", "120", "--out", str(tmp_path / "r"), "--no-progress", "--no-plot")
    assert p.returncode != 0 and "--rt-priority must be 1..99, got 120" in p.stderr
    assert not (tmp_path / "r" / "controllers").exists() or not any((tmp_path / "r" / "controllers").iterdir())


def test_lockstep_mock_that_could_never_report_its_position_is_refused():
    p = subprocess.run([sys.executable, "-m", "mock_vehicle.cli", "--instance", "0", "--lockstep", "--lockstep-resend-hz", "0",
                        "--onboard-url", "udpout:127.0.0.1:9"], capture_output=True, text=True, timeout=60)
    assert p.returncode == 2 and "--lockstep-resend-hz must be > 0 in lockstep, got 0.0" in p.stderr


def test_negative_fpk_weight_log_interval_is_refused():
    from mfg_autopilot.runtime.cli import build_parser, config_from_args

    args = build_parser().parse_args(["--instance", "0", "--n", "1", "--mode", "mfg", "--log-fpk-weights-every", "-1"])
    with pytest.raises(ValueError, match="--log-fpk-weights-every must be >= 0, got -1"):
        config_from_args(args)
    args = build_parser().parse_args(["--instance", "0", "--n", "1", "--mode", "mfg", "--log-fpk-weights-every", "0"])
    assert config_from_args(args).log_fpk_weights_every == 0
