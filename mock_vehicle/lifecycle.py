"""The mock vehicle's PX4 mode machine: arming, takeoff, hold, land, the offboard-loss failsafe, the
vertical axis and the ground (issue 19; docs/mavlink.md "Flying a real field" cites the PX4 source of
every rule).

``LifecycleMixin`` is a part of ``MockVehicle`` (mock_vehicle/vehicle.py), split out where the reader
pauses: it reads and writes the vehicle's state (``armed``, ``mode``, ``landed``, ``flying``, ``z_m``,
``vz_m_s``, ``z_target_m``, ``hold_pos_m``, ``params``, the setpoint) and talks through the vehicle's
telemetry (``_send_heartbeat``, ``_statustext``). The altitude loop itself is the pure
``vertical_step`` (PX4's mc_pos_control: P on z -> vz within MPC_Z_VEL_MAX_UP/DN -> P on vz -> a
vertical acceleration within the thrust limits).

Two starts (``VehicleConfig.start_on_ground``):
- air (the default, as before issue 19): the vehicle hovers at its slot, disarmed, frozen until the
  first OFFBOARD entry; Land touches down and disarms at once; disarming is always accepted.
- ground: ON_GROUND, disarmed, z = 0, at its launch point; PX4's lifecycle: arm; MAV_CMD_NAV_TAKEOFF
  (also while disarmed: the mode changes and the climb starts at arming) climbs in AUTO.TAKEOFF to
  param 7 (AMSL) or MIS_TAKEOFF_ALT above where it is, then AUTO.LOITER; MAV_CMD_NAV_LAND descends at
  MPC_LAND_SPEED, touches down, disarms COM_DISARM_LAND later; armed on the ground without a takeoff,
  it disarms after COM_DISARM_PRFLT; disarming in the air is refused unless forced (21196).
"""

from __future__ import annotations

import logging
import math

import numpy as np

from mavlink_bridge import (
    PX4_HOLD,
    PX4_LAND,
    PX4_OFFBOARD,
    PX4_POSCTL,
    PX4_TAKEOFF,
    MavFrame,
    MavModeFlag,
    MavResult,
    MavSeverity,
    PositionTargetTypeMask,
    Px4MainMode,
    Px4Mode,
    SetMode,
)

from .plant import braking_stop_m, position_brake_path_m

__all__ = ["LifecycleMixin", "vertical_step", "HOLD_LIKE", "GRAVITY_M_S2"]

log = logging.getLogger("mock_vehicle")

GRAVITY_M_S2 = 9.80665
HOLD_LIKE = (PX4_HOLD, PX4_POSCTL)
FORCE_ARM_DISARM = 21196.0       # COMPONENT_ARM_DISARM param 2: force arming or disarming (PX4 Commander.cpp)
VERTICAL_SUBSTEP_S = 0.05        # the altitude loop's Euler step: MPC_Z_VEL_P_ACC * h well below 1
ACC_UP_MAX_M_S2 = GRAVITY_M_S2   # thrust limits around hover thrust 0.5 (MPC_THR_HOVER): MPC_THR_MAX 1.0 gives +1 g up,
ACC_DOWN_MAX_M_S2 = 0.76 * GRAVITY_M_S2  # MPC_THR_MIN 0.12 at most 0.76 g down
POSCTL_DT_S = 0.02               # PX4's flight task rate (50 Hz): the Position-mode braking path's step
OBL_ACTIONS = {4: "Land"}        # COM_OBL_RC_ACT values the mock flies other than Hold (docs/mavlink.md)

_Z_IGNORE, _VZ_IGNORE, _AZ_IGNORE = int(PositionTargetTypeMask.Z_IGNORE), int(PositionTargetTypeMask.VZ_IGNORE), int(PositionTargetTypeMask.AZ_IGNORE)


def vertical_step(z_m: float, vz_m_s: float, dt_s: float, *, z_sp_m: float | None = None, vz_sp_m_s: float | None = None,
                  az_ff_m_s2: float | None = None, z_p_per_s: float = 1.0, vel_p_per_s: float = 4.0,
                  vel_max_up_m_s: float = 3.0, vel_max_dn_m_s: float = 1.5) -> tuple[float, float]:
    """One ``dt_s`` of PX4's altitude loop (mc_pos_control ``PositionControl::_positionControl`` and
    ``_velocityControl``; NED, z down): with a z setpoint, vz_sp = clip(MPC_Z_P (z_sp - z) + vz_ff,
    -MPC_Z_VEL_MAX_UP, MPC_Z_VEL_MAX_DN); with only a vz setpoint, vz_sp = clip(vz_ff, ...); then
    az = MPC_Z_VEL_P_ACC (vz_sp - vz) + az_ff within the thrust limits. With neither (an
    acceleration-only setpoint) there is no feedback: vz changes by az_ff only (``_vertical`` holds z
    for az_ff = 0, the mock's optimistic hover; a real vehicle drifts). Explicit Euler in sub-steps of
    at most VERTICAL_SUBSTEP_S (the integral and derivative terms, MPC_Z_VEL_I_ACC/D_ACC, are not
    modelled). Returns (z_m, vz_m_s)."""
    n = max(1, math.ceil(dt_s / VERTICAL_SUBSTEP_S - 1e-9))
    h = dt_s / n
    az_ff = 0.0 if az_ff_m_s2 is None else az_ff_m_s2
    for _ in range(n):
        if z_sp_m is not None:
            vz_sp = min(max(z_p_per_s * (z_sp_m - z_m) + (vz_sp_m_s or 0.0), -vel_max_up_m_s), vel_max_dn_m_s)
        elif vz_sp_m_s is not None:
            vz_sp = min(max(vz_sp_m_s, -vel_max_up_m_s), vel_max_dn_m_s)
        else:
            vz_sp = None
        az = az_ff if vz_sp is None else vel_p_per_s * (vz_sp - vz_m_s) + az_ff
        az = min(max(az, -ACC_UP_MAX_M_S2), ACC_DOWN_MAX_M_S2)
        vz_m_s += az * h
        z_m += vz_m_s * h
    return z_m, vz_m_s


class LifecycleMixin:
    """Arming, modes, takeoff, land, the failsafe and the vertical axis of ``MockVehicle`` (module docstring)."""

    # ------------------------------------------------------------------ arming
    def _arm_disarm(self, p1: float, p2: float) -> MavResult:
        """COMMAND_LONG 400. PX4 (Commander.cpp ``handle_command``): a refused (dis)arming is
        TEMPORARILY_REJECTED; the mock answers its SIM_ARM_DENY (a failed preflight check) with DENIED."""
        if p1 == 1.0:
            if self.params["SIM_ARM_DENY"] >= 0.5 and p2 != FORCE_ARM_DISARM:
                self._statustext(MavSeverity.CRITICAL, "Preflight Fail: SIM_ARM_DENY set")
                self.rejects.reject("arming denied", "SIM_ARM_DENY set")
                return MavResult.DENIED
            if not self.armed:
                self.armed = True
                self._armed_at_s = self.wall_s()
                self._taken_off_since_arming = not self.landed
                self.home = self._here()          # PX4 sets home where it arms
                self._landed_since_s = None       # COM_DISARM_LAND counts from a touchdown, not from arming
                log.info("armed")
                self._send_heartbeat()
                if self.mode == PX4_TAKEOFF and self.landed:
                    self._lift_off()              # armed in AUTO.TAKEOFF: the climb starts (PX4's `commander takeoff`)
            return MavResult.ACCEPTED
        if p1 == 0.0:
            if self.armed:
                if self.cfg.start_on_ground and not self.landed and p2 != FORCE_ARM_DISARM:
                    self._statustext(MavSeverity.CRITICAL, "Disarming denied: not landed")
                    self.rejects.reject("disarm denied", "not landed (force: param 2 = 21196)")
                    return MavResult.TEMPORARILY_REJECTED
                self.armed = False
                log.info("disarmed")
                self._send_heartbeat()
                if self.cfg.start_on_ground and not self.landed:
                    log.warning("disarmed in the air (forced): the vehicle falls to the ground")
                    self._touch_down()
            return MavResult.ACCEPTED
        return MavResult.DENIED

    def _disarm_landed(self, reason: str) -> None:
        if self.armed:
            self.armed = False
            log.info("disarmed by %s", reason)
            self._statustext(MavSeverity.INFO, f"Disarmed by {reason}")
            self._send_heartbeat()

    # ------------------------------------------------------------------ takeoff and modes
    def _takeoff(self, alt_amsl_m: float) -> MavResult:
        """MAV_CMD_NAV_TAKEOFF: AUTO.TAKEOFF to ``alt_amsl_m`` (param 7; not finite: MIS_TAKEOFF_ALT above
        where the vehicle is; never below it: "Already higher than takeoff altitude"), climbing at
        MPC_TKO_SPEED, then AUTO.LOITER there. PX4 (Commander.cpp) only changes the mode, so it is
        accepted while disarmed too; the climb starts when the vehicle is armed (navigator/takeoff.cpp)."""
        here_amsl = self.cfg.home_alt_amsl_m - self.z_m
        if math.isfinite(alt_amsl_m):
            target = float(alt_amsl_m)
        else:
            target = here_amsl + self.params["MIS_TAKEOFF_ALT"]
            self._statustext(MavSeverity.INFO, f"Using default takeoff altitude: {self.params['MIS_TAKEOFF_ALT']:.1f} m")
        if target < here_amsl:
            target = here_amsl
            self._statustext(MavSeverity.CRITICAL, "Already higher than takeoff altitude")
        self._set_mode(PX4_TAKEOFF, reason="takeoff command")
        self.z_target_m = self.cfg.home_alt_amsl_m - target
        self.hold_pos_m = self.state[0:2].copy()
        above_home = self.frame.local_z_to_world(self.home[5]) - self.z_target_m
        rad = self.params["NAV_MC_ALT_RAD"]
        self._takeoff_accept_m = above_home / 2.0 if 0.0 < above_home < rad else rad   # navigator's MissionBlock
        if self.armed:
            self._lift_off()
        return MavResult.ACCEPTED

    def _lift_off(self) -> None:
        if self.landed:
            self.landed = False
            self._landed_since_s = None
            self.plant.states[0, 2:4] = 0.0
            self.plant.acc_flown_m_s2 = np.zeros((1, 2))   # level on the ground: no tilt to carry into the air
            self.applied_acc_m_s2 = np.zeros(2)     # PX4's FlightTaskAuto::reActivate on the ground: acceleration 0
            self.hold_pos_m = self.state[0:2].copy()
            log.info("lift-off")
        self._taken_off_since_arming = self._taken_off_since_arming or self.armed
        self.flying = True
        self._vert_wall_s = self.wall_s()

    def _request_mode(self, mode: Px4Mode) -> MavResult:
        if mode.main_mode == Px4MainMode.OFFBOARD:
            mode = PX4_OFFBOARD
            if self.mode != PX4_OFFBOARD and not self._offboard_stream_ok():
                self._statustext(MavSeverity.CRITICAL, "Switching to Offboard is currently not available")
                self.rejects.reject("OFFBOARD refused", f"no offboard setpoint within COM_OF_LOSS_T = {self.params['COM_OF_LOSS_T']:g} s")
                return MavResult.TEMPORARILY_REJECTED
        elif mode == PX4_TAKEOFF:
            return self._takeoff(math.nan)
        elif mode.main_mode == Px4MainMode.AUTO and mode.sub_mode in (0, PX4_HOLD.sub_mode):
            mode = PX4_HOLD
        elif mode not in (PX4_LAND, PX4_POSCTL):
            self.rejects.reject("unsupported mode", f"mode {mode} not supported by the mock")
            return MavResult.TEMPORARILY_REJECTED
        self._set_mode(mode, reason="commanded")
        return MavResult.ACCEPTED

    def _set_mode(self, mode: Px4Mode, reason: str, keep_targets: bool = False) -> None:
        """Enter ``mode``. Hold holds at PX4's braking stop ahead (``plant.braking_stop_m``), Position follows PX4's
        braking velocity setpoint and holds where it stops (``plant.position_brake_path_m``), Land where it begins (PX4's land item has no
        position: ``FlightTaskAuto`` locks the current one); landed, every mode holds where it is. Altitude: the
        one where the mode begins, unless ``keep_targets`` (AUTO.LOITER after a takeoff keeps the takeoff's)."""
        if mode == self.mode:
            return
        log.info("mode %s -> %s (%s)", self.mode, mode, reason)
        self.mode = mode
        self.posctl_path = None
        if mode == PX4_OFFBOARD:
            if not self.landed:
                self.flying = True
            self._last_sp_sim_s = self.sim_time_s()
        elif (mode in HOLD_LIKE or mode == PX4_LAND) and not keep_targets:
            if mode == PX4_HOLD and not self.landed:
                # PX4 (multicopter): the loiter point is the braking stop ahead, not the position the hold began at
                # (navigator's calculate_breaking_stop: "otherwise the vehicle will overshoot and go back")
                self.hold_pos_m = braking_stop_m(self.plant.states, self.params["MPC_ACC_HOR"])[0]
            elif mode == PX4_POSCTL and not self.landed:
                # PX4 Position mode, sticks centred: the vehicle follows a velocity setpoint braking from its current
                # velocity, and the position locks where that reaches zero (StickAccelerationXY)
                path = position_brake_path_m(self.plant.states[0], self.params["MPC_ACC_HOR"], self.params["MPC_VEL_MANUAL"],
                                             POSCTL_DT_S)
                self.posctl_path = (self.sim_time_s(), path[1])
                self.hold_pos_m = path[0][-1].copy()      # the setpoint's stop, until the lock (vehicle._current_acc_m_s2)
            else:
                self.hold_pos_m = self.state[0:2].copy()
            self.z_target_m = self.z_m
        self._vert_wall_s = self.wall_s()
        self._send_heartbeat()

    def _on_set_mode_msg(self, m: SetMode) -> None:
        if m.target_system not in (0, self.sysid):
            self.rejects.reject("SET_MODE for another system", f"target_system {m.target_system}")
            return
        if not m.base_mode & MavModeFlag.CUSTOM_MODE_ENABLED:
            self.rejects.reject("SET_MODE without custom mode", f"base_mode {m.base_mode}")
            return
        self._request_mode(Px4Mode.from_custom_mode(m.custom_mode))

    # ------------------------------------------------------------------ failsafe and the ground, every tick
    def _offboard_loss_tick(self) -> None:
        """COM_OF_LOSS_T without a setpoint in OFFBOARD: the COM_OBL_RC_ACT failsafe. PX4's default (0,
        Position mode) needs RC; without it the failsafe framework falls through Altitude and Stabilized
        to Hold (commander/failsafe/framework.cpp), so the mock flies Hold for every value but 4 (Land)."""
        if self.mode != PX4_OFFBOARD or self.sim_time_s() - self._last_sp_sim_s <= self.params["COM_OF_LOSS_T"]:
            return
        act = int(self.params["COM_OBL_RC_ACT"])
        name = OBL_ACTIONS.get(act, "Hold")
        self._statustext(MavSeverity.WARNING, f"Failsafe: offboard setpoints lost, {name}")
        log.warning("offboard setpoint stream lost for > COM_OF_LOSS_T = %g s: failsafe to %s (COM_OBL_RC_ACT %d)",
                    self.params["COM_OF_LOSS_T"], name.upper(), act)
        self._set_mode(PX4_LAND if name == "Land" else PX4_HOLD, reason="offboard loss failsafe")

    def _ground_tick(self) -> None:
        """The AUTO modes' vertical motion in lockstep (on the wall clock, the horizontal plant frozen:
        lockstep time advances only with OFFBOARD setpoints); PX4's auto-disarm (Commander.cpp
        ``handleAutoDisarm``): COM_DISARM_LAND after a touchdown if the vehicle took off since arming,
        COM_DISARM_PRFLT after arming if it did not (ground start; <= 0 disables either); OFFBOARD on
        the ground lifts off only for a setpoint that asks to climb."""
        now = self.wall_s()
        if self.cfg.lockstep and self._auto_vertical_pending():
            h = self.cfg.physics_dt_s
            while self._vert_wall_s + h <= now:
                self._vertical(h)
                self._vert_wall_s += h
        else:
            self._vert_wall_s = now
        if self.armed and self.cfg.start_on_ground:
            if self._taken_off_since_arming:
                t = self.params["COM_DISARM_LAND"]
                if self.landed and t > 0 and self._landed_since_s is not None and now - self._landed_since_s >= t:
                    self._disarm_landed("auto disarm on land")
            else:
                t = self.params["COM_DISARM_PRFLT"]
                if t > 0 and now - self._armed_at_s >= t:
                    self._disarm_landed("auto preflight disarming")
        if self.landed and self.mode == PX4_OFFBOARD and self.armed and self._wants_climb():
            self._lift_off()            # mc_pos_control: want_takeoff in OFFBOARD

    def _auto_vertical_pending(self) -> bool:
        """Lockstep: an AUTO mode moves the vehicle vertically (takeoff, land, a hold still converging)."""
        if not self.armed or self.landed or self.mode == PX4_OFFBOARD:
            return False
        return self.mode in (PX4_TAKEOFF, PX4_LAND) or self.z_m != self.z_target_m or self.vz_m_s != 0.0

    def _wants_climb(self) -> bool:
        """MulticopterPositionControl, OFFBOARD: want_takeoff if the setpoint's z is above the vehicle,
        its vz < 0 or its az < 0."""
        z_sp, vz_sp, az_sp = self._z_setpoint_world()
        return (z_sp is not None and z_sp < self.z_m) or (vz_sp is not None and vz_sp < 0.0) or (az_sp is not None and az_sp < 0.0)

    # ------------------------------------------------------------------ the vertical axis
    def _z_setpoint_world(self) -> tuple[float | None, float | None, float | None]:
        """(z, vz, az) the OFFBOARD setpoint asks for (z in the world frame), None where it has no such term;
        all None for a setpoint PX4's position controller refuses (it stops: ``_vertical``)."""
        sp = self.setpoint
        if sp is None or not self._setpoint_flyable:
            return None, None, None
        m = sp.type_mask
        z = None if m & _Z_IGNORE or sp.coordinate_frame != MavFrame.LOCAL_NED else self.frame.local_z_to_world(float(sp.z_m))
        vz = None if m & _VZ_IGNORE else float(sp.vz_m_s)
        az = None if m & _AZ_IGNORE else float(sp.afz_m_s2)
        return z, vz, az

    def _vertical(self, dt_s: float) -> None:
        """z over ``dt_s`` in the current mode (``vertical_step``); touchdown, the end of a takeoff."""
        if self.landed:
            self.vz_m_s = 0.0               # on the ground until a takeoff or a climbing setpoint lifts it off
            return
        p = self.params
        kw = dict(z_p_per_s=p["MPC_Z_P"], vel_p_per_s=p["MPC_Z_VEL_P_ACC"], vel_max_up_m_s=p["MPC_Z_VEL_MAX_UP"],
                  vel_max_dn_m_s=p["MPC_Z_VEL_MAX_DN"])
        mode = self.mode
        if mode == PX4_OFFBOARD:
            z_sp, vz_sp, az_sp = self._z_setpoint_world()
            if not self._setpoint_flyable or self.setpoint is None:
                vz_sp = 0.0                 # PX4's "stop and wait"
            if z_sp is None and vz_sp is None and not az_sp:
                self.vz_m_s = 0.0           # acceleration-only with az = 0: the mock holds z (optimistic: PX4 hovers on its
                return                      # thrust estimate with no altitude feedback and drifts); as before issue 19
            z, vz = vertical_step(self.z_m, self.vz_m_s, dt_s, z_sp_m=z_sp, vz_sp_m_s=vz_sp, az_ff_m_s2=az_sp, **kw)
        elif mode == PX4_LAND:
            z, vz = vertical_step(self.z_m, self.vz_m_s, dt_s, vz_sp_m_s=p["MPC_LAND_SPEED"], **kw)
        elif mode == PX4_TAKEOFF:
            kw["vel_max_up_m_s"] = p["MPC_TKO_SPEED"]
            z, vz = vertical_step(self.z_m, self.vz_m_s, dt_s, z_sp_m=self.z_target_m, **kw)
        else:                               # Hold, Position: the altitude where they began (or the takeoff's)
            if self.z_m == self.z_target_m and self.vz_m_s == 0.0:
                return
            z, vz = vertical_step(self.z_m, self.vz_m_s, dt_s, z_sp_m=self.z_target_m, **kw)
            if abs(z - self.z_target_m) < 1e-4 and abs(vz) < 1e-4:
                z, vz = self.z_target_m, 0.0  # settled (a lockstep vehicle stops waking up for it)
        if z >= 0.0 and (self.cfg.start_on_ground or mode == PX4_LAND):
            z = 0.0                         # the ground
        self.z_m, self.vz_m_s = z, vz
        if mode == PX4_TAKEOFF and self.z_m - self.z_target_m <= self._takeoff_accept_m:
            log.info("takeoff done at %.2f m above home", self.frame.local_z_to_world(self.home[5]) - self.z_m)
            self._set_mode(PX4_HOLD, reason="takeoff done", keep_targets=True)
        if self.z_m >= 0.0 and self.vz_m_s >= 0.0 and (mode == PX4_LAND or self.cfg.start_on_ground):
            self._touch_down()

    def _touch_down(self) -> None:
        self.landed = True
        self.flying = False
        self.vz_m_s = 0.0
        self.z_m = 0.0
        self.plant.states[0, 2:4] = 0.0
        self.plant.acc_flown_m_s2 = np.zeros((1, 2))       # level on the ground (the acceleration lag's state)
        self._landed_since_s = self.wall_s()
        log.info("landed")
        if not self.cfg.start_on_ground:
            self._disarm_landed("landing")      # the air start's Land, as before issue 19
