"""Fuzzing the MAVLink inputs (issue 10 "Bad input, fuzzed").

- CI: 100,000 random and mutated frames (``tests/fuzz_mavlink.py``: valid CRCs with wrong
  fields, truncated frames, wrong lengths, NaN/inf/huge values, garbage, ...) to a running
  mock-vehicle process over loopback UDP, and 100,000 to a listening controller-side
  ``VehicleLink``. Then: no process died, the vehicle's telemetry is finite, it still sends
  HEARTBEATs and obeys a legitimate command, and every kind of rejection was logged once
  (plus at most one count line per 5 s), not once per frame.
- In process, hypothesis drives the setpoint filter and the vehicle's setpoint handling
  with arbitrary floats: nothing non-finite or out of range reaches the plant.

Long run: ``.venv/bin/python -m tests.fuzz_mavlink --frames 1000000`` (docs/security.md).
"""

from __future__ import annotations

import collections
import logging
import math
import re
import time
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from _net import free_udp_port, running_mock_vehicle
from fuzz_mavlink import KINDS, FrameFuzzer, fuzz_link, fuzz_mock
from mavlink_bridge import (
    PX4_HOLD,
    PX4_OFFBOARD,
    Heartbeat,
    LocalPositionNed,
    MavlinkPort,
    SetPositionTargetLocalNed,
    SigningConfig,
    VehicleLink,
    load_signing_key,
    write_signing_key,
)
from mavlink_bridge.codec import MAVLINK_MSG_ID, MavCodec
from mock_vehicle.vehicle import SETPOINT_LIMITS, MockVehicle, VehicleConfig, check_setpoint

CI_FRAMES = 100_000
RATE_PERIOD_S = 5.0  # RejectLog's summary period
_REJECT_LINE = re.compile(r"rejected (.+?): ")


def _rejection_lines(lines: list[str]) -> collections.Counter:
    out: collections.Counter = collections.Counter()
    for line in lines:
        if "in total" in line:
            continue  # the shutdown summary
        m = _REJECT_LINE.search(line)
        if m and ("WARNING" in line or "further ones are counted" in line or "more (total" in line):
            out[m.group(1)] += 1
    return out


def _assert_once_per_kind(lines: list[str], wall_s: float, frames: int) -> collections.Counter:
    per_kind = _rejection_lines(lines)
    firsts = collections.Counter(_REJECT_LINE.search(l).group(1) for l in lines if "further ones are counted" in l)  # noqa: E741
    assert per_kind, "no rejection was logged at all"
    assert set(firsts) == set(per_kind) and all(n == 1 for n in firsts.values()), firsts
    bound = 2 + math.ceil(wall_s / RATE_PERIOD_S)
    assert max(per_kind.values()) <= bound, (per_kind, bound)
    assert sum(per_kind.values()) < frames / 100
    return per_kind


def _finite_lp(lp: LocalPositionNed) -> bool:
    return all(map(math.isfinite, (lp.x_m, lp.y_m, lp.z_m, lp.vx_m_s, lp.vy_m_s, lp.vz_m_s)))


def run_mock_fuzz(frames: int, seed: int, log_dir: Path, key_path: Path | None = None) -> dict:
    """Fuzz a mock-vehicle process with ``frames`` datagrams and check it afterwards
    (``key_path``: the vehicle runs with ``--signing-key``; the checks use a keyed link)."""
    key = None if key_path is None else load_signing_key(key_path)
    extra = () if key_path is None else ("--signing-key", str(key_path))
    with running_mock_vehicle("--initial-pos-m", "5,-5", *extra, log_dir=log_dir) as mock:
        report = fuzz_mock(mock.onboard_port, frames, seed=seed, signing=None if key is None else SigningConfig(key))
        assert mock.proc.alive(), mock.log_text()[-3000:]
        with VehicleLink.open(mock.onboard_url, target_system=1, signing_key=key) as link:
            # the fuzz may have switched telemetry off (SET_MESSAGE_INTERVAL -1): restore it
            for name in ("HEARTBEAT", "LOCAL_POSITION_NED"):
                link.set_message_interval(MAVLINK_MSG_ID[name], 0, timeout_s=10.0)
            t = time.monotonic()
            hb = link.wait_heartbeat(timeout_s=5.0, newer_than_monotonic_s=t)
            report["armed_before_legit_arm"] = hb.armed
            lp = link.wait_local_position(None, timeout_s=5.0)
            assert _finite_lp(lp), lp
            link.set_param("SIM_ARM_DENY", 0.0, timeout_s=10.0)  # the fuzz may have set it
            assert link.arm(timeout_s=10.0).armed  # a legitimate command still works
            lp2 = link.wait_local_position(lp.time_boot_ms, timeout_s=5.0)
            assert _finite_lp(lp2), lp2
            report.update(after_heartbeat_mode=hb.px4_mode.name, after_pos_m=[lp2.x_m, lp2.y_m], after_vel_m_s=[lp2.vx_m_s, lp2.vy_m_s])
        assert mock.proc.alive()
    assert mock.proc.popen.returncode == 0, "the mock did not exit cleanly on SIGTERM"
    log = mock.log_text().splitlines()
    assert not any("Traceback" in line or "internal error" in line for line in log), "\n".join(log[-80:])
    report["rejection_log_lines"] = dict(_assert_once_per_kind(log, report["wall_s"], frames))
    report["log_lines_total"] = len(log)
    datagrams = [int(m.group(1)) for line in log if (m := re.search(r"link udpout:\S+: (\d+) datagrams", line))]
    assert datagrams, "no link summary at shutdown"
    report["datagrams_read_by_mock"] = datagrams[0]
    # every fuzz datagram (plus syncs and the legit link's traffic) was read, none lost
    assert datagrams[0] >= frames, (datagrams, frames)
    assert report["sync_timeouts"] == 0
    return report


class _Lines(logging.Handler):
    def __init__(self) -> None:
        super().__init__(logging.DEBUG)
        self.lines: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.lines.append(f"{record.levelname} {record.getMessage()}")


def run_link_fuzz(frames: int, seed: int) -> dict:
    """Fuzz a listening VehicleLink (controller side) and check it afterwards."""
    handler = _Lines()
    logger = logging.getLogger("mavlink_bridge")
    old_level = logger.level
    logger.addHandler(handler)
    logger.setLevel(logging.DEBUG)
    try:
        port = free_udp_port()
        with VehicleLink.open(f"udpin:127.0.0.1:{port}", target_system=1, heartbeat_rate_hz=10) as link:
            report = fuzz_link(link, frames, seed=seed)
            assert link._rx_thread.is_alive() and link._hb_thread.is_alive()
            lp = link.latest_local_position()
            assert lp is not None and _finite_lp(lp), lp
            assert len(link._params) <= 4096  # random PARAM_VALUEs cannot grow it without bound
            # a real vehicle's HEARTBEAT still gets through, and the link still sends
            vehicle = MavlinkPort.open(f"udpout:127.0.0.1:{port}", 1, 1)
            try:
                t = time.monotonic()
                vehicle.send(Heartbeat(2, 12, 0x81 | 0x80, PX4_OFFBOARD.custom_mode, 4))
                hb = link.wait_heartbeat(timeout_s=5.0, newer_than_monotonic_s=t)
                assert hb.is_offboard and hb.armed
                got = []
                deadline = time.monotonic() + 5.0
                while not any(isinstance(r.msg, Heartbeat) for r in got) and time.monotonic() < deadline:
                    got += vehicle.recv(0.2)
                assert any(isinstance(r.msg, Heartbeat) and (r.src_system, r.src_component) == (1, 191) for r in got)
            finally:
                vehicle.close()
        report["rejections_by_kind"] = dict(link.rejects.counts)
        report["ignored_other_system"] = link.n_ignored_other_system
    finally:
        logger.removeHandler(handler)
        logger.setLevel(old_level)
    report["rejection_log_lines"] = dict(_assert_once_per_kind(handler.lines, report["wall_s"], frames))
    report["log_lines_total"] = len(handler.lines)
    assert report["sync_timeouts"] == 0
    return report


# ------------------------------------------------------------------ CI runs
@pytest.mark.e2e
def test_fuzz_mock_vehicle_process_with_100k_frames(tmp_path, capsys):
    t0 = time.monotonic()
    report = run_mock_fuzz(CI_FRAMES, seed=1, log_dir=tmp_path)
    report["test_wall_s"] = round(time.monotonic() - t0, 1)
    with capsys.disabled():
        print(f"\nmock-vehicle fuzz: {report}")
    assert report["frames"] == CI_FRAMES and all(report["kinds"][k] > 0 for k in KINDS)


@pytest.mark.e2e
def test_fuzz_signing_mock_vehicle_with_30k_frames(tmp_path, capsys):
    """With --signing-key, none of the fuzz frames (unsigned, or with random signature
    blocks) gets past the signature check: the vehicle stays disarmed in HOLD, parameters and
    telemetry rates untouched, and it still flies for the keyed link."""
    key_path = tmp_path / "k.key"
    write_signing_key(key_path)
    t0 = time.monotonic()
    report = run_mock_fuzz(30_000, seed=4, log_dir=tmp_path, key_path=key_path)
    report["test_wall_s"] = round(time.monotonic() - t0, 1)
    with capsys.disabled():
        print(f"\nsigning mock-vehicle fuzz: {report}")
    assert report["after_heartbeat_mode"] == PX4_HOLD.name and report["armed_before_legit_arm"] is False
    kinds = set(report["rejection_log_lines"])
    assert {"unsigned COMMAND_LONG", "unsigned SET_POSITION_TARGET_LOCAL_NED", "unsigned other message", "bad packet"} <= kinds
    assert any(k.startswith("bad signature") for k in kinds)
    handler_kinds = {"setpoint wrong target system", "unsupported command", "PARAM_SET refused", "setpoint non-finite field"}
    assert not (kinds & handler_kinds), "a fuzz frame reached the handlers past the signature check"


@pytest.mark.e2e
def test_fuzz_controller_vehicle_link_with_100k_frames(capsys):
    t0 = time.monotonic()
    report = run_link_fuzz(CI_FRAMES, seed=2)
    report["test_wall_s"] = round(time.monotonic() - t0, 1)
    with capsys.disabled():
        print(f"\nVehicleLink fuzz: {report}")
    assert report["frames"] == CI_FRAMES and all(report["kinds"][k] > 0 for k in KINDS)


def test_fuzzer_makes_every_kind_and_valid_crc_frames_that_parse():
    """The generator itself: its 'valid CRC, wrong fields' frames do parse as messages
    (so they reach the handlers instead of dying at the CRC check)."""
    fz = FrameFuzzer(seed=3)
    codec = MavCodec(9, 9)
    parsed, top = collections.Counter(), collections.Counter()
    for _ in range(5000):
        kind, data = fz.frame()
        top[kind] += 1
        if kind in ("mutated", "fields"):
            out = codec.decode_datagram(data)
            parsed[kind] += sum(1 for r in out if r.msg.MSG_NAME not in ("BAD_DATA",))
    assert all(fz.counts[k] > 0 for k in KINDS)
    assert parsed["mutated"] > 0.95 * top["mutated"] and parsed["fields"] > 0.95 * top["fields"], (parsed, top)


# ------------------------------------------------------------------ in process (hypothesis)
any_float = st.floats(allow_nan=True, allow_infinity=True, width=32)


@settings(max_examples=1000, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    mask=st.integers(0, 0xFFFF),
    frame=st.sampled_from([1, 8, 7, 0]),
    values=st.lists(any_float, min_size=11, max_size=11),
)
def test_setpoint_filter_lets_only_finite_bounded_used_fields_through(mask, frame, values):
    sp = SetPositionTargetLocalNed(0, 1, 1, frame, mask, *values)
    if check_setpoint(sp, 1, 1) is None:
        used = [v for bit, v in zip((1, 2, 4, 8, 16, 32, 64, 128, 256, 1024, 2048), values) if not mask & bit]
        assert all(math.isfinite(v) for v in used)
        assert all(abs(v) <= max(SETPOINT_LIMITS.values()) for v in used)


class _Clock:
    def __init__(self) -> None:
        self.t = 1000.0

    def __call__(self) -> float:
        return self.t


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(setpoints=st.lists(st.tuples(st.sampled_from([3135, 0x0DC7, 0x0DF8, 0x0DF9, 0x0DC0, 0]), st.lists(any_float, min_size=11, max_size=11)),
                          min_size=1, max_size=20))  # fmt: skip
def test_vehicle_state_stays_finite_whatever_setpoints_arrive_in_offboard(setpoints):
    """Given an armed vehicle in OFFBOARD, any sequence of setpoints (NaN, inf, 3.4e38 in
    any field, any mask) leaves the plant state finite, and the plant never raises."""
    clock = _Clock()
    sent: list = []
    v = MockVehicle(VehicleConfig(), lambda m, p: sent.append(m), clock=clock)
    good = SetPositionTargetLocalNed(0, 1, 1, 1, 3135, 0, 0, 0, 0, 0, 0, 0.5, 0.5, 0, 0, 0)
    from mavlink_bridge import Received

    for _ in range(15):  # stream > 1 s at 10 Hz, then OFFBOARD
        v.handle(Received(good, 1, 191))
        clock.t += 0.1
        v.tick()
    v.armed = True
    v._request_mode(PX4_OFFBOARD)
    assert v.mode == PX4_OFFBOARD
    for mask, vals in setpoints:
        v.handle(Received(SetPositionTargetLocalNed(0, 1, 1, 1, mask, *vals), 1, 191))
        clock.t += 0.25
        v.tick()
        assert np.all(np.isfinite(v.state)), (mask, vals, v.state)
    assert "non-finite acceleration" not in v.rejects.counts and "non-finite plant state" not in v.rejects.counts
