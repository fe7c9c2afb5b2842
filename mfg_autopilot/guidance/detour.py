"""The plan's detour around a vehicle lost to it (issue 18): every lane near a failed vehicle is deflected together.

A vehicle that failed into Hold hovers where the stream has left it; the lanes of the plan still run through it. The
backstop's escape lets each UAV pass it alone, and a UAV alone cannot keep both the failed vehicle and the next lane at
half the lattice spacing (measured: `dense --fail-vehicle` passes 0.12-0.26 m, the others 0.19-0.30 m, against 0.25 /
0.71 m asked). Here the plan itself is deformed around it, the same way by every UAV that senses it: a pure function
of a plan particle's state (s, a) and of the failed vehicle's sensed position o, so the UAVs agree without talking.

In the particle's own frame (u its velocity's direction, n = u turned left), with x = (p - o).u along and
y = (p - o).n across, the particle is moved across by

    dy = sgn(y) * c * max(0, 1 - |y| / W) * H(x) * alpha,

sgn(0) = -1 (the lane right through the vehicle passes on its right, as the backstop's keep-right and lane side),
H = 1 on |x| <= plateau, a raised cosine to 0 over the next ``ramp_m``, and alpha in [0, 1] the onset (below). Across
the lanes y -> y + dy is increasing with slope >= 1 - c / W, so lanes keep their order, neighbouring lanes at
least (1 - c / W) x their spacing apart, and on the plateau every lane is at least c from o: |y + dy| >= c. The
displacement's velocity is n dy'(x) |v|; the command adds its mean acceleration over the control step (the plan's
command is the mean over the step). The support (|x| <= plateau + ramp, |y| <= W) lies inside the sensor range,
so every UAV whose particle is deflected senses the vehicle (and one that does not sense it sees its deflected
neighbours only near the support's edge, where the displacement is small).

The vehicle to detour around hovers (slower than the backstop's ``hover_max_speed_m_s``) farther than
``onset_from_m`` from its own particle (by its id, from the t = 0 exchange). alpha ramps in with that distance (every
observer computes the same number from the sensed state and the plan), so the lanes swing out over ``onset_m`` of the
stream, not in one step; particles slower than ``min_speed_m_s`` are faded out (a parked particle has no lane).
"""

from __future__ import annotations

import numpy as np

from mfg_autopilot.guidance.params import DetourParams

__all__ = ["detour_offset", "detour_onset", "detour_side"]


def _profile(x: np.ndarray, plateau_m: float, ramp_m: float) -> tuple[np.ndarray, np.ndarray]:
    """H(x) and dH/dx: 1 on |x| <= plateau, 0.5 (1 + cos(pi (|x| - plateau) / ramp)) on the ramp, 0 beyond."""
    ax = np.abs(x)
    t = np.clip((ax - plateau_m) / ramp_m, 0.0, 1.0)
    h = 0.5 * (1.0 + np.cos(np.pi * t))
    on_ramp = (ax > plateau_m) & (ax < plateau_m + ramp_m)
    dh = np.where(on_ramp, -0.5 * np.pi / ramp_m * np.sin(np.pi * t) * np.sign(x), 0.0)
    return h, dh


def detour_onset(dist_from_own_particle_m: np.ndarray, p: DetourParams) -> np.ndarray:
    """alpha (m,): 0 until the hovering vehicle is ``onset_from_m`` from its own particle, 1 from ``onset_m`` further
    on, a smoothstep between (the stream leaves it behind at its speed: the lanes swing out over onset_m / v)."""
    t = np.clip((np.asarray(dist_from_own_particle_m, dtype=float) - p.onset_from_m) / p.onset_m, 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def detour_side(part: np.ndarray, o: np.ndarray, a_part: np.ndarray | None = None) -> np.ndarray:
    """(m,) +1 / -1: the side (left / right of its own track) on which each particle passes the vehicle at o: the side
    of the vehicle its lane lies on where it passes it, right for a lane through it. A turning lane (``a_part`` (m, 2),
    the particles' command: a rigid turn's lanes are arcs) passes at y + kappa x^2 / 2, kappa = a.n / |v|^2 its
    curvature, x and y the vehicle's offset along and across the track now (an arc of 50 m radius drifts 0.7 m across
    over the 8.5 m before the vehicle)."""
    part = np.asarray(part, dtype=float)
    v = part[:, 2:4]
    d = part[:, 0:2] - o
    speed2 = v[:, 0] ** 2 + v[:, 1] ** 2
    sp = np.sqrt(speed2)
    y = (v[:, 0] * d[:, 1] - v[:, 1] * d[:, 0]) / np.maximum(sp, 1e-12)
    if a_part is not None:
        x = (v[:, 0] * d[:, 0] + v[:, 1] * d[:, 1]) / np.maximum(sp, 1e-12)
        a_n = (v[:, 0] * a_part[:, 1] - v[:, 1] * a_part[:, 0]) / np.maximum(sp, 1e-12)
        y = y + np.where(x < 0, 0.5 * a_n / np.maximum(speed2, 1e-12) * x * x, 0.0)
    return np.where(y > 0, 1.0, -1.0)


def detour_offset(part: np.ndarray, a_part: np.ndarray, o: np.ndarray, alpha: np.ndarray, clear_m: float,
                  p: DetourParams, dt_s: float, side: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(ds (m, 4), da (m, 2)): the deflection of plan particles ``part`` (m, 4) [x, y, vx, vy] around the lost vehicles
    at ``o`` (m, 2) (row by row), with onset ``alpha`` (m,) and clearance ``clear_m`` (c above), and the mean
    acceleration of the deflection over the next control step (``a_part`` (m, 2): the particles' own command, along
    which they speed up or slow down). ``side`` (m,) +1 / -1: the side to pass on (default detour_side: a UAV keeps
    the side it chose at its first meeting, because the vehicle drifts in the wind across a lane that is close to it)."""
    part = np.asarray(part, dtype=float)
    m = part.shape[0]
    ds, da = np.zeros((m, 4)), np.zeros((m, 2))
    if m == 0:
        return ds, da
    v = part[:, 2:4]
    speed = np.hypot(v[:, 0], v[:, 1])
    moving = speed > 1e-9
    u = np.where(moving[:, None], v / np.maximum(speed, 1e-12)[:, None], 0.0)
    nrm = np.stack([-u[:, 1], u[:, 0]], axis=1)
    d = part[:, 0:2] - o
    x = np.sum(d * u, axis=1)
    y = np.sum(d * nrm, axis=1)
    side = np.where(y > 0, 1.0, -1.0) if side is None else np.asarray(side, dtype=float)
    amp = side * clear_m * np.maximum(0.0, 1.0 - np.abs(y) / p.width_m) * alpha
    amp *= np.clip(speed / p.min_speed_m_s, 0.0, 1.0) * moving
    h, dh = _profile(x, p.plateau_m, p.ramp_m)
    a_al = np.sum(a_part * u, axis=1)
    speed_next = np.maximum(speed + a_al * dt_s, 0.0)
    x_next = x + 0.5 * (speed + speed_next) * dt_s
    _, dh_next = _profile(x_next, p.plateau_m, p.ramp_m)
    ds[:, 0:2] = nrm * (amp * h)[:, None]
    ds[:, 2:4] = nrm * (amp * dh * speed)[:, None]
    da[:] = nrm * (amp * (dh_next * speed_next - dh * speed) / dt_s)[:, None]
    return ds, da
