"""Physical limits of what any controller can keep (issue 18): the UAV right behind a vehicle that fails into Hold.

A vehicle that fails into Hold brakes along its track at ``a_brake_m_s2``: from the first instant (``jerk_m_s3`` None:
the simulator's Hold with ``--hold-jerk 0``, a saturated PD towards PX4's braking stop), or building it up at
``jerk_m_s3`` (PX4's Hold, MPC_JERK_AUTO = 4 m/s^3: its setpoints come from the jerk-limited PositionSmoothing; the
simulator's and the mock's default). The UAV ``gap_m`` behind it in its lane, at the same speed
``v_m_s``, can react only ``delay_s`` later (the braking is seen in the sensed states one control period later) and
then with at most ``a_max_m_s2``. Relative to the failed vehicle its along-track acceleration is a + a_brake >= 0 (it
can at best cancel the braking), so it keeps closing at >= the speed the vehicle lost in the delay until it stops; the question is
how far across its track it can be when it draws abeam.

``follower_best_clearance_m`` answers it numerically: the largest smallest distance over the flight, maximised over
accelerations of norm a_max in a direction that is piecewise constant over ``step_s`` (each piece free), from the best
constant direction and seeded restarts (L-BFGS-B on a soft minimum). A maximum over a family of controls is a lower
bound of the true optimum; the constant-direction optimum and the piecewise-free one agree to about a millimetre
(tests/test_limits.py), which is the evidence that the bound is the optimum.

``gap_needed_m`` turns it round: the smallest gap in the lane at which a given reaction delay can still keep a given
clearance (bisection on the gap over the constant-direction optimum). ``longest_delay_s`` turns it the other way: the
longest reaction delay at which a given gap still keeps a given clearance.

**The delay is the detection's age plus the sampling period.** A controller that sees its neighbours every T (the
control period) and flags a Hold once it has lasted tau_det (its test's threshold: the velocity lost, j tau^2 / 2 on the
ramp, or the braking averaged over the last period) reacts, for a failure at an arbitrary instant, up to tau_det + T
after it: the sample before came just too early. A failure on the control grid (the simulator's ``--fail-at`` at a
multiple of dt) is the most favourable phase, not the worst.

Command: ``.venv/bin/python bench/onset_bound.py`` (tables over the delay and the gap).
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import minimize

__all__ = ["follower_best_clearance_m", "failed_along_track_m", "gap_needed_m", "longest_delay_s"]


def _distances(theta: np.ndarray, v_m_s: float, gap_m: float, delay_s: float, a_brake_m_s2: float, a_max_m_s2: float,
               step_s: float, horizon_s: float, jerk_m_s3: float | None = None) -> np.ndarray:
    """Distance follower - failed vehicle every step_s (exact at the samples: piecewise-constant accelerations)."""
    n_wait = int(round(delay_s / step_s))
    n = int(round(horizon_s / step_s))
    th = np.broadcast_to(theta, (n - n_wait,))
    ax = np.concatenate([np.zeros(n_wait), a_max_m_s2 * np.cos(th)])
    ay = np.concatenate([np.zeros(n_wait), a_max_m_s2 * np.sin(th)])
    t = np.arange(n + 1) * step_s
    vx = v_m_s + np.concatenate([[0.0], np.cumsum(ax) * step_s])
    vy = np.concatenate([[0.0], np.cumsum(ay) * step_s])
    x = -gap_m + np.concatenate([[0.0], np.cumsum(0.5 * (vx[1:] + vx[:-1]) * step_s)])
    y = np.concatenate([[0.0], np.cumsum(0.5 * (vy[1:] + vy[:-1]) * step_s)])
    return np.hypot(x - failed_along_track_m(t, v_m_s, a_brake_m_s2, jerk_m_s3), y)


def failed_along_track_m(t_s: np.ndarray, v_m_s: float, a_brake_m_s2: float, jerk_m_s3: float | None = None) -> np.ndarray:
    """How far the failed vehicle has gone along its track t_s after it failed: it brakes from v_m_s at a_brake_m_s2,
    from the first instant (``jerk_m_s3`` None or 0) or building the braking up from 0 at ``jerk_m_s3`` (PX4's
    Hold: MPC_JERK_AUTO), until it stops."""
    t = np.asarray(t_s, dtype=float)
    if not jerk_m_s3:
        tt = np.minimum(t, v_m_s / a_brake_m_s2)
        return v_m_s * tt - 0.5 * a_brake_m_s2 * tt * tt
    t1 = a_brake_m_s2 / jerk_m_s3                       # the ramp's end
    if v_m_s <= 0.5 * jerk_m_s3 * t1 * t1:              # it stops on the ramp
        t1 = np.sqrt(2.0 * v_m_s / jerk_m_s3)
        tt = np.minimum(t, t1)
        return v_m_s * tt - jerk_m_s3 * tt ** 3 / 6.0
    v1 = v_m_s - 0.5 * jerk_m_s3 * t1 * t1
    x1 = v_m_s * t1 - jerk_m_s3 * t1 ** 3 / 6.0
    t_ramp = np.minimum(t, t1)
    tt = np.clip(t - t1, 0.0, v1 / a_brake_m_s2)
    return np.where(t <= t1, v_m_s * t_ramp - jerk_m_s3 * t_ramp ** 3 / 6.0, x1 + v1 * tt - 0.5 * a_brake_m_s2 * tt * tt)


def follower_best_clearance_m(v_m_s: float = 4.0, gap_m: float = np.sqrt(2.0), delay_s: float = 0.5,
                              a_brake_m_s2: float = 2.0, a_max_m_s2: float = 2.0, step_s: float = 0.05,
                              horizon_s: float = 4.0, restarts: int = 6, seed: int = 0,
                              jerk_m_s3: float | None = None) -> dict:
    """{"constant_m": best over constant directions, "piecewise_m": best over piecewise-constant ones (>= constant),
    "direction_deg": the best constant direction from straight ahead (180: full braking)}. Distances at the step_s
    samples; the failed vehicle brakes from t = 0 (at once, or built up at ``jerk_m_s3``: PX4's Hold), the follower
    acts from delay_s (a multiple of step_s)."""
    args = (v_m_s, gap_m, delay_s, a_brake_m_s2, a_max_m_s2, step_s, horizon_s, jerk_m_s3)
    dirs = np.linspace(0.0, np.pi, 721)     # by symmetry one side
    const = np.array([_distances(np.array(th), *args).min() for th in dirs])
    i = int(np.argmax(const))
    best_c, th_c = float(const[i]), float(dirs[i])
    n_ctrl = int(round(horizon_s / step_s)) - int(round(delay_s / step_s))

    def neg_soft_min(th: np.ndarray, k: float = 80.0) -> float:
        d = _distances(th, *args)
        return float(np.log(np.sum(np.exp(-k * (d - d.min())))) / k - d.min())

    rng = np.random.default_rng(seed)
    best_p = best_c
    for r in range(restarts):
        th0 = np.full(n_ctrl, th_c) if r == 0 else th_c + 0.4 * rng.standard_normal(n_ctrl)
        res = minimize(neg_soft_min, th0, method="L-BFGS-B", options={"maxiter": 300})
        best_p = max(best_p, float(_distances(res.x, *args).min()))
    return {"constant_m": best_c, "piecewise_m": best_p, "direction_deg": float(np.degrees(th_c))}


def _best_constant_m(gap_m: float, delay_s: float, v_m_s: float, a_brake_m_s2: float, a_max_m_s2: float,
                     jerk_m_s3: float | None, step_s: float, horizon_s: float) -> float:
    """The largest smallest distance over constant directions of acceleration (0.5 deg grid, one side by symmetry)."""
    return max(float(_distances(np.array(th), v_m_s, gap_m, delay_s, a_brake_m_s2, a_max_m_s2, step_s, horizon_s,
                                jerk_m_s3).min()) for th in np.linspace(0.0, np.pi, 361))


def gap_needed_m(clearance_m: float, delay_s: float, v_m_s: float = 4.0, a_brake_m_s2: float = 2.0,
                 a_max_m_s2: float = 2.0, jerk_m_s3: float | None = 4.0, step_s: float = 0.05, horizon_s: float = 8.0,
                 gap_max_m: float = 10.0, tol_m: float = 0.005) -> float:
    """The smallest gap in the lane (to within tol_m) behind a vehicle failing into Hold at which a follower reacting
    delay_s late can keep clearance_m over the best constant direction of acceleration (within a millimetre of the
    piecewise optimum: follower_best_clearance_m); inf if not even gap_max_m does. A bisection: it assumes that the
    clearance, once kept, stays kept at larger gaps; tests/test_limits.py checks it on a grid (1.0-6.0 m, delays
    0.5-1.5 s, both Holds, half the 1.41 m spacing), not proven."""
    def best(gap: float) -> float:
        return _best_constant_m(gap, delay_s, v_m_s, a_brake_m_s2, a_max_m_s2, jerk_m_s3, step_s, horizon_s)

    if best(gap_max_m) < clearance_m:
        return float("inf")
    lo, hi = clearance_m, gap_max_m        # a gap below the clearance keeps nothing: the pair starts closer
    while hi - lo > tol_m:
        mid = 0.5 * (lo + hi)
        if best(mid) >= clearance_m:
            hi = mid
        else:
            lo = mid
    return hi


def longest_delay_s(clearance_m: float, gap_m: float = np.sqrt(2.0), v_m_s: float = 4.0, a_brake_m_s2: float = 2.0,
                    a_max_m_s2: float = 2.0, jerk_m_s3: float | None = 4.0, step_s: float = 0.05,
                    horizon_s: float = 8.0, delay_max_s: float = 3.0) -> float:
    """The longest reaction delay (a multiple of step_s) at which the UAV gap_m behind a vehicle failing into Hold can
    keep clearance_m over the best constant direction of acceleration; -1 if not even an immediate reaction does. Scans
    the delays upwards and stops at the first one that fails (the clearance falls with the delay:
    tests/test_limits.py checks it on the grid it is used on)."""
    n_max = int(round(delay_max_s / step_s))
    last = -1.0
    for i in range(n_max + 1):
        d = i * step_s
        if _best_constant_m(gap_m, d, v_m_s, a_brake_m_s2, a_max_m_s2, jerk_m_s3, step_s, horizon_s) < clearance_m:
            break
        last = d
    return last
