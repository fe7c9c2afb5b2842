"""PX4's two gates for SET_POSITION_TARGET_LOCAL_NED, as the mock vehicle applies them (SPEC 4;
docs/mavlink.md "Setpoints"). Pure functions, no I/O.

1. The MAVLink receiver (PX4-Autopilot ``src/modules/mavlink/mavlink_receiver.cpp``,
   ``MavlinkReceiver::handle_message_set_position_target_local_ned``) drops a message whose target
   system/component is neither this vehicle nor 0, whose frame is neither LOCAL_NED nor BODY_NED, that
   sets FORCE_SET while it carries an acceleration, or that leaves position, velocity and acceleration
   all NaN ("SET_POSITION_TARGET_LOCAL_NED invalid"). Per field, an ignore bit makes the field NaN and
   any other value is copied as it is (so a NaN value is an ignored field too). In BODY_NED the position
   is always NaN, and one ignore bit among vx, vy, vz (or ax, ay, az) drops the whole vector. Whatever
   passes publishes ``offboard_control_mode``: it feeds the offboard check (COM_OF_LOSS_T) and, in
   OFFBOARD, becomes the ``trajectory_setpoint``.
2. The position controller (``src/modules/mc_pos_control/PositionControl/PositionControl.cpp``,
   ``PositionControl::_inputValid``) needs on each of x, y, z at least one finite term (position,
   velocity or acceleration), and x, y in pairs per kind. Otherwise ``MulticopterPositionControl``
   flies ``generateFailsafeSetpoint``: velocity 0 on every axis ("Failsafe: stop and wait"), while
   the vehicle stays in OFFBOARD (the receiver did accept the message).

``classify_setpoint`` returns None for a setpoint the mock flies, or a ``SetpointVerdict`` saying which
gate refused it (``keeps_offboard``: the receiver accepted it, only the position controller refused).
The mock adds one guard of its own, "setpoint out of range" (a used field beyond ``SETPOINT_LIMITS``),
a receiver-level rejection PX4 does not have, so a plant can never be driven to overflow. And a
non-finite value in a field the mask uses always makes the mock "stop and wait": PX4 drops just that
field and flies the rest when every axis keeps a term (e.g. position and velocity on x with a NaN
velocity); for 3135 and 3387, the masks this project uses, the two agree.
"""

from __future__ import annotations

import math
from typing import NamedTuple

from mavlink_bridge import MavFrame, PositionTargetTypeMask, SetPositionTargetLocalNed

__all__ = ["SETPOINT_LIMITS", "SetpointVerdict", "classify_setpoint", "check_setpoint", "RECEIVER_KINDS", "CONTROLLER_KINDS"]

SETPOINT_LIMITS = {"position_m": 1.0e5, "velocity_m_s": 100.0, "acceleration_m_s2": 100.0, "yaw_rad": 100.0, "yaw_rate_rad_s": 100.0}
"""Largest magnitude of a used SET_POSITION_TARGET_LOCAL_NED field; beyond it the setpoint
is rejected ("setpoint out of range") before it can reach the plant (the mock's own guard, not
PX4's). The plant also saturates the acceleration at MPC_ACC_HOR_MAX."""

RECEIVER_KINDS = ("setpoint wrong target system", "setpoint wrong target component", "setpoint unsupported frame",
                  "setpoint FORCE_SET bit", "setpoint ignores everything", "setpoint out of range")
"""Refused before anything happens: not an offboard heartbeat, the held setpoint is kept."""
CONTROLLER_KINDS = ("setpoint non-finite field", "setpoint axis without a term", "setpoint x/y not in pairs")
"""Accepted by the receiver (feeds the offboard check), refused by the position controller: stop and wait."""


class SetpointVerdict(NamedTuple):
    kind: str
    detail: str
    keeps_offboard: bool
    """True: PX4's receiver accepts it (the offboard check is fed, OFFBOARD stays), but its
    position controller flies the failsafe "stop and wait" instead."""


_F = PositionTargetTypeMask
_FORCE_SET = int(_F.FORCE_SET)
_LOCAL_NED, _BODY_NED = int(MavFrame.LOCAL_NED), int(MavFrame.BODY_NED)
_VEL_BITS = int(_F.VELOCITY_IGNORE)
_ACC_BITS = int(_F.ACCELERATION_IGNORE)
_SETPOINT_FIELDS = (
    (int(_F.X_IGNORE), "x_m", "position_m"), (int(_F.Y_IGNORE), "y_m", "position_m"), (int(_F.Z_IGNORE), "z_m", "position_m"),
    (int(_F.VX_IGNORE), "vx_m_s", "velocity_m_s"), (int(_F.VY_IGNORE), "vy_m_s", "velocity_m_s"),
    (int(_F.VZ_IGNORE), "vz_m_s", "velocity_m_s"),
    (int(_F.AX_IGNORE), "afx_m_s2", "acceleration_m_s2"), (int(_F.AY_IGNORE), "afy_m_s2", "acceleration_m_s2"),
    (int(_F.AZ_IGNORE), "afz_m_s2", "acceleration_m_s2"),
    (int(_F.YAW_IGNORE), "yaw_rad", "yaw_rad"), (int(_F.YAW_RATE_IGNORE), "yaw_rate_rad_s", "yaw_rate_rad_s"),
)  # fmt: skip
"""(ignore bit, field, SETPOINT_LIMITS key) of every field a mask can use, in wire order."""
_isfinite = math.isfinite


def _terms(sp: SetPositionTargetLocalNed, values: list[float]) -> tuple[list[bool], list[bool], list[bool]]:
    """Which of the ``trajectory_setpoint`` terms PX4's receiver leaves finite: (position, velocity,
    acceleration), each [x, y, z]. ``values``: the 9 position/velocity/acceleration fields in wire order."""
    m = sp.type_mask
    fin = [(not m & bit) and _isfinite(v) for (bit, _, _), v in zip(_SETPOINT_FIELDS[:9], values)]
    if sp.coordinate_frame == _LOCAL_NED:
        return fin[0:3], fin[3:6], fin[6:9]
    # BODY_NED: no position; a vector with any ignore bit is dropped whole; the rotation to NED mixes
    # x and y (cos/sin of yaw; the mock's yaw is 0, but 0 * NaN is NaN), and the acceleration all three
    vel = [False] * 3 if m & _VEL_BITS else [fin[3] and fin[4], fin[3] and fin[4], fin[5]]
    acc = [False] * 3 if m & _ACC_BITS else [all(fin[6:9])] * 3
    return [False] * 3, vel, acc


def classify_setpoint(sp: SetPositionTargetLocalNed, system_id: int, component_id: int) -> SetpointVerdict | None:
    """None if the mock flies ``sp`` as given; else the verdict of PX4's receiver (``keeps_offboard``
    False) or of its position controller (True). See the module docstring."""
    if sp.target_system not in (0, system_id):
        return SetpointVerdict("setpoint wrong target system", f"target_system {sp.target_system}, this vehicle is {system_id}", False)
    if sp.target_component not in (0, component_id):
        return SetpointVerdict("setpoint wrong target component", f"target_component {sp.target_component}", False)
    if sp.coordinate_frame not in (_LOCAL_NED, _BODY_NED):
        return SetpointVerdict("setpoint unsupported frame",
                               f"coordinate_frame {sp.coordinate_frame} (LOCAL_NED=1 or BODY_NED=8 only)", False)
    mask = sp.type_mask
    values = [sp.x_m, sp.y_m, sp.z_m, sp.vx_m_s, sp.vy_m_s, sp.vz_m_s, sp.afx_m_s2, sp.afy_m_s2, sp.afz_m_s2]
    pos, vel, acc = _terms(sp, values)
    if mask & _FORCE_SET and any(acc):
        return SetpointVerdict("setpoint FORCE_SET bit", f"type_mask {mask:#06x}: force is not supported", False)
    if not (any(pos) or any(vel) or any(acc)):
        return SetpointVerdict("setpoint ignores everything",
                               f"type_mask {mask:#06x}: no finite position, velocity or acceleration", False)
    used = [(getattr(sp, name), SETPOINT_LIMITS[key]) for bit, name, key in _SETPOINT_FIELDS if not mask & bit]
    if any(_isfinite(v) and abs(v) > limit for v, limit in used):
        return SetpointVerdict("setpoint out of range", f"a used field beyond its limit {SETPOINT_LIMITS} (type_mask {mask:#06x})", False)
    if not all(_isfinite(v) for v, _ in used):
        return SetpointVerdict("setpoint non-finite field",
                               f"NaN/inf in a used field (type_mask {mask:#06x}): offboard kept, stop and wait", True)
    for i in range(3):
        if not (pos[i] or vel[i] or acc[i]):
            return SetpointVerdict("setpoint axis without a term",
                                   f"type_mask {mask:#06x}: {'xyz'[i]} has no position, velocity or acceleration "
                                   "(PX4's PositionControl refuses it): offboard kept, stop and wait", True)
    if pos[0] != pos[1] or vel[0] != vel[1] or acc[0] != acc[1]:
        return SetpointVerdict("setpoint x/y not in pairs",
                               f"type_mask {mask:#06x}: x and y need the same kinds of terms (PX4's PositionControl): "
                               "offboard kept, stop and wait", True)
    return None


def check_setpoint(sp: SetPositionTargetLocalNed, system_id: int, component_id: int) -> tuple[str, str] | None:
    """None if the mock flies ``sp`` as given (every field the mask uses is then finite and within
    ``SETPOINT_LIMITS``), else (kind, detail) of the refusal, from either gate (``classify_setpoint``)."""
    v = classify_setpoint(sp, system_id, component_id)
    return None if v is None else (v.kind, v.detail)
