"""PX4's auto-mode trajectory and position loop, horizontal plane: how a PX4 multicopter flies Hold (and Takeoff, Land).

A port, pure Python/numpy with no I/O, of what PX4 runs in its auto modes (``FlightTaskAuto``):

- ``VelocitySmoothing`` (``src/lib/motion_planning/VelocitySmoothing.{hpp,cpp}``): one axis of a jerk-limited
  trajectory. Each cycle ``updateDurations(vel_setpoint)`` plans three phases from the current (a, v, x) to the
  velocity setpoint (T1: jerk +-j_max, T2: constant acceleration at most a_max, T3: jerk -+j_max back to zero
  acceleration, minimising the total time), ``updateTraj(dt, time_stretch)`` integrates the plan.
  ``timeSynchronization`` stretches the shorter axes to the longest one's total time (straight lines).
- ``PositionSmoothing`` (``src/lib/motion_planning/PositionSmoothing.{hpp,cpp}``): turns a target position into a
  velocity setpoint (towards the target, or an L1 point when turning, at the largest speed from which the trajectory
  can still stop there: ``TrajMath.hpp: computeMaxSpeedFromDistance``, ``TrajectoryConstraints.hpp:
  computeXYSpeedFromWaypoints``, capped at the cruise speed) and smooths it with one ``VelocitySmoothing`` per axis;
  the trajectory's clock slows down while the vehicle lags behind it (``time_stretch``, MPC_XY_ERR_MAX).
- ``FlightTaskAuto`` (``src/modules/flight_mode_manager/tasks/Auto/FlightTaskAuto.cpp``): ``activate`` resets the
  smoothing to the last setpoint (NaN entries replaced by the vehicle's position and velocity, acceleration by 0),
  ``_updateTrajConstraints`` sets MPC_ACC_HOR, MPC_XY_VEL_MAX, MPC_JERK_AUTO, MPC_XY_ERR_MAX, MPC_XY_TRAJ_P, the
  cruise speed (MPC_XY_CRUISE for a loiter item without a planned speed, capped at MPC_XY_VEL_MAX) and the
  acceptance radius (NAV_ACC_RAD), ``_generateSetpoints`` calls ``generateSetpoints`` with the triplet
  (previous, target, next) and uses the trajectory's position, velocity and acceleration as the setpoints.
- ``PositionControl`` (``src/modules/mc_pos_control/PositionControl/PositionControl.cpp``, ``_positionControl``,
  ``_velocityControl``): P on position (MPC_XY_P) added to the velocity feed-forward, the velocity limited to
  MPC_XY_VEL_MAX (``ControlMath::constrainXY``, the position part first); PID on velocity (MPC_XY_VEL_P_ACC,
  MPC_XY_VEL_I_ACC on the integral, MPC_XY_VEL_D_ACC on the measured velocity derivative) added to the acceleration
  feed-forward; the horizontal integrator's tracking anti-windup (gain 2 / MPC_XY_VEL_P_ACC on what saturation cut).

Versions read (the stored PX4 source of the project's reference library; PX4 main as of 2024-2025): VelocitySmoothing
.hpp/.cpp at 1e944a5a / b4948814, PositionSmoothing.cpp at 000f5fdb (per-axis time stretch; XY is the same as at
09937579 bar an MPC_XY_ERR_MAX > FLT_EPSILON guard), PositionSmoothing.hpp at 1e944a5a, TrajMath.hpp at 13012ce4
(``computeMaxSpeedFromDistance`` returns at least the final speed), TrajectoryConstraints.hpp at 01486656,
FlightTaskAuto.cpp at e21b963f, FlightTask.cpp at 0102713e, PositionControl.cpp at fa3a14d9, parameter defaults from
multicopter_autonomous_params.yaml, multicopter_position_control_gain_params.yaml and
multicopter_position_control_limits_params.yaml, NAV_ACC_RAD from navigator_params.c (10 m).

What the mock's model needs and what it leaves out (the mock is 2-D horizontal with its own altitude loop):

- XY only. PX4 synchronises X, Y and Z (``timeSynchronization`` over three axes); in Hold the altitude target is the
  altitude where Hold began, the Z trajectory has (to within the altitude loop's noise) nothing to do, so its total
  time is 0 and XY-only synchronisation is the same.
- The triplet is the loiter item's: previous = the vehicle's position when Hold began (navigator sends no valid
  previous item, ``_evaluateTriplets`` uses the position), target = next = the Hold point. ``_getCurrentState`` /
  ``_updateInternalWaypoints`` are not ported: they can only move the previous waypoint, which enters through the L1
  point, which is used only while ``_isTurning``, which needs the target farther than NAV_ACC_RAD (10 m); a Hold
  point is the braking stop, ~5 m ahead at 4 m/s. Yaw, weather vane, obstacle avoidance, emergency braking (Z),
  EKF reset handlers, landing gear: not modelled.
- The first update after ``activate``: ``FlightModeManager::switchTask`` constructs the new task and calls its
  ``updateInitialize`` (which stamps ``_time_stamp_last``) and ``activate``; the first ``update`` follows in the same
  cycle, so its ``_deltatime`` is microseconds, not 0. A new ``VelocitySmoothing`` has T1 = T2 = T3 = 0, so that
  first ``updateTraj(dt > 0)`` ends in its zero-acceleration phase: the trajectory drops the acceleration it was
  reset to (the last setpoint's) at once, and its acceleration feed-forward starts from 0 (then rises at most
  MPC_JERK_AUTO). Ported as is (``first_update_dt_s``, 1 us; 0 would keep the reset acceleration: the difference
  is measured in docs/default_controller.md). It matters only between two flight tasks: from Offboard, where
  ``start_flight_task`` runs none, ``switchTask`` hands ``activate`` an empty (NaN) setpoint, so the reset
  acceleration is 0 anyway.
- Not ported: ``PositionControl`` keeps its velocity integrator across mode switches (reset only while landed; frozen
  in Offboard, whose velocity setpoint is NaN); each activation here starts it from 0.
- The position controller. What the mock's plant (eq. 9) needs to be tracked under wind is the velocity PID with its
  integrator (the drag c0 (v - v_o) is an unmodelled disturbance to PX4's loop, as wind is; the integrator removes
  its steady-state error), so ``_positionControl`` and the horizontal part of ``_velocityControl`` are ported whole.
  The thrust and tilt stage (``_accelerationControl``: hover thrust, MPC_TILTMAX_AIR, the vertical priority) is
  replaced by the airframe's horizontal acceleration limit (the plant's ``acc_limit_m_s2``, the mock's
  MPC_ACC_HOR_MAX): the anti-windup sees the acceleration that limit lets through, as PX4's sees the thrust
  the tilt and thrust limits let through. The velocity derivative (PX4: the derivative of the low-passed velocity
  estimate, low-passed, MPC_VELD_LP) is the finite difference of the velocity over the last physics sub-step (at
  activation: the acceleration flown before); the velocity estimate is the true velocity (no EKF, no MPC_VEL_LP).
- Rates. PX4 runs the flight task and the position controller at the local-position rate (~50-100 Hz); the mock's
  plant holds an acceleration for a physics sub-step (0.1 s), so the controller runs once per sub-step, on the state
  at its start. The trajectory can be integrated on a finer internal step (``internal_dt_s``: that many
  ``updateTraj``/``updateDurations`` cycles per sub-step, the drone's position held), as PX4's 50 Hz task would.
- Arithmetic is float64 (PX4: float32).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

__all__ = [
    "FLT_EPSILON",
    "VelocitySmoothing",
    "PositionSmoothing",
    "AutoParams",
    "FlightTaskAutoXY",
    "PositionControlXY",
    "Px4AutoXY",
    "compute_max_speed_from_distance",
    "compute_max_speed_in_waypoint",
    "compute_braking_distance_from_velocity",
    "compute_xy_speed_from_waypoints",
]

FLT_EPSILON = 1.1920929e-07
"""float.h's FLT_EPSILON: PX4's thresholds use it."""


def _sign(x: float) -> int:
    """matrix::sign: -1, 0 or 1."""
    return (0.0 < x) - (x < 0.0)


def _constrain(x: float, lo: float, hi: float) -> float:
    return lo if x < lo else hi if x > hi else x


# ---------------------------------------------------------------------------------------------- TrajMath.hpp
def compute_max_speed_from_distance(jerk_m_s3: float, accel_m_s2: float, braking_distance_m: float,
                                    final_speed_m_s: float) -> float:
    """``math::trajectory::computeMaxSpeedFromDistance``: the largest speed from which a constant-deceleration
    profile with a delay of 2 accel / jerk still reaches ``final_speed_m_s`` within ``braking_distance_m``:
    v^2 + (4 a^2 / j) v - (2 a d + v_f^2) = 0, at least ``final_speed_m_s``."""
    with np.errstate(divide="ignore", invalid="ignore"):      # C float semantics: 0 / 0 is NaN, sqrtf(< 0) NaN
        b = float(np.float64(4.0 * accel_m_s2 * accel_m_s2) / np.float64(jerk_m_s3))
        c = -2.0 * accel_m_s2 * braking_distance_m - final_speed_m_s * final_speed_m_s
        max_speed = 0.5 * (-b + float(np.sqrt(np.float64(b * b - 4.0 * c))))
    return final_speed_m_s if math.isnan(max_speed) else max(max_speed, final_speed_m_s)      # fmaxf


def compute_max_speed_in_waypoint(alpha_rad: float, accel_m_s2: float, d_m: float) -> float:
    """``math::trajectory::computeMaxSpeedInWaypoint``: sqrt(a d tan(alpha / 2))."""
    return math.sqrt(accel_m_s2 * d_m * math.tan(alpha_rad / 2.0))


def compute_braking_distance_from_velocity(velocity_m_s: float, jerk_m_s3: float, accel_m_s2: float,
                                           accel_delay_max_m_s2: float) -> float:
    """``math::trajectory::computeBrakingDistanceFromVelocity``: v (v / (2 a) + a_delay / j) (navigator's
    ``calculate_breaking_stop`` with a_delay = 0.6 MPC_JERK_AUTO; ``plant.braking_stop_m``)."""
    return velocity_m_s * (velocity_m_s / (2.0 * accel_m_s2) + accel_delay_max_m_s2 / jerk_m_s3)


# ---------------------------------------------------------------------------------------------- VelocitySmoothing
class VelocitySmoothing:
    """One axis of PX4's jerk-limited trajectory (``VelocitySmoothing``; names as PX4's, units SI).

    State ``_state`` = (j, a, v, x): jerk m/s^3, acceleration m/s^2, velocity m/s, position m. Constraints
    ``_max_jerk`` (MPC_JERK_AUTO), ``_max_accel`` (MPC_ACC_HOR), ``_max_vel`` (MPC_XY_VEL_MAX). A new object, as
    PX4's, has T1 = T2 = T3 = 0, direction 0, local time 0; ``reset`` sets only the state."""

    __slots__ = ("_vel_sp", "_max_jerk", "_max_accel", "_max_vel", "_state", "_direction", "_state_init",
                 "_T1", "_T2", "_T3", "_local_time")

    def __init__(self, initial_accel: float = 0.0, initial_vel: float = 0.0, initial_pos: float = 0.0) -> None:
        self._vel_sp = 0.0
        self._max_jerk = 0.0
        self._max_accel = 0.0
        self._max_vel = 0.0
        self._direction = 0
        self._T1 = self._T2 = self._T3 = 0.0
        self._local_time = 0.0
        self._state = (0.0, 0.0, 0.0, 0.0)
        self._state_init = self._state
        self.reset(initial_accel, initial_vel, initial_pos)

    def reset(self, accel: float, vel: float, pos: float) -> None:
        """``reset``: jerk 0, the given acceleration, velocity and position (also the initial conditions)."""
        self._state = (0.0, float(accel), float(vel), float(pos))
        self._state_init = self._state

    # getters / setters (PX4's)
    def getMaxJerk(self) -> float: return self._max_jerk
    def setMaxJerk(self, max_jerk: float) -> None: self._max_jerk = float(max_jerk)
    def getMaxAccel(self) -> float: return self._max_accel
    def setMaxAccel(self, max_accel: float) -> None: self._max_accel = float(max_accel)
    def getMaxVel(self) -> float: return self._max_vel
    def setMaxVel(self, max_vel: float) -> None: self._max_vel = float(max_vel)
    def getCurrentJerk(self) -> float: return self._state[0]
    def getCurrentAcceleration(self) -> float: return self._state[1]
    def getCurrentVelocity(self) -> float: return self._state[2]
    def getCurrentPosition(self) -> float: return self._state[3]
    def getT1(self) -> float: return self._T1
    def getT2(self) -> float: return self._T2
    def getT3(self) -> float: return self._T3
    def getTotalTime(self) -> float: return self._T1 + self._T2 + self._T3

    def setCurrentAcceleration(self, accel: float) -> None:
        j, _, v, x = self._state
        self._state = (j, float(accel), v, x)
        ji, _, vi, xi = self._state_init
        self._state_init = (ji, float(accel), vi, xi)

    def setCurrentVelocity(self, vel: float) -> None:
        j, a, _, x = self._state
        self._state = (j, a, float(vel), x)
        ji, ai, _, xi = self._state_init
        self._state_init = (ji, ai, float(vel), xi)

    def setCurrentPosition(self, pos: float) -> None:
        j, a, v, _ = self._state
        self._state = (j, a, v, float(pos))
        ji, ai, vi, _ = self._state_init
        self._state_init = (ji, ai, vi, float(pos))

    # durations
    @staticmethod
    def _saturateT1ForAccel(a0: float, j_max: float, T1: float, a_max: float) -> float:
        accel_T1 = a0 + j_max * T1
        if accel_T1 > a_max:
            return (a_max - a0) / j_max
        if accel_T1 < -a_max:
            return (-a_max - a0) / j_max
        return T1

    def _computeT1(self, a0: float, v3: float, j_max: float, a_max: float) -> float:
        """Increasing-acceleration time minimising the total time."""
        delta = 2.0 * a0 * a0 + 4.0 * j_max * v3
        if delta < 0.0:
            return 0.0                                  # solution is not real
        sqrt_delta = math.sqrt(delta)
        T1_plus = (-a0 + 0.5 * sqrt_delta) / j_max
        T1_minus = (-a0 - 0.5 * sqrt_delta) / j_max
        T3_plus = a0 / j_max + T1_plus
        T3_minus = a0 / j_max + T1_minus
        T1 = 0.0
        if T1_plus >= 0.0 and T3_plus >= 0.0:
            T1 = T1_plus
        elif T1_minus >= 0.0 and T3_minus >= 0.0:
            T1 = T1_minus
        T1 = self._saturateT1ForAccel(a0, j_max, T1, a_max)
        return max(T1, 0.0)

    def _computeT1GivenTotalTime(self, T123: float, a0: float, v3: float, j_max: float, a_max: float) -> float:
        """Increasing-acceleration time with the total time T123 given (PX4's second ``computeT1``)."""
        a = -j_max
        b = j_max * T123 - a0
        delta = T123 * T123 * j_max * j_max + 2.0 * T123 * a0 * j_max - a0 * a0 - 4.0 * j_max * v3
        if delta < 0.0:
            return 0.0                                  # solution is not real
        sqrt_delta = math.sqrt(delta)
        denominator_inv = 1.0 / (2.0 * a)
        T1_plus = max((-b + sqrt_delta) * denominator_inv, 0.0)
        T1_minus = max((-b - sqrt_delta) * denominator_inv, 0.0)
        T3_plus = a0 / j_max + T1_plus
        T3_minus = a0 / j_max + T1_minus
        T1 = 0.0
        if T1_plus >= 0.0 and T3_plus >= 0.0 and T1_plus + T3_plus <= T123:
            T1 = T1_plus
        elif T1_minus >= 0.0 and T3_minus >= 0.0 and T1_minus + T3_minus <= T123:
            T1 = T1_minus
        return self._saturateT1ForAccel(a0, j_max, T1, a_max)

    @staticmethod
    def _computeT2(T1: float, T3: float, a0: float, v3: float, j_max: float) -> float:
        T2 = 0.0
        den = a0 + j_max * T1
        if abs(den) > FLT_EPSILON:
            T2 = (-0.5 * T1 * T1 * j_max - T1 * T3 * j_max - T1 * a0 + 0.5 * T3 * T3 * j_max - T3 * a0 + v3) / den
        return max(T2, 0.0)

    @staticmethod
    def _computeT3(T1: float, a0: float, j_max: float) -> float:
        return max(a0 / j_max + T1, 0.0)

    def updateDurations(self, vel_setpoint: float) -> None:
        """``updateDurations``: plan T1, T2, T3 from the current state to ``vel_setpoint`` (constrained to
        +-``_max_vel``); restarts the local time."""
        self._vel_sp = _constrain(float(vel_setpoint), -self._max_vel, self._max_vel)
        self._local_time = 0.0
        self._state_init = self._state
        self._direction = self._computeDirection()
        self._updateDurationsMinimizeTotalTime()

    def _computeDirection(self) -> int:
        vel_zero_acc = self._computeVelAtZeroAcc()
        direction = _sign(self._vel_sp - vel_zero_acc)
        if direction == 0:
            direction = _sign(self._state[1])   # braking now gives exactly the setpoint at zero acceleration: brake
        return direction

    def _computeVelAtZeroAcc(self) -> float:
        _, a, v, _ = self._state
        vel_zero_acc = v
        if abs(a) > FLT_EPSILON:
            j_zero_acc = -_sign(a) * self._max_jerk
            t_zero_acc = -a / j_zero_acc
            vel_zero_acc = v + a * t_zero_acc + 0.5 * j_zero_acc * t_zero_acc * t_zero_acc
        return vel_zero_acc

    def _updateDurationsMinimizeTotalTime(self) -> None:
        jerk_max_T1 = self._direction * self._max_jerk
        a = self._state[1]
        delta_v = self._vel_sp - self._state[2]
        if abs(jerk_max_T1) > FLT_EPSILON:
            self._T1 = self._computeT1(a, delta_v, jerk_max_T1, self._max_accel)
            self._T3 = self._computeT3(self._T1, a, jerk_max_T1)
            self._T2 = self._computeT2(self._T1, self._T3, a, delta_v, jerk_max_T1)
        else:
            self._T1 = self._T2 = self._T3 = 0.0

    def _updateDurationsGivenTotalTime(self, T123: float) -> None:
        jerk_max_T1 = self._direction * self._max_jerk
        a = self._state[1]
        delta_v = self._vel_sp - self._state[2]
        if abs(jerk_max_T1) > FLT_EPSILON:
            self._T1 = self._computeT1GivenTotalTime(T123, a, delta_v, jerk_max_T1, self._max_accel)
            self._T3 = self._computeT3(self._T1, a, jerk_max_T1)
            self._T2 = max(T123 - self._T1 - self._T3, 0.0)
        else:
            self._T1 = self._T2 = self._T3 = 0.0

    # integration
    @staticmethod
    def _evaluatePoly(j: float, a0: float, v0: float, x0: float, t: float, d: float) -> tuple[float, float, float, float]:
        jt = d * j
        t2 = t * t
        t3 = t2 * t
        return (jt, a0 + jt * t, v0 + a0 * t + 0.5 * jt * t2, x0 + v0 * t + 0.5 * a0 * t2 + 1.0 / 6.0 * jt * t3)

    def updateTraj(self, dt: float, time_stretch: float = 1.0) -> None:
        """``updateTraj``: the state at local time (+= dt x time_stretch) of the plan: T1 at jerk direction x j_max,
        T2 at constant acceleration, T3 at -direction x j_max, then constant velocity with zero acceleration."""
        self._local_time += dt * time_stretch
        t_remain = self._local_time
        _, a_i, v_i, x_i = self._state_init
        t1 = min(t_remain, self._T1)
        s = self._evaluatePoly(self._max_jerk, a_i, v_i, x_i, t1, self._direction)
        t_remain -= t1
        if t_remain > 0.0:
            t2 = min(t_remain, self._T2)
            s = self._evaluatePoly(0.0, s[1], s[2], s[3], t2, 0.0)
            t_remain -= t2
        if t_remain > 0.0:
            t3 = min(t_remain, self._T3)
            s = self._evaluatePoly(self._max_jerk, s[1], s[2], s[3], t3, -self._direction)
            t_remain -= t3
        if t_remain > 0.0:
            s = self._evaluatePoly(0.0, 0.0, s[2], s[3], t_remain, 0.0)
        self._state = s

    @staticmethod
    def timeSynchronization(traj: list["VelocitySmoothing"]) -> None:
        """``timeSynchronization``: give every trajectory the longest one's total time (straight lines)."""
        desired_time = 0.0
        longest = 0
        for i, t in enumerate(traj):
            T123 = t.getTotalTime()
            if T123 > desired_time:
                desired_time, longest = T123, i
        if desired_time > FLT_EPSILON:
            for i, t in enumerate(traj):
                if i != longest and t.getTotalTime() < desired_time:
                    t._updateDurationsGivenTotalTime(desired_time)


# ---------------------------------------------------------------------------------------------- TrajectoryConstraints
def _unit_or_zero(v: np.ndarray) -> np.ndarray:
    n = math.hypot(float(v[0]), float(v[1]))
    return v / n if n > 1e-6 else np.zeros(2)          # matrix::Vector::unit_or_zero: eps 1e-6


def compute_start_xy_speed_from_waypoints(start_m: np.ndarray, target_m: np.ndarray, next_target_m: np.ndarray,
                                          exit_speed_m_s: float, xy_accept_rad_m: float, max_acc_xy_m_s2: float,
                                          max_jerk_m_s3: float, max_speed_xy_m_s: float,
                                          max_acc_xy_radius_scale: float) -> float:
    """``math::trajectory::computeStartXYSpeedFromWaypoints`` (XY)."""
    distance_target_next = float(np.hypot(*(target_m - next_target_m)))
    target_next_different = distance_target_next > 0.001
    waypoint_overlap = distance_target_next < xy_accept_rad_m
    speed_at_target = 0.0
    if target_next_different and not waypoint_overlap:
        c = float(np.dot(_unit_or_zero(target_m - start_m), _unit_or_zero(target_m - next_target_m)))
        alpha = math.acos(_constrain(c, -1.0, 1.0))
        safe_alpha = _constrain(alpha, 0.0, math.pi - FLT_EPSILON)
        max_speed_in_turn = compute_max_speed_in_waypoint(safe_alpha, max_acc_xy_radius_scale * max_acc_xy_m_s2,
                                                          xy_accept_rad_m)
        speed_at_target = min(max_speed_in_turn, exit_speed_m_s, max_speed_xy_m_s)
    start_to_target = float(np.hypot(*(start_m - target_m)))
    max_speed = compute_max_speed_from_distance(max_jerk_m_s3, max_acc_xy_m_s2, start_to_target, speed_at_target)
    return min(max_speed_xy_m_s, max_speed)


def compute_xy_speed_from_waypoints(waypoints_m: np.ndarray, **limits: float) -> float:
    """``math::trajectory::computeXYSpeedFromWaypoints<N>``: backwards through the waypoints (N, 2), the first being
    the start; ``limits`` as ``compute_start_xy_speed_from_waypoints``'s (PX4's ``VehicleDynamicLimits``)."""
    n = len(waypoints_m)
    max_speed = 0.0
    for i in range(n - 2, -1, -1):
        max_speed = compute_start_xy_speed_from_waypoints(waypoints_m[i], waypoints_m[i + 1],
                                                          waypoints_m[min(i + 2, n - 1)], max_speed, **limits)
    return max_speed


# ---------------------------------------------------------------------------------------------- PositionSmoothing
class PositionSmoothing:
    """PX4's ``PositionSmoothing``, horizontal axes (x north, y east): two ``VelocitySmoothing``s synchronised.

    ``generateSetpoints(position_m (2,), waypoints_m (3, 2) [previous, target, next], feedforward_velocity_m_s (2,)
    (NaN: none), delta_time_s, force_zero_velocity_setpoint)`` returns a dict of (2,) arrays: jerk, acceleration,
    velocity, position, unsmoothed_velocity."""

    def __init__(self) -> None:
        self._max_allowed_horizontal_error = 0.0
        self._cruise_speed = 0.0
        self._horizontal_trajectory_gain = 0.0
        self._target_acceptance_radius = 0.0
        self._trajectory = [VelocitySmoothing(), VelocitySmoothing()]
        self._max_speed_previous = 0.0

    # setters (PX4's)
    def setMaxAllowedHorizontalError(self, error: float) -> None: self._max_allowed_horizontal_error = float(error)
    def setCruiseSpeed(self, speed: float) -> None: self._cruise_speed = float(speed)
    def setHorizontalTrajectoryGain(self, gain: float) -> None: self._horizontal_trajectory_gain = float(gain)
    def setTargetAcceptanceRadius(self, radius: float) -> None: self._target_acceptance_radius = float(radius)

    def setMaxJerkXY(self, jerk: float) -> None:
        for t in self._trajectory:
            t.setMaxJerk(jerk)

    def setMaxAccelerationXY(self, accel: float) -> None:
        for t in self._trajectory:
            t.setMaxAccel(accel)

    def setMaxVelocityXY(self, vel: float) -> None:
        for t in self._trajectory:
            t.setMaxVel(vel)

    def reset(self, acceleration: np.ndarray, velocity: np.ndarray, position: np.ndarray) -> None:
        for i, t in enumerate(self._trajectory):
            t.reset(float(acceleration[i]), float(velocity[i]), float(position[i]))

    def getCurrentPositionXY(self) -> np.ndarray:
        return np.array([t.getCurrentPosition() for t in self._trajectory])

    def getCurrentVelocityXY(self) -> np.ndarray:
        return np.array([t.getCurrentVelocity() for t in self._trajectory])

    def getCurrentAccelerationXY(self) -> np.ndarray:
        return np.array([t.getCurrentAcceleration() for t in self._trajectory])

    def generateSetpoints(self, position_m: np.ndarray, waypoints_m: np.ndarray, feedforward_velocity_m_s: np.ndarray,
                          delta_time_s: float, force_zero_velocity_setpoint: bool = False,
                          is_single_waypoint: bool = False) -> dict[str, np.ndarray]:
        """``_generateSetpoints``: the velocity setpoint towards the target (zero if forced), then the trajectory."""
        waypoints_m = np.asarray(waypoints_m, dtype=float).reshape(3, 2)
        velocity_setpoint = np.zeros(2)
        if not force_zero_velocity_setpoint:
            velocity_setpoint = self._generateVelocitySetpoint(waypoints_m, is_single_waypoint,
                                                               np.asarray(feedforward_velocity_m_s, dtype=float))
        out = {"unsmoothed_velocity": velocity_setpoint}
        out.update(self._generateTrajectory(np.asarray(position_m, dtype=float), velocity_setpoint, delta_time_s))
        return out

    def _isTurning(self, target: np.ndarray) -> bool:
        vel_traj = self.getCurrentVelocityXY()
        pos_to_target = target - self.getCurrentPositionXY()
        cos_align = float(np.dot(_unit_or_zero(vel_traj), _unit_or_zero(pos_to_target)))
        return (math.hypot(*vel_traj) > 0.2 and cos_align < 0.98
                and math.hypot(*pos_to_target) > self._target_acceptance_radius)

    def _getMaxXYSpeed(self, waypoints_m: np.ndarray) -> float:
        pos_to_waypoints = np.stack([self.getCurrentPositionXY(), waypoints_m[1], waypoints_m[2]])
        t = self._trajectory[0]
        return compute_xy_speed_from_waypoints(
            pos_to_waypoints, xy_accept_rad_m=self._target_acceptance_radius, max_acc_xy_m_s2=t.getMaxAccel(),
            max_jerk_m_s3=t.getMaxJerk(), max_speed_xy_m_s=self._cruise_speed,
            max_acc_xy_radius_scale=self._horizontal_trajectory_gain)

    def _getL1Point(self, waypoints_m: np.ndarray) -> np.ndarray:
        pos_traj = self.getCurrentPositionXY()
        u_prev_to_target = _unit_or_zero(waypoints_m[1] - waypoints_m[0])
        prev_to_pos = pos_traj - waypoints_m[0]
        closest_pt = waypoints_m[0] + u_prev_to_target * float(np.dot(prev_to_pos, u_prev_to_target))
        crosstrack_error = float(np.hypot(*(closest_pt - pos_traj)))
        l1 = max(self._target_acceptance_radius, 5.0)
        alongtrack_error = math.sqrt(l1 * l1 - crosstrack_error * crosstrack_error) if l1 > crosstrack_error else 0.0
        return closest_pt + alongtrack_error * u_prev_to_target

    def _getCrossingPoint(self, waypoints_m: np.ndarray) -> np.ndarray:
        target = waypoints_m[1]
        return target if not self._isTurning(target) else self._getL1Point(waypoints_m)

    def _generateVelocitySetpoint(self, waypoints_m: np.ndarray, is_single_waypoint: bool,
                                  feedforward_velocity_setpoint: np.ndarray) -> np.ndarray:
        """``_generateVelocitySetpoint``, its XY part: towards the crossing point at ``_getMaxXYSpeed`` (the speed held
        at ``_max_speed_previous`` while turning), added to a finite feed-forward."""
        target = waypoints_m[1]
        velocity_setpoint = feedforward_velocity_setpoint.copy()
        if not np.all(np.isfinite(target)):
            return velocity_setpoint
        pos_traj = self.getCurrentPositionXY()
        crossing_point = target if is_single_waypoint else self._getCrossingPoint(waypoints_m)
        u_pos_traj_to_dest_xy = _unit_or_zero(crossing_point - pos_traj)
        xy_speed = self._getMaxXYSpeed(waypoints_m)
        if not is_single_waypoint and self._isTurning(target):
            xy_speed = min(self._max_speed_previous, xy_speed)          # limit speed during a turn
        else:
            self._max_speed_previous = xy_speed
        vel_sp_constrained_xy = u_pos_traj_to_dest_xy * xy_speed
        for i in range(2):
            if math.isfinite(velocity_setpoint[i]):
                velocity_setpoint[i] += vel_sp_constrained_xy[i]
            else:
                velocity_setpoint[i] = vel_sp_constrained_xy[i]
        return velocity_setpoint

    def _generateTrajectory(self, position_m: np.ndarray, velocity_setpoint: np.ndarray,
                            delta_time_s: float) -> dict[str, np.ndarray]:
        """``_generateTrajectory``: advance the trajectory by delta_time x time_stretch (slowed linearly while the
        vehicle lags behind it by up to MPC_XY_ERR_MAX, not when it is ahead), read it, then plan towards
        ``velocity_setpoint`` and synchronise the axes."""
        if not np.all(np.isfinite(velocity_setpoint)):
            raise ValueError(f"velocity setpoint must be finite, got {velocity_setpoint}")
        drone_to_trajectory_xy = self.getCurrentPositionXY() - position_m
        vel_traj_xy = self.getCurrentVelocityXY()
        position_error_xy = math.hypot(*drone_to_trajectory_xy)
        along = float(np.dot(drone_to_trajectory_xy, vel_traj_xy))
        time_stretch_xy = 1.0
        if self._max_allowed_horizontal_error > FLT_EPSILON and along >= 0.0:
            time_stretch_xy = 1.0 - _constrain(position_error_xy / self._max_allowed_horizontal_error, 0.0, 1.0)
        if along < 0.0:
            time_stretch_xy = 1.0
        out = {k: np.empty(2) for k in ("jerk", "acceleration", "velocity", "position")}
        for i, t in enumerate(self._trajectory):
            t.updateTraj(delta_time_s, time_stretch_xy)
            out["jerk"][i] = t.getCurrentJerk()
            out["acceleration"][i] = t.getCurrentAcceleration()
            out["velocity"][i] = t.getCurrentVelocity()
            out["position"][i] = t.getCurrentPosition()
        for i, t in enumerate(self._trajectory):
            t.updateDurations(float(velocity_setpoint[i]))
        VelocitySmoothing.timeSynchronization(self._trajectory)
        return out


# ---------------------------------------------------------------------------------------------- parameters
@dataclass(frozen=True)
class AutoParams:
    """PX4's parameters of the auto modes' horizontal trajectory and position loop (defaults: PX4's, from the yaml
    files named in the module docstring), and the port's two choices (``first_update_dt_s``, ``internal_dt_s``)."""

    mpc_jerk_auto_m_s3: float = 4.0        # MPC_JERK_AUTO (1..80)
    mpc_acc_hor_m_s2: float = 3.0          # MPC_ACC_HOR (2..15)
    mpc_xy_cruise_m_s: float = 5.0         # MPC_XY_CRUISE (3..20): a loiter item's speed limit (no planned speed)
    mpc_xy_vel_max_m_s: float = 12.0       # MPC_XY_VEL_MAX (0..20)
    mpc_xy_err_max_m: float = 2.0          # MPC_XY_ERR_MAX (0.1..10)
    mpc_xy_traj_p: float = 0.5             # MPC_XY_TRAJ_P (0.1..1)
    nav_acc_rad_m: float = 10.0            # NAV_ACC_RAD (0.05..200): the triplet's acceptance radius
    mpc_xy_p_per_s: float = 0.95           # MPC_XY_P (0..2)
    mpc_xy_vel_p_acc_per_s: float = 1.8    # MPC_XY_VEL_P_ACC (1.2..5)
    mpc_xy_vel_i_acc_per_s2: float = 0.4   # MPC_XY_VEL_I_ACC (0..60)
    mpc_xy_vel_d_acc: float = 0.2          # MPC_XY_VEL_D_ACC (0.1..2)
    first_update_dt_s: float = 1e-6
    """The first ``_deltatime`` after ``activate``, s: the same FlightModeManager cycle (module docstring). Any value
    > 0 drops the reset acceleration as PX4 does; 0 keeps it."""
    internal_dt_s: float | None = None
    """Largest trajectory step: each physics sub-step runs ceil(h / internal_dt_s) trajectory cycles (PX4 ~0.02 s).
    None: one cycle per sub-step."""

    def __post_init__(self) -> None:
        bounds = {"mpc_jerk_auto_m_s3": (1.0, 80.0), "mpc_acc_hor_m_s2": (0.01, 15.0), "mpc_xy_cruise_m_s": (0.0, 20.0),
                  "mpc_xy_vel_max_m_s": (0.0, 20.0), "mpc_xy_err_max_m": (0.1, 10.0), "mpc_xy_traj_p": (0.1, 1.0),
                  "nav_acc_rad_m": (0.05, 200.0), "mpc_xy_p_per_s": (0.0, 2.0), "mpc_xy_vel_p_acc_per_s": (1.2, 5.0),
                  "mpc_xy_vel_i_acc_per_s2": (0.0, 60.0), "mpc_xy_vel_d_acc": (0.0, 2.0)}
        for name, (lo, hi) in bounds.items():
            v = getattr(self, name)
            if not (math.isfinite(v) and lo <= v <= hi):
                raise ValueError(f"{name} must be in [{lo}, {hi}], got {v}")
        if not (math.isfinite(self.first_update_dt_s) and 0.0 <= self.first_update_dt_s <= 0.5):
            raise ValueError(f"first_update_dt_s must be in [0, 0.5], got {self.first_update_dt_s}")
        if self.internal_dt_s is not None and not (math.isfinite(self.internal_dt_s) and self.internal_dt_s > 0):
            raise ValueError(f"internal_dt_s must be None or finite and > 0, got {self.internal_dt_s}")

    def with_(self, **kw) -> "AutoParams":
        return replace(self, **kw)


# ---------------------------------------------------------------------------------------------- FlightTaskAuto
class FlightTaskAutoXY:
    """PX4's ``FlightTaskAuto`` for a loiter item, horizontal part: ``activate``, ``_updateTrajConstraints``,
    ``_generateSetpoints`` (module docstring: what is not ported)."""

    def __init__(self, params: AutoParams) -> None:
        self.params = params
        self._position_smoothing = PositionSmoothing()
        self._waypoints_m = np.full((3, 2), np.nan)
        self._first = True

    def _updateTrajConstraints(self) -> None:
        p, ps = self.params, self._position_smoothing
        ps.setMaxAllowedHorizontalError(p.mpc_xy_err_max_m)
        ps.setCruiseSpeed(min(p.mpc_xy_cruise_m_s, p.mpc_xy_vel_max_m_s))   # _evaluateTriplets' _mc_cruise_speed
        ps.setHorizontalTrajectoryGain(p.mpc_xy_traj_p)
        ps.setTargetAcceptanceRadius(p.nav_acc_rad_m)
        ps.setMaxAccelerationXY(p.mpc_acc_hor_m_s2)
        ps.setMaxVelocityXY(p.mpc_xy_vel_max_m_s)
        ps.setMaxJerkXY(p.mpc_jerk_auto_m_s3)

    def activate(self, position_m: np.ndarray, velocity_m_s: np.ndarray, target_m: np.ndarray,
                 last_acceleration_m_s2: np.ndarray, last_velocity_m_s: np.ndarray | None = None,
                 last_position_m: np.ndarray | None = None) -> None:
        """``activate(last_setpoint)``: reset the smoothing to the last setpoint, a NaN (or absent) position or
        velocity replaced by the vehicle's, a NaN acceleration by 0; the triplet: previous = the position now,
        target = next = ``target_m`` (a loiter item)."""
        pos = np.asarray(position_m, dtype=float).reshape(2)
        vel = np.asarray(velocity_m_s, dtype=float).reshape(2)
        pos_prev = pos.copy() if last_position_m is None else np.where(np.isfinite(last_position_m), last_position_m, pos)
        vel_prev = vel.copy() if last_velocity_m_s is None else np.where(np.isfinite(last_velocity_m_s), last_velocity_m_s, vel)
        acc_prev = np.asarray(last_acceleration_m_s2, dtype=float).reshape(2)
        acc_prev = np.where(np.isfinite(acc_prev), acc_prev, 0.0)
        self._position_smoothing = PositionSmoothing()          # the mode switch constructs a new task
        self._position_smoothing.reset(acc_prev, vel_prev, pos_prev)
        self._updateTrajConstraints()
        target = np.asarray(target_m, dtype=float).reshape(2)
        self._waypoints_m = np.stack([pos, target, target])
        self._first = True

    def update(self, position_m: np.ndarray, dt_s: float) -> dict[str, np.ndarray]:
        """One ``update`` (``_generateSetpoints``) ``dt_s`` after the previous one (the first after ``activate``:
        ``first_update_dt_s`` after it, whatever ``dt_s``). Returns the setpoints (dict of (2,) arrays)."""
        if self._first:
            dt_s = self.params.first_update_dt_s
        self._first = False
        self._updateTrajConstraints()
        return self._position_smoothing.generateSetpoints(position_m, self._waypoints_m, np.full(2, np.nan), dt_s)


# ---------------------------------------------------------------------------------------------- PositionControl
class PositionControlXY:
    """PX4's ``PositionControl``, horizontal part (module docstring): ``update`` returns the acceleration setpoint
    (2,) before the airframe's limit; ``limit_acc_m_s2`` then tells the anti-windup what that limit let through."""

    def __init__(self, params: AutoParams) -> None:
        self.params = params
        self._vel_int = np.zeros(2)

    def reset(self) -> None:
        self._vel_int = np.zeros(2)

    def update(self, pos_sp_m: np.ndarray, vel_sp_m_s: np.ndarray, acc_sp_m_s2: np.ndarray, pos_m: np.ndarray,
               vel_m_s: np.ndarray, vel_dot_m_s2: np.ndarray, acc_limit_m_s2: float, dt_s: float) -> np.ndarray:
        """``_positionControl`` then ``_velocityControl`` (XY): vel_sp += MPC_XY_P (pos_sp - pos), constrained to
        MPC_XY_VEL_MAX with the position part first (``ControlMath::constrainXY``); acc_sp += MPC_XY_VEL_P_ACC
        (vel_sp - vel) + vel_int - MPC_XY_VEL_D_ACC vel_dot; the integral grows by MPC_XY_VEL_I_ACC x (vel_error -
        2 / MPC_XY_VEL_P_ACC x (acc_sp - its limited value)) dt (tracking anti-windup). Returns acc_sp (2,)."""
        p = self.params
        vel_sp_position = (np.asarray(pos_sp_m, dtype=float) - pos_m) * p.mpc_xy_p_per_s
        vel_sp_position = np.where(np.isfinite(vel_sp_position), vel_sp_position, 0.0)
        vel_sp = np.asarray(vel_sp_m_s, dtype=float)
        vel_sp = np.where(np.isfinite(vel_sp), vel_sp + vel_sp_position, vel_sp_position)
        vel_sp = _constrain_xy(vel_sp_position, vel_sp - vel_sp_position, p.mpc_xy_vel_max_m_s)
        vel_error = vel_sp - vel_m_s
        acc_sp_velocity = vel_error * p.mpc_xy_vel_p_acc_per_s + self._vel_int - np.asarray(vel_dot_m_s2) * p.mpc_xy_vel_d_acc
        acc_ff = np.asarray(acc_sp_m_s2, dtype=float)
        acc_sp = np.where(np.isfinite(acc_ff), acc_ff + acc_sp_velocity, acc_sp_velocity)
        norm = math.hypot(*acc_sp)
        acc_limited = acc_sp * (acc_limit_m_s2 / norm) if norm > acc_limit_m_s2 else acc_sp
        arw_gain = 2.0 / p.mpc_xy_vel_p_acc_per_s
        vel_error = vel_error - arw_gain * (acc_sp - acc_limited)
        vel_error = np.where(np.isfinite(vel_error), vel_error, 0.0)
        self._vel_int = self._vel_int + vel_error * p.mpc_xy_vel_i_acc_per_s2 * dt_s
        return acc_sp


def _constrain_xy(v0: np.ndarray, v1: np.ndarray, max_norm: float) -> np.ndarray:
    """``ControlMath::constrainXY``: v0 + v1 limited to ``max_norm``, v0 (the position loop's part) kept first: if
    |v0 + v1| <= max: v0 + v1; if |v0| >= max (or v1 ~ v0): v0 scaled to max; if v0 ~ 0: v1 scaled to max; else
    v0 + s u1 (u1 = v1 / |v1|) with s >= 0 solving |v0 + s u1| = max."""
    total = v0 + v1
    if math.hypot(*total) <= max_norm:
        return total
    n0 = math.hypot(*v0)
    if n0 >= max_norm:
        return v0 / n0 * max_norm
    if math.hypot(*(v1 - v0)) < 0.001:
        return v0 / n0 * max_norm
    n1 = math.hypot(*v1)
    if n0 < 0.001:
        return v1 / n1 * max_norm
    u1 = v1 / n1
    m = float(np.dot(u1, v0))
    c = n0 * n0 - max_norm * max_norm
    s = -m + math.sqrt(m * m - c)
    return v0 + u1 * s


# ---------------------------------------------------------------------------------------------- the model
class Px4AutoXY:
    """One vehicle's horizontal auto-mode flight, PX4 style: ``FlightTaskAutoXY`` (the smoothed setpoints) tracked by
    ``PositionControlXY``, once per physics sub-step, usable by the mock vehicle and the simulator's failed vehicle.

    ``activate(state (4,), target_m (2,), last_acceleration_m_s2 (2,))`` when the mode begins (state
    ``[x_m, y_m, vx_m_s, vy_m_s]``, the acceleration flown until then); ``acc_m_s2(state (4,), dt_s, acc_limit_m_s2)``
    each sub-step: the acceleration to hold over it (2,), before the airframe's limit."""

    def __init__(self, params: AutoParams | None = None) -> None:
        self.params = AutoParams() if params is None else params
        self.task = FlightTaskAutoXY(self.params)
        self.control = PositionControlXY(self.params)
        self.active = False
        self._vel_prev = np.zeros(2)
        self._vel_dot = np.zeros(2)
        self._last_dt_s = 0.0
        self.last_setpoints: dict[str, np.ndarray] | None = None

    def activate(self, state: np.ndarray, target_m: np.ndarray, last_acceleration_m_s2: np.ndarray) -> None:
        state = np.asarray(state, dtype=float).reshape(4)
        acc = np.asarray(last_acceleration_m_s2, dtype=float).reshape(2)
        self.task = FlightTaskAutoXY(self.params)
        self.task.activate(state[0:2], state[2:4], target_m, acc)
        self.control = PositionControlXY(self.params)
        self._vel_prev = state[2:4].copy()
        self._vel_dot = np.where(np.isfinite(acc), acc, 0.0)   # at activation: the acceleration flown before
        self.last_setpoints = None
        self.active = True

    def acc_m_s2(self, state: np.ndarray, dt_s: float, acc_limit_m_s2: float) -> np.ndarray:
        if not self.active:
            raise RuntimeError("Px4AutoXY.acc_m_s2 before activate")
        state = np.asarray(state, dtype=float).reshape(4)
        pos, vel = state[0:2], state[2:4]
        if self.last_setpoints is not None:           # the velocity derivative over the last sub-step
            self._vel_dot = (vel - self._vel_prev) / self._last_dt_s
        self._vel_prev = vel.copy()
        self._last_dt_s = dt_s
        idt = self.params.internal_dt_s
        if idt is None or self.task._first:
            sp = self.task.update(pos, dt_s)       # one cycle (the first after activate: at the activation instant)
        else:
            k = max(1, int(math.ceil(dt_s / idt - 1e-9)))
            for _ in range(k):
                sp = self.task.update(pos, dt_s / k)
        self.last_setpoints = sp
        return self.control.update(sp["position"], sp["velocity"], sp["acceleration"], pos, vel, self._vel_dot,
                                   acc_limit_m_s2, dt_s)
