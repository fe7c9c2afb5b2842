"""MAVLink 2 signing with real processes over loopback (issue 10 "Security"): a mock
vehicle started with ``--signing-key`` flies for the controller that holds the key, and
intruder processes on the same UDP network -- a VehicleLink without the key, one with a
wrong key, a plain pymavlink client, and a replay of the controller's own signed packets --
cannot arm it, change its mode, steer it or change its parameters. The vehicle process
keeps running and logs each kind of rejection once."""

from __future__ import annotations

import json
import math
import os
import socket
import subprocess
import time

import pytest

from _net import PYTHON, REPO, running_mock_vehicle, wait_until
from mavlink_bridge import (
    PX4_HOLD,
    CommandLong,
    Heartbeat,
    HeartbeatTimeout,
    MavCmd,
    MavlinkPort,
    VehicleLink,
    load_signing_key,
    read_tlog,
    write_signing_key,
)

pytestmark = pytest.mark.e2e

LEGIT_COMPONENT = 191  # the controller's (companion computer's) component id; intruders spoof it

# An intruder built on mavlink_bridge: no key (argv[3] == "-") or a wrong key. It spoofs
# the controller's ids and tries everything: arm, disarm, OFFBOARD/HOLD/LAND by
# COMMAND_LONG, COMMAND_INT and SET_MODE, PARAM_SET, and an east-bound setpoint stream.
BRIDGE_INTRUDER = r"""
import json, sys, time
from mavlink_bridge import (VehicleLink, BridgeError, CommandInt, SetMode, ParamSet, MavCmd,
                            MavParamType, PX4_OFFBOARD, PX4_HOLD, PX4_LAND, SetPositionTargetLocalNed)
port, seconds, key_hex = int(sys.argv[1]), float(sys.argv[2]), sys.argv[3]
key = None if key_hex == "-" else bytes.fromhex(key_hex)
out = {}
with VehicleLink.open(f"udpout:127.0.0.1:{port}", target_system=1, source_component=191,
                      signing_key=key, heartbeat_rate_hz=10) as link:
    def attempt(name, fn):
        try:
            fn(); out[name] = "accepted"
        except BridgeError as exc:
            out[name] = type(exc).__name__
    attempt("arm", lambda: link.arm(timeout_s=0.6))
    attempt("disarm", lambda: link.disarm(timeout_s=0.6, force=True))
    attempt("hold", lambda: link.hold(timeout_s=0.6))
    attempt("land", lambda: link.land(timeout_s=0.6))
    attempt("set_param", lambda: link.set_param("MPC_ACC_HOR_MAX", 0.01, timeout_s=0.6))
    t_end = time.monotonic() + seconds
    n = 0
    while time.monotonic() < t_end:
        link.send_acc_setpoint((0.0, 2.0, 0.0))
        link.port.send(SetPositionTargetLocalNed(0, 1, 1, 1, 0x0DC7, 0, 0, 0, 0.0, 5.0, 0, 0, 0, 0, 0, 0))  # velocity east
        link.port.send(CommandInt(1, 1, MavCmd.COMPONENT_ARM_DISARM, 0, (0.0, 21196.0, 0.0, 0.0)))
        link.port.send(SetMode(1, 1, PX4_LAND.custom_mode))
        link.port.send(ParamSet(1, 1, "SIM_ARM_DENY", 1.0, MavParamType.REAL32))
        n += 5
        time.sleep(0.02)
    out["streamed"] = n
print(json.dumps(out), flush=True)
"""

# The attacker's everyday tool: plain pymavlink (run as its own process, like the MAVSDK
# client in test_mock_e2e; the project's code itself imports pymavlink only in mavlink_bridge).
PYMAVLINK_INTRUDER = r"""
import json, sys, time
from pymavlink import mavutil
port, seconds = int(sys.argv[1]), float(sys.argv[2])
m = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=1, source_component=191, dialect="common")
mav = m.mav
n = 0
t_end = time.monotonic() + seconds
while time.monotonic() < t_end:
    mav.heartbeat_send(18, 8, 0, 0, 4)
    mav.command_long_send(1, 1, 400, 0, 1, 21196, 0, 0, 0, 0, 0)                    # arm (forced)
    mav.command_long_send(1, 1, 400, 0, 0, 21196, 0, 0, 0, 0, 0)                    # disarm (forced)
    mav.command_long_send(1, 1, 176, 0, 1 | 128, 6, 0, 0, 0, 0, 0)                  # OFFBOARD
    mav.command_long_send(1, 1, 176, 0, 1 | 128, 4, 6, 0, 0, 0, 0)                  # LAND
    mav.set_mode_send(1, 1, 4 << 16 | 3 << 24)                                      # HOLD
    mav.set_position_target_local_ned_send(0, 1, 1, 1, 3135, 0, 0, 0, 0, 0, 0, 0, -2.0, 0, 0, 0)
    mav.param_set_send(1, 1, b"COM_OF_LOSS_T", 0.0, 9)
    n += 8
    time.sleep(0.02)
print(json.dumps({"sent": n, "version": mavutil.mavlink.WIRE_PROTOCOL_VERSION}), flush=True)
"""


def _run_intruders(mock_port: int, seconds: float, wrong_key: bytes) -> list[subprocess.Popen]:
    env = dict(os.environ, MAVLINK20="1", PYTHONPATH=str(REPO))
    argvs = [
        [PYTHON, "-c", BRIDGE_INTRUDER, str(mock_port), str(seconds), "-"],
        [PYTHON, "-c", BRIDGE_INTRUDER, str(mock_port), str(seconds), wrong_key.hex()],
        [PYTHON, "-c", PYMAVLINK_INTRUDER, str(mock_port), str(seconds)],
    ]
    return [
        subprocess.Popen(a, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=REPO, env=env, start_new_session=True)
        for a in argvs
    ]


def _finish(procs: list[subprocess.Popen]) -> list[dict]:
    results = []
    try:
        for p in procs:
            out, err = p.communicate(timeout=30)
            assert p.returncode == 0, err[-2000:]
            results.append(json.loads(out.strip().splitlines()[-1]))
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.wait(5)
    return results


def _watch(link: VehicleLink, procs: list[subprocess.Popen], check) -> int:
    """Call ``check(heartbeat, local_position)`` every 20 ms while the intruders run."""
    n = 0
    deadline = time.monotonic() + 30
    while any(p.poll() is None for p in procs) and time.monotonic() < deadline:
        check(link.latest_heartbeat(), link.latest_local_position())
        n += 1
        time.sleep(0.02)
    return n


def test_intruders_cannot_arm_change_mode_steer_or_set_params_of_a_signing_vehicle(tmp_path):
    key_path = tmp_path / "swarm.key"
    write_signing_key(key_path)
    key = load_signing_key(key_path)
    wrong_key = bytes(b ^ 0x5A for b in key)
    mock_tlog, ctl_tlog = tmp_path / "mock.tlog", tmp_path / "ctl.tlog"
    # noise-free and windless: a vehicle nobody steers east keeps vy == 0 exactly
    with running_mock_vehicle(
        "--signing-key", str(key_path), "--initial-vel-m-s", "0,0", "--wind-diffusion", "0", "--mean-wind", "0,0",
        "--tlog", str(mock_tlog), log_dir=tmp_path,
    ) as mock:  # fmt: skip
        with VehicleLink.open(mock.onboard_url, target_system=1, signing_key=key, tlog_path=str(ctl_tlog)) as link:
            link.wait_heartbeat(timeout_s=10.0)
            assert link.rejects.counts == {}  # everything the vehicle sends is validly signed
            mock_port = wait_until(lambda: link.port.transport.peer, 5.0, "the vehicle's address")[1]

            # --- phase A: on the ground, disarmed, HOLD
            t_a0 = time.time()
            procs = _run_intruders(mock_port, 2.0, wrong_key)

            def grounded(hb: Heartbeat, lp) -> None:
                assert not hb.armed and hb.px4_mode == PX4_HOLD, hb

            assert _watch(link, procs, grounded) > 10
            phase_a = _finish(procs)
            t_a1 = time.time()
            for r in phase_a[:2]:
                assert r["arm"] == "CommandTimeout" and r["hold"] == "CommandTimeout" and r["land"] == "CommandTimeout"
                assert r["set_param"] == "TelemetryTimeout" and r["streamed"] > 100
            assert phase_a[2]["sent"] > 100 and phase_a[2]["version"] == "2.0"
            assert link.get_param("MPC_ACC_HOR_MAX", timeout_s=2.0) == pytest.approx(2.0)
            assert link.get_param("SIM_ARM_DENY", timeout_s=2.0) == 0.0
            assert link.get_param("COM_OF_LOSS_T", timeout_s=2.0) == pytest.approx(1.0)

            # --- phase B: the legitimate controller arms, streams north, enters OFFBOARD
            assert link.arm(timeout_s=3.0).armed
            link.start_setpoint_stream(rate_hz=20, acc_ned_m_s2=(1.0, 0.0, 0.0))
            time.sleep(1.2)
            assert link.start_offboard(timeout_s=3.0).is_offboard
            x0 = link.wait_local_position(None, timeout_s=2.0).x_m
            t_b0 = time.time()
            procs = _run_intruders(mock_port, 3.0, wrong_key)

            def flying(hb: Heartbeat, lp) -> None:
                assert hb.armed and hb.is_offboard, hb
                assert lp.vy_m_s == 0.0 and lp.y_m == 0.0, lp  # never steered east (or west)

            assert _watch(link, procs, flying) > 10
            _finish(procs)
            t_b1 = time.time()
            lp = link.wait_local_position(None, timeout_s=1.0)
            assert lp.x_m > x0 + 1.0 and lp.vx_m_s > 1.0  # the legitimate setpoints do steer it
            assert link.latest_heartbeat().is_offboard and link.latest_heartbeat().armed

            # --- phase C: replay the controller's own signed commands (captured in its tlog)
            assert link.hold(timeout_s=3.0).px4_mode == PX4_HOLD  # setpoints keep streaming
            captured = [
                r.raw for _, r in read_tlog(ctl_tlog)
                if isinstance(r.msg, CommandLong) and r.msg.command == MavCmd.DO_SET_MODE and r.msg.params[1] == 6.0
            ]  # fmt: skip  (the DO_SET_MODE OFFBOARD it sent in phase B)
            assert captured and all(raw[2] & 0x01 for raw in captured)  # the controller signs
            with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
                for _ in range(3):
                    for raw in captured:
                        s.sendto(raw, ("127.0.0.1", mock_port))
                    time.sleep(0.1)
            time.sleep(0.5)
            hb = link.latest_heartbeat()
            assert hb.px4_mode == PX4_HOLD and hb.armed  # the replayed OFFBOARD changed nothing
            link.stop_setpoint_stream()
            assert mock.proc.alive()
    log = mock.log_text()
    assert mock.proc.popen.returncode == 0  # a clean SIGTERM exit, nothing crashed

    # The vehicle logged each kind of rejection once (then counted), and why.
    for kind in ("unsigned COMMAND_LONG", "unsigned COMMAND_INT", "unsigned SET_MODE", "unsigned PARAM_SET",
                 "unsigned SET_POSITION_TARGET_LOCAL_NED", "bad signature COMMAND_LONG", "bad signature COMMAND_INT",
                 "bad signature SET_MODE", "bad signature PARAM_SET", "bad signature SET_POSITION_TARGET_LOCAL_NED",
                 "replayed timestamp COMMAND_LONG"):  # fmt: skip
        assert log.count(f"WARNING rejected {kind}: ") >= 1, kind
        assert log.count(f"WARNING rejected {kind}: ") <= 1 + 3, kind  # first line + at most one summary per 5 s
        assert log.count(f"WARNING rejected {kind}: {kind.split(' ')[-1]} from 1/191 (further ones are counted)") == 1, kind
    totals = {line.split("rejected ")[1].split(":")[0]: int(line.split(": ")[-1].split()[0]) for line in log.splitlines() if "in total" in line}
    assert totals["unsigned COMMAND_LONG"] > 100 and totals["bad signature SET_POSITION_TARGET_LOCAL_NED"] > 100
    assert totals["replayed timestamp COMMAND_LONG"] >= len(captured)

    # The vehicle's tlog: it signed everything it sent; it received the intruders' packets;
    # no HEARTBEAT it sent showed it armed in phase A, or out of armed OFFBOARD in phase B.
    records = read_tlog(mock_tlog)
    sent = [(t, r) for t, r in records if (r.src_system, r.src_component) == (1, 1)]
    assert sent and all(r.raw[0] == 0xFD and r.raw[2] & 0x01 for _, r in sent)
    received_unsigned = [r for _, r in records if r.src_component == LEGIT_COMPONENT and not r.raw[2] & 0x01]
    assert len(received_unsigned) > 100  # the intruders' packets did reach the vehicle
    hbs = [(t, r.msg) for t, r in sent if isinstance(r.msg, Heartbeat)]
    assert [h for t, h in hbs if t_a0 <= t <= t_a1 and h.armed] == []
    in_b = [h for t, h in hbs if t_b0 <= t <= t_b1]
    assert len(in_b) >= 2 and all(h.armed and h.is_offboard for h in in_b)


def test_link_with_a_key_ignores_an_unsigned_vehicle_unless_told_to_accept_unsigned(tmp_path):
    """The controller side: a VehicleLink with a key does not believe an unsigned (or
    differently keyed) vehicle's HEARTBEAT -- it could be an intruder posing as the vehicle."""
    key = bytes(range(32))
    with running_mock_vehicle(log_dir=tmp_path) as plain_mock:
        with VehicleLink.open(plain_mock.onboard_url, target_system=1, signing_key=key) as link:
            wait_until(lambda: link.rejects.counts.get("unsigned packet", 0) > 50, 40.0, "the vehicle's unsigned telemetry")
            with pytest.raises(HeartbeatTimeout):
                link.wait_heartbeat(timeout_s=1.5)
            assert link.latest_local_position() is None
        with VehicleLink.open(plain_mock.onboard_url, target_system=1, signing_key=key, accept_unsigned=True) as link:
            assert link.wait_heartbeat(timeout_s=5.0).autopilot == 12
    other = tmp_path / "other.key"
    write_signing_key(other)
    with running_mock_vehicle("--signing-key", str(other), log_dir=tmp_path) as keyed_mock:
        with VehicleLink.open(keyed_mock.onboard_url, target_system=1, signing_key=key, accept_unsigned=True) as link:
            wait_until(lambda: link.rejects.counts.get("bad signature packet", 0) > 50, 40.0, "the vehicle's telemetry")
            with pytest.raises(HeartbeatTimeout):
                link.wait_heartbeat(timeout_s=1.5)
            assert link.latest_local_position() is None


def test_mock_vehicle_refuses_a_missing_or_loose_key_file_with_the_fix(tmp_path):
    from _net import mock_vehicle_cmd

    loose = tmp_path / "loose.key"
    write_signing_key(loose)
    os.chmod(loose, 0o644)
    for path, needle in ((tmp_path / "missing.key", "does not exist"), (loose, "chmod 600")):
        out = subprocess.run(
            mock_vehicle_cmd(9, "--signing-key", str(path)), cwd=REPO, capture_output=True, text=True, timeout=30
        )
        assert out.returncode == 2 and needle in out.stderr and str(path) in out.stderr, out.stderr


def test_a_signing_listening_link_answers_only_validly_signed_senders():
    """``udpin`` answers the last sender; with signing on, only a sender of a validly signed
    packet becomes that peer, so an intruder's datagrams cannot divert the controller's
    commands and setpoints away from the vehicle."""
    from _net import free_udp_port
    from mavlink_bridge import SigningConfig

    key = bytes(range(32))
    port = free_udp_port()
    with VehicleLink.open(f"udpin:127.0.0.1:{port}", target_system=1, signing_key=key, heartbeat_rate_hz=20) as link:
        vehicle = MavlinkPort.open(f"udpout:127.0.0.1:{port}", 1, 1, signing=SigningConfig(key))
        intruder = MavlinkPort.open(f"udpout:127.0.0.1:{port}", 1, 1)
        wrong = MavlinkPort.open(f"udpout:127.0.0.1:{port}", 1, 1, signing=SigningConfig(bytes(32)))
        try:
            hb = Heartbeat(2, 12, 0x81, 0, 4)
            vehicle.send(hb)
            link.wait_heartbeat(timeout_s=5.0)
            vehicle_addr = vehicle.transport.local_address
            assert wait_until(lambda: link.port.transport.peer == vehicle_addr, 5.0, "peer = the vehicle")
            for _ in range(50):
                intruder.send(hb)
                wrong.send(hb)
                intruder.send_raw(b"\xfd garbage")
            time.sleep(0.3)
            assert link.port.transport.peer == vehicle_addr
            got = []
            deadline = time.monotonic() + 3.0
            while not got and time.monotonic() < deadline:
                got = [r for r in vehicle.recv(0.2) if r.signed_ok and isinstance(r.msg, Heartbeat)]
            assert got, "the link's signed heartbeats still reach the vehicle"
            assert intruder.recv(0.3) == [] and wrong.recv(0.1) == []
        finally:
            for p in (vehicle, intruder, wrong):
                p.close()
