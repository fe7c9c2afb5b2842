"""The plant: how a vehicle really moves (paper eq. 9, Ornstein-Uhlenbeck wind).

    dv_i = a_i dt - c0 (v_i - v_o) dt + V_o dW_i            (eq. 1)
    dr_i = v_i dt                                            (eq. 2)
    ds_i = (A s_i + B (a_i + c0 v_o)) dt + G dW_i            (eq. 5 / 9)

integrated with Euler-Maruyama (the Wiener increment scales with sqrt(h)).

This module is pure numpy with no I/O. It is the one piece of code that both the
mock vehicle process and the in-process simulator (``mfg_swarm.sim``) use to move
vehicles, so that a vehicle's wind is the same whichever process simulates it:
each vehicle's noise is one stream derived from ``(seed, vehicle_id)`` and consumed
in a fixed order (2 standard normals for the initial wind velocity, then 2 per
physics sub-step). The controller never imports it: it keeps its own model of the
dynamics (A, B, G in ``mfg_autopilot.paper.model``).

Shapes: ``states`` is ``(n_vehicles, 4)`` with columns ``[x_m, y_m, vx_m_s, vy_m_s]``
(paper frame: x = north, y = east of MAVLink LOCAL_NED).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

__all__ = [
    "WindParams",
    "PlantParams",
    "PX4_ACC_LAG_S",
    "NoiseStream",
    "noise_stream",
    "initial_wind_velocity",
    "euler_maruyama_step",
    "lag_coefficients",
    "lagged_acc_m_s2",
    "saturate_norm",
    "hold_acc_m_s2",
    "jerk_limited_m_s2",
    "braking_stop_m",
    "SwarmPlant",
]


@dataclass(frozen=True)
class WindParams:
    """Ornstein-Uhlenbeck wind of eq. 1 (paper Sec. V values by default)."""

    c0_per_s: float = 0.1
    """c0: rate at which the airframe's velocity relaxes to the wind, 1/s."""
    mean_wind_m_s: tuple[float, float] = (1.0, -1.0)
    """v_o: average wind velocity (north, east), m/s."""
    wind_diffusion_m_s: tuple[tuple[float, float], tuple[float, float]] = ((0.1, 0.0), (0.0, 0.1))
    """V_o: 2x2 diffusion matrix of the wind velocity, m/s per sqrt(s)."""

    def __post_init__(self) -> None:
        if not (np.isfinite(self.c0_per_s) and self.c0_per_s > 0):
            raise ValueError(f"c0_per_s must be finite and > 0, got {self.c0_per_s}")
        if not np.all(np.isfinite(self.mean_wind_m_s)) or len(self.mean_wind_m_s) != 2:
            raise ValueError(f"mean_wind_m_s must be 2 finite numbers, got {self.mean_wind_m_s}")
        v = np.asarray(self.wind_diffusion_m_s, dtype=float)
        if v.shape != (2, 2) or not np.all(np.isfinite(v)):
            raise ValueError(f"wind_diffusion_m_s must be a finite 2x2 matrix, got {self.wind_diffusion_m_s}")

    @property
    def v_o(self) -> np.ndarray:
        return np.asarray(self.mean_wind_m_s, dtype=float)

    @property
    def V_o(self) -> np.ndarray:
        return np.asarray(self.wind_diffusion_m_s, dtype=float)

    def stationary_velocity_cov(self) -> np.ndarray:
        """Stationary covariance of v under a = 0 (continuous time): V_o V_o^T / (2 c0)."""
        return self.V_o @ self.V_o.T / (2.0 * self.c0_per_s)


PX4_ACC_LAG_S = 0.154
"""PX4's acceleration response lag, s: its attitude loop is a P on the angle, MC_ROLL_P = MC_PITCH_P = 6.5 /s by
default (mc_att_control_params.c), over a much faster rate loop: about 1 / 6.5 s. The mock vehicle's default
(``mock-vehicle --acc-lag-s``, SIM_ACC_TAU) and the simulator's for the default guidance (``mfg_swarm.sim``)."""


@dataclass(frozen=True)
class PlantParams:
    wind: WindParams = field(default_factory=WindParams)
    acc_limit_m_s2: float = 2.0
    """The airframe's acceleration limit (norm of the horizontal acceleration), m/s^2."""
    physics_dt_s: float = 0.1
    """Largest Euler-Maruyama sub-step, s. A control step dt is split into
    ceil(dt / physics_dt_s) equal sub-steps with the acceleration held."""
    acc_lag_s: float = 0.0
    """Time constant of the airframe's acceleration response, s: the acceleration flown follows the (saturated)
    command as a first-order lag, da/dt = (a_cmd - a) / acc_lag_s (``lagged_acc_m_s2``). 0 (the plant's default, the
    paper's model): the command is flown at once, as eq. 9 writes it. A multicopter tilts to accelerate, and PX4's attitude loop is a
    P on the angle (MC_ROLL_P = MC_PITCH_P = 6.5 /s by default, mc_att_control_params.c) over a much faster rate
    loop: about 1 / 6.5 = 0.154 s (PX4_ACC_LAG_S), more with slow motors. The paper's model assumes none; the mock
    vehicle flies PX4's by default."""

    def __post_init__(self) -> None:
        if not (np.isfinite(self.acc_limit_m_s2) and self.acc_limit_m_s2 > 0):
            raise ValueError(f"acc_limit_m_s2 must be finite and > 0, got {self.acc_limit_m_s2}")
        if not (np.isfinite(self.physics_dt_s) and self.physics_dt_s > 0):
            raise ValueError(f"physics_dt_s must be finite and > 0, got {self.physics_dt_s}")
        if not (np.isfinite(self.acc_lag_s) and 0.0 <= self.acc_lag_s <= 2.0):
            raise ValueError(f"acc_lag_s must be in [0, 2] s (0: no lag), got {self.acc_lag_s}")

    def substeps(self, dt_s: float) -> int:
        """Number of physics sub-steps for a control step of ``dt_s``."""
        if not (np.isfinite(dt_s) and dt_s > 0):
            raise ValueError(f"dt_s must be finite and > 0, got {dt_s}")
        return max(1, int(np.ceil(dt_s / self.physics_dt_s - 1e-9)))


class NoiseStream:
    """One vehicle's stream of standard normals, derived from ``(seed, vehicle_id)``.

    Draws are served from an internal buffer; numpy's ``Generator.standard_normal``
    yields the same sequence whatever the chunk sizes, so a buffered stream (the
    simulator) and an unbuffered one (a mock process) agree draw for draw.
    """

    __slots__ = ("seed", "vehicle_id", "_rng", "_buf", "_pos", "_chunk")

    def __init__(self, seed: int, vehicle_id: int, chunk: int = 512) -> None:
        if seed < 0 or vehicle_id < 0:
            raise ValueError(f"seed and vehicle_id must be >= 0, got {seed}, {vehicle_id}")
        self.seed = int(seed)
        self.vehicle_id = int(vehicle_id)
        self._rng = np.random.Generator(np.random.PCG64(np.random.SeedSequence([self.seed, self.vehicle_id])))
        self._chunk = int(chunk)
        self._buf = np.empty(0)
        self._pos = 0

    def normals(self, n: int) -> np.ndarray:
        """The next ``n`` standard normals of this vehicle's stream, shape (n,)."""
        out = np.empty(n)
        filled = 0
        while filled < n:
            if self._pos >= self._buf.size:
                self._buf = self._rng.standard_normal(max(self._chunk, n - filled))
                self._pos = 0
            take = min(n - filled, self._buf.size - self._pos)
            out[filled : filled + take] = self._buf[self._pos : self._pos + take]
            self._pos += take
            filled += take
        return out


def noise_stream(seed: int, vehicle_id: int) -> NoiseStream:
    """The noise stream of vehicle ``vehicle_id`` in a run seeded with ``seed``."""
    return NoiseStream(seed, vehicle_id)


def _stationary_velocity_chol(wind: WindParams) -> np.ndarray:
    """Cholesky factor of the stationary velocity covariance of eq. 1 (with a 1e-15 jitter), (2, 2)."""
    return np.linalg.cholesky(wind.stationary_velocity_cov() + 1e-15 * np.eye(2))


def initial_wind_velocity(wind: WindParams, stream: NoiseStream) -> np.ndarray:
    """Initial velocity "solely determined by the wind" (Sec. V): one draw from the
    stationary law of eq. 1 with a = 0, N(v_o, V_o V_o^T / (2 c0)). Consumes 2 draws."""
    return wind.v_o + _stationary_velocity_chol(wind) @ stream.normals(2)


def saturate_norm(vec: np.ndarray, limit: float) -> np.ndarray:
    """Scale each row of ``vec`` (..., 2) down so that its norm is at most ``limit``."""
    vec = np.asarray(vec, dtype=float)
    norm = np.linalg.norm(vec, axis=-1, keepdims=True)
    scale = np.minimum(1.0, limit / np.maximum(norm, 1e-300))
    return vec * scale


def lag_coefficients(h_s: float, lag_s: float) -> tuple[float, float]:
    """(end, mean) of a first-order lag over a sub-step ``h_s`` with the command held: starting from ``a`` with the
    command ``c``, the acceleration at the sub-step's end is ``a + (c - a) end`` and its mean over the sub-step
    ``a + (c - a) mean`` (exact for the held command). ``lag_s`` 0: (1, 1), the command at once."""
    if lag_s <= 0.0:
        return 1.0, 1.0
    x = h_s / lag_s
    end = -math.expm1(-x)                 # 1 - exp(-h / tau)
    return end, 1.0 - end / x             # mean of 1 - exp(-t / tau) over [0, h]


def lagged_acc_m_s2(acc_flown_m_s2: np.ndarray, acc_cmd_m_s2: np.ndarray, end: float,
                    mean: float) -> tuple[np.ndarray, np.ndarray]:
    """One sub-step of the first-order acceleration response (``PlantParams.acc_lag_s``; coefficients from
    ``lag_coefficients``): (the acceleration at its end, its mean over the sub-step), each (n, 2)."""
    gap = acc_cmd_m_s2 - acc_flown_m_s2
    return acc_flown_m_s2 + gap * end, acc_flown_m_s2 + gap * mean


def euler_maruyama_step(
    states: np.ndarray,
    acc_m_s2: np.ndarray,
    dt_s: float,
    wind: WindParams,
    normals: np.ndarray,
) -> np.ndarray:
    """One Euler-Maruyama step of eq. 9 for every vehicle.

    states: (n, 4); acc_m_s2: (n, 2), already within the airframe's limit;
    normals: (n, 2) standard normals. Returns the new states (n, 4).
    """
    r = states[:, 0:2]
    v = states[:, 2:4]
    dW = normals * np.sqrt(dt_s)
    v_next = v + (acc_m_s2 - wind.c0_per_s * (v - wind.v_o)) * dt_s + dW @ wind.V_o.T
    r_next = r + v * dt_s
    return np.concatenate([r_next, v_next], axis=1)


def braking_stop_m(states: np.ndarray, acc_hor_m_s2: float = 3.0) -> np.ndarray:
    """Where a multicopter entering Hold holds, (n, 2): PX4's loiter point (navigator ``Loiter::set_loiter_position``
    -> ``MissionBlock::setLoiterItemFromCurrentPositionWithBreaking`` -> ``Navigator::calculate_breaking_stop``: "for
    multirotors we need to account for the braking distance, otherwise the vehicle will overshoot and go back"): the
    position moved along the course over ground by ``computeBrakingDistanceFromVelocity(|v|, MPC_JERK_AUTO,
    MPC_ACC_HOR, 0.6 MPC_JERK_AUTO)`` = |v| (|v| / (2 MPC_ACC_HOR) + 0.6 s): the jerk cancels (PX4's TrajMath.hpp;
    default 3 m/s^2). states: (n, 4)."""
    states = np.asarray(states, dtype=float)
    v = states[:, 2:4]
    speed = np.linalg.norm(v, axis=1)
    dist = speed * (speed / (2.0 * acc_hor_m_s2) + 0.6)
    unit = v / np.maximum(speed, 1e-300)[:, None]
    return states[:, 0:2] + dist[:, None] * unit


def position_brake_path_m(state: np.ndarray, acc_hor_m_s2: float = 3.0, vel_manual_m_s: float = 10.0,
                          dt_s: float = 0.02, max_s: float = 120.0) -> tuple[np.ndarray, np.ndarray]:
    """The path of a multicopter entering Position mode with the sticks centred: (positions (K, 2), velocities (K, 2))
    every dt_s from the entry state (4,); the last position is where PX4 locks it. PX4's
    ``FlightTaskManualAcceleration`` starts its velocity setpoint at the current velocity and its brake boost at 1
    (``activate``). ``StickAccelerationXY::generateSetpoints`` then brakes that setpoint with the drag
    (2 MPC_ACC_HOR / MPC_VEL_MANUAL) b sqrt_linear(|v_sp|) along v_sp. The boost b is an ``AlphaFilter`` with a 0.8 s time
    constant, driven to max(2, sqrt(MPC_VEL_MANUAL)) while the sticks are centred. A setpoint that the drag would
    reverse within one step is set to zero, and ``lockPosition`` locks the position once it is. Integrated at PX4's
    50 Hz task rate. Not modelled: the jerk-limited decay of the last commanded acceleration (MPC_JERK_MAX) and the
    tilt limit (it binds only above ~5 m/s with the defaults). Defaults: PX4's 3 m/s^2 and 10 m/s."""
    state = np.asarray(state, dtype=float).reshape(4)
    p, v = state[0:2].copy(), state[2:4].copy()
    k0 = 2.0 * acc_hor_m_s2 / vel_manual_m_s
    target, alpha = max(2.0, math.sqrt(vel_manual_m_s)), dt_s / (0.8 + dt_s)
    boost = 1.0
    ps, vs = [p.copy()], [v.copy()]
    for _ in range(int(max_s / dt_s)):
        speed = float(np.linalg.norm(v))
        if speed == 0.0:
            break
        boost += alpha * (target - boost)
        drag = k0 * boost * (math.sqrt(speed) if speed < 1.0 else speed)     # math::sqrt_linear
        v = np.zeros(2) if speed < drag * dt_s else v - drag * dt_s * v / speed
        p = p + v * dt_s
        ps.append(p.copy())
        vs.append(v.copy())
    return np.array(ps), np.array(vs)


def hold_acc_m_s2(
    states: np.ndarray,
    hold_pos_m: np.ndarray,
    acc_limit_m_s2: float,
    kp_per_s2: float = 1.0,
    kd_per_s: float = 2.0,
) -> np.ndarray:
    """Acceleration of a vehicle in HOLD (PX4 "Hold": brake to zero velocity and keep
    hold_pos_m, the braking stop of ``braking_stop_m`` where the hold began): a critically damped PD on position,
    saturated (from the braking stop it reaches the point without overshoot).

    states: (n, 4); hold_pos_m: (n, 2). Returns (n, 2).
    """
    acc = -kp_per_s2 * (states[:, 0:2] - hold_pos_m) - kd_per_s * states[:, 2:4]
    return saturate_norm(acc, acc_limit_m_s2)


def jerk_limited_m_s2(acc_prev_m_s2: np.ndarray, acc_target_m_s2: np.ndarray, jerk_m_s3: float, dt_s: float) -> np.ndarray:
    """The acceleration of a multicopter in an auto mode (Takeoff, Hold, Land) after ``dt_s``: PX4 does not jump to the
    new acceleration. Its auto modes (``FlightTaskAuto``) take their setpoints from ``PositionSmoothing``, a trajectory
    whose acceleration changes at most ``MPC_JERK_AUTO`` (default 4 m/s^3, ``_updateTrajConstraints``), reset when the
    mode begins to the last setpoint's acceleration (``FlightTaskAuto::activate``: the offboard acceleration a vehicle
    flew until then). Modelled as a rate limit on the change of the acceleration: acc_prev + the change towards
    ``acc_target_m_s2`` (here the Hold PD's, ``hold_acc_m_s2``) capped at ``jerk_m_s3`` x ``dt_s`` in norm. So a vehicle
    that enters Hold at cruise builds its braking up over ~0.5 s (2 m/s^2 at 4 m/s^3) instead of braking at the
    airframe's limit from the first instant. ``jerk_m_s3`` <= 0 or infinite: no limit (``acc_target_m_s2``).
    Shapes (..., 2)."""
    acc_target_m_s2 = np.asarray(acc_target_m_s2, dtype=float)
    if not (math.isfinite(jerk_m_s3) and jerk_m_s3 > 0.0):
        return acc_target_m_s2
    acc_prev_m_s2 = np.asarray(acc_prev_m_s2, dtype=float)
    return acc_prev_m_s2 + saturate_norm(acc_target_m_s2 - acc_prev_m_s2, jerk_m_s3 * dt_s)


class SwarmPlant:
    """N vehicles moved by eq. 9, each with its own noise stream from ``(seed, id)``.

    ``step`` integrates one control step ``dt_s`` in ``params.substeps(dt_s)`` equal
    Euler-Maruyama sub-steps with the (saturated) acceleration held. A mock vehicle
    process that makes the same calls for its own id moves bit-for-bit the same.
    With ``params.acc_lag_s`` > 0 each sub-step flies the mean of the lagged acceleration
    (``acc_flown_m_s2``, the lag's state, starting at 0) instead of the command.
    """

    _PREFETCH = 500          # draws per vehicle taken from its stream at a time

    def __init__(
        self,
        initial_pos_m: np.ndarray,
        params: PlantParams,
        seed: int,
        vehicle_ids: np.ndarray | None = None,
        initial_vel_m_s: np.ndarray | None = None,
    ) -> None:
        pos = np.asarray(initial_pos_m, dtype=float)
        if pos.ndim != 2 or pos.shape[1] != 2 or not np.all(np.isfinite(pos)):
            raise ValueError(f"initial_pos_m must be a finite (n, 2) array, got shape {pos.shape}")
        n = pos.shape[0]
        self.params = params
        self.vehicle_ids = np.arange(n) if vehicle_ids is None else np.asarray(vehicle_ids, dtype=int)
        if self.vehicle_ids.shape != (n,):
            raise ValueError("vehicle_ids must have one id per vehicle")
        self.streams = [noise_stream(seed, int(i)) for i in self.vehicle_ids]
        # Initial wind velocity is drawn first from each stream even when an initial
        # velocity is given, so that the stream position never depends on the caller.
        # = initial_wind_velocity(params.wind, s) per stream, with the Cholesky factor computed once
        chol = _stationary_velocity_chol(params.wind)
        v_o = params.wind.v_o
        vel0 = np.array([v_o + chol @ s.normals(2) for s in self.streams]).reshape(n, 2)
        if initial_vel_m_s is not None:
            vel0 = np.asarray(initial_vel_m_s, dtype=float).reshape(n, 2)
        self.states = np.concatenate([pos, vel0], axis=1)
        self.time_s = 0.0
        # draws taken from the streams ahead of use, (n, m) (consumed from column _noise_pos):
        # one Python call per vehicle every ~_PREFETCH / (2 k) steps instead of every step.
        # Each vehicle still uses the consecutive draws of its own stream, so the numbers
        # are the same as a mock process's, which draws its 2 k per step unbuffered.
        self._noise = np.empty((n, 0))
        self._noise_pos = 0
        self._single_cache: tuple | None = None   # _step_single: (params, dt_s, what it derives from them)
        self.acc_flown_m_s2 = np.zeros((n, 2))    # the lag's state (params.acc_lag_s > 0): the acceleration flown now

    @property
    def n(self) -> int:
        return self.states.shape[0]

    def step(self, acc_m_s2: np.ndarray, dt_s: float) -> np.ndarray:
        """Advance every vehicle by ``dt_s`` holding ``acc_m_s2`` (n, 2). Returns the
        acceleration actually applied (after the airframe limit), (n, 2): the command the
        airframe took; with ``params.acc_lag_s`` > 0 it flies that command's lagged response
        (``acc_flown_m_s2``)."""
        if self.n == 1:
            return self._step_single(acc_m_s2, dt_s)
        return self._step_vectorised(acc_m_s2, dt_s)

    def _step_vectorised(self, acc_m_s2: np.ndarray, dt_s: float) -> np.ndarray:
        acc = np.asarray(acc_m_s2, dtype=float).reshape(self.n, 2)
        if not np.all(np.isfinite(acc)):
            raise ValueError("acceleration must be finite")
        acc = saturate_norm(acc, self.params.acc_limit_m_s2)
        k = self.params.substeps(dt_s)
        h = dt_s / k
        noise = self._take_noise(k)
        x = self.states
        if self.params.acc_lag_s > 0.0:
            end, mean = lag_coefficients(h, self.params.acc_lag_s)
            a = self.acc_flown_m_s2
            for j in range(k):
                a, a_mean = lagged_acc_m_s2(a, acc, end, mean)
                x = euler_maruyama_step(x, a_mean, h, self.params.wind, noise[:, j, :])
            self.acc_flown_m_s2 = a
        else:
            for j in range(k):
                x = euler_maruyama_step(x, acc, h, self.params.wind, noise[:, j, :])
            self.acc_flown_m_s2 = acc
        self.states = x
        self.time_s += dt_s
        return acc

    def _take_noise(self, k: int) -> np.ndarray:
        """The next 2 k draws of every vehicle's stream, (n, k, 2)."""
        need = 2 * k
        if self._noise.shape[1] - self._noise_pos < need:
            m = max(need, self._PREFETCH)
            fresh = np.stack([s.normals(m) for s in self.streams]) if self.n else np.empty((0, m))
            self._noise = np.concatenate([self._noise[:, self._noise_pos:], fresh], axis=1)
            self._noise_pos = 0
        noise = np.ascontiguousarray(self._noise[:, self._noise_pos:self._noise_pos + need]).reshape(self.n, k, 2)
        self._noise_pos += need
        return noise

    def _step_single(self, acc_m_s2: np.ndarray, dt_s: float) -> np.ndarray:
        """``step`` of a plant of one vehicle (a mock process's), with the numbers of the
        vectorised code: saturate_norm and euler_maruyama_step's elementwise IEEE operations
        (+ - * / sqrt, each rounded, in the same order) on Python floats instead of (1, 2)
        arrays; the wind term ``dW @ V_o.T`` is still numpy's matmul of each (1, 2) row
        (one stacked call over the sub-steps, the same row-by-row products)."""
        acc = np.asarray(acc_m_s2, dtype=float).reshape(1, 2)
        ax, ay = acc[0].tolist()
        if not (math.isfinite(ax) and math.isfinite(ay)):
            raise ValueError("acceleration must be finite")
        norm = math.sqrt(ax * ax + ay * ay)                                     # saturate_norm
        scale = self.params.acc_limit_m_s2 / (norm if norm >= 1e-300 else 1e-300)
        if scale >= 1.0:
            scale = 1.0
        ax, ay = ax * scale, ay * scale
        cached = self._single_cache
        if cached is None or cached[0] is not self.params or cached[1] != dt_s:
            wind = self.params.wind
            k = self.params.substeps(dt_s)
            cached = self._single_cache = (self.params, dt_s, k, dt_s / k, np.sqrt(dt_s / k), wind.c0_per_s,
                                           *wind.v_o.tolist(), wind.V_o.T,
                                           *lag_coefficients(dt_s / k, self.params.acc_lag_s))
        _, _, k, h, sqrt_h, c0, vox, voy, diffusion_t, end, mean = cached
        dW = (self._take_noise(k) * sqrt_h).reshape(k, 1, 2)                    # euler_maruyama_step's dW, per sub-step
        diffusion = np.matmul(dW, diffusion_t).reshape(k, 2).tolist()
        x, y, vx, vy = self.states[0].tolist()
        if self.params.acc_lag_s > 0.0:
            fx, fy = self.acc_flown_m_s2[0].tolist()
            for dvx, dvy in diffusion:                                          # lagged_acc_m_s2, euler_maruyama_step
                gx, gy = ax - fx, ay - fy
                mx, my = fx + gx * mean, fy + gy * mean
                fx, fy = fx + gx * end, fy + gy * end
                x, y, vx, vy = (x + vx * h, y + vy * h,
                                vx + (mx - c0 * (vx - vox)) * h + dvx, vy + (my - c0 * (vy - voy)) * h + dvy)
            self.acc_flown_m_s2 = np.array([[fx, fy]])
        else:
            for dvx, dvy in diffusion:                                          # euler_maruyama_step
                x, y, vx, vy = (x + vx * h, y + vy * h,
                                vx + (ax - c0 * (vx - vox)) * h + dvx, vy + (ay - c0 * (vy - voy)) * h + dvy)
            self.acc_flown_m_s2 = np.array([[ax, ay]])
        self.states = np.array([[x, y, vx, vy]])
        self.time_s += dt_s
        return np.array([[ax, ay]])
