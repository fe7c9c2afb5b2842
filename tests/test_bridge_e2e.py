"""mavlink_bridge.VehicleLink against a real mock-vehicle process over loopback UDP:
the handshake and its typed failures (issue 4 "Must show")."""

from __future__ import annotations

import math
import time

import pytest

from _net import running_mock_vehicle
from mavlink_bridge import (
    PX4_HOLD,
    PX4_LAND,
    CommandDenied,
    HeartbeatTimeout,
    MavResult,
    SetPositionTargetLocalNed,
    VehicleLink,
    read_tlog,
)

pytestmark = pytest.mark.e2e


def test_full_handshake_arm_offboard_hold_land(tmp_path):
    with running_mock_vehicle("--initial-pos-m", "150,100") as mock:
        with VehicleLink.open(mock.onboard_url, target_system=1, tlog_path=str(tmp_path / "ctl.tlog")) as link:
            hb = link.wait_heartbeat(timeout_s=10.0)
            assert hb.autopilot == 12 and hb.type == 2 and not hb.armed
            p0 = link.wait_local_position(None, timeout_s=2.0)
            assert (p0.x_m, p0.y_m, p0.z_m) == (150.0, 100.0, -10.0)  # frozen at its slot before OFFBOARD
            assert link.arm(timeout_s=3.0).armed
            link.start_setpoint_stream(rate_hz=20, acc_ned_m_s2=(-1.0, 0.0, 0.0))
            time.sleep(1.2)  # PX4: >= 2 Hz for > 1 s
            hb = link.start_offboard(timeout_s=3.0)
            assert hb.is_offboard and hb.armed
            time.sleep(1.0)
            assert link.telemetry_age_s() < 0.2 and link.heartbeat_age_s() < 1.5
            p1 = link.wait_local_position(p0.time_boot_ms, timeout_s=1.0)
            assert p1.x_m != p0.x_m  # it flies now
            assert link.hold(timeout_s=3.0).px4_mode == PX4_HOLD
            link.stop_setpoint_stream()
            assert link.land(timeout_s=3.0).px4_mode == PX4_LAND
            assert not link.disarm(timeout_s=3.0).armed
        sent = [r for _, r in read_tlog(tmp_path / "ctl.tlog") if isinstance(r.msg, SetPositionTargetLocalNed)]
        assert len(sent) > 20 and {(r.msg.target_system, r.msg.target_component) for r in sent} == {(1, 1)}


def test_no_heartbeat_from_target_is_a_timeout():
    """A vehicle is there, but it is system 1; the link waits for system 2."""
    with running_mock_vehicle() as mock:
        with VehicleLink.open(mock.onboard_url, target_system=2) as link:
            with pytest.raises(HeartbeatTimeout, match="no HEARTBEAT from system 2"):
                link.wait_heartbeat(timeout_s=1.5)
            assert link.n_ignored_other_system > 0


def test_arm_denied_and_offboard_denied_are_typed_errors():
    with running_mock_vehicle("--deny-arming") as mock:
        with VehicleLink.open(mock.onboard_url, target_system=1) as link:
            link.wait_heartbeat(timeout_s=10.0)
            with pytest.raises(CommandDenied, match=r"COMPONENT_ARM_DISARM\(400\) refused by system 1: MAV_RESULT_DENIED") as e:
                link.arm(timeout_s=3.0)
            assert e.value.result == MavResult.DENIED
            # no setpoint stream: PX4 refuses OFFBOARD
            with pytest.raises(CommandDenied, match=r"DO_SET_MODE\(176\).*TEMPORARILY_REJECTED"):
                link.start_offboard(timeout_s=3.0)
            # arming becomes possible once the preflight "failure" is cleared
            assert link.set_param("SIM_ARM_DENY", 0.0, timeout_s=2.0) == 0.0
            assert link.arm(timeout_s=3.0).armed


def test_wait_local_position_returns_newer_samples():
    with running_mock_vehicle() as mock:
        with VehicleLink.open(mock.onboard_url, target_system=1) as link:
            first = link.wait_local_position(None, timeout_s=10.0)
            nxt = link.wait_local_position(first.time_boot_ms, timeout_s=1.0)
            assert nxt.time_boot_ms > first.time_boot_ms and not math.isnan(nxt.received_monotonic_s)
