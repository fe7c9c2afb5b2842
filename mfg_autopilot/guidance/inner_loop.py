"""The telemetry-rate inner loop: the period's command tracked between control steps (not from the paper; issue 18).

The controller decides an acceleration a_k once per control period dt (0.5 s) and the airframe holds it. A real
multicopter does not fly an acceleration setpoint at once: it tilts first, a first-order lag of ~1 / MC_ROLL_P =
0.154 s on PX4 (``mock_vehicle.plant.PlantParams.acc_lag_s``). Against that lag eq. 8's held gains ring (0.93 per
period) and no held gains at 2 Hz stay well damped over the lags an airframe may have (``bench/tracking_jitter.py
--lag``): what the lag needs is a faster loop, not other gains.

So between two control steps each vehicle tracks the *trajectory its command promised*: the state the controller's
model of eq. 9 (no noise), dv/dt = a_k - c0 (v - v_o), reaches from the step's state (r_k, v_k) with a_k held,

    v_ref(t) = u / c0 + (v_k - u / c0) e^{-c0 t},    u = a_k + c0 v_o
    r_ref(t) = r_k + (u / c0) t + (v_k - u / c0) (1 - e^{-c0 t}) / c0               (t since the step; c0 -> 0: Taylor)

and at every telemetry sample in between flies

    a(t) = sat_{a_max}( a_k + k_p (r_ref(t) - r(t)) + k_d (v_ref(t) - v(t)) ).

At the step's own sample the correction is 0: a(0) = a_k. So whatever the controller chose - the plan's tracking, an
escape, a barrier filter's brake - is what the vehicle flies, now also through a lag; and a disturbance inside the
period (a gust, the wind's noise) is fought at telemetry rate instead of one period later. Each vehicle needs only
its own telemetry and its own last command: no communication.

Pure functions and one small state holder; the simulator calls it at every physics sub-step, the autopilot at every
LOCAL_POSITION_NED between its steps (``TrackingParams.inner_loop``).
"""

from __future__ import annotations

import numpy as np

from mfg_autopilot.paper.model import cap_norm

__all__ = ["reference_state", "inner_acc_m_s2", "InnerLoop"]


def reference_state(r0_m: np.ndarray, v0_m_s: np.ndarray, acc_m_s2: np.ndarray, t_s: float | np.ndarray,
                    c0_per_s: float, v_o_m_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(r_ref, v_ref), each (n, 2): the state eq. 9's drift (no noise) reaches t_s after (r0_m, v0_m_s) (n, 2) with
    acc_m_s2 (n, 2) held (module docstring; exact). t_s: a scalar or one per row (n,)."""
    r0, v0, a = (np.asarray(x, dtype=float) for x in (r0_m, v0_m_s, acc_m_s2))
    t = np.asarray(t_s, dtype=float)
    t = t[:, None] if t.ndim == 1 else t
    v_o = np.asarray(v_o_m_s, dtype=float).reshape(1, 2)
    c0 = float(c0_per_s)
    if c0 * float(np.max(t, initial=0.0)) < 1e-9:        # no drag (or none yet): the constant-acceleration motion
        return r0 + v0 * t + 0.5 * (a - c0 * (v0 - v_o)) * t * t, v0 + (a - c0 * (v0 - v_o)) * t
    v_inf = a / c0 + v_o                                 # u / c0: the velocity the held command tends to
    decay = -np.expm1(-c0 * t)                           # 1 - e^{-c0 t}
    return r0 + v_inf * t + (v0 - v_inf) * decay / c0, v0 + (v_inf - v0) * decay


def inner_acc_m_s2(acc_m_s2: np.ndarray, r_ref_m: np.ndarray, v_ref_m_s: np.ndarray, r_m: np.ndarray, v_m_s: np.ndarray,
                   kp_per_s2: float, kd_per_s: float, a_max_m_s2: float) -> np.ndarray:
    """(n, 2) sat_{a_max}(a + k_p (r_ref - r) + k_d (v_ref - v)): the command corrected towards its reference."""
    a = (np.asarray(acc_m_s2, dtype=float) + kp_per_s2 * (np.asarray(r_ref_m, dtype=float) - np.asarray(r_m, dtype=float))
         + kd_per_s * (np.asarray(v_ref_m_s, dtype=float) - np.asarray(v_m_s, dtype=float)))
    return cap_norm(a, a_max_m_s2)


class InnerLoop:
    """The inner loop of a bank of vehicles (one row each; the autopilot's bank is its own vehicle): ``start`` at a
    control step with the states the step observed and the commands it sent, then ``acc_m_s2`` at any time after it."""

    def __init__(self, kp_per_s2: float, kd_per_s: float, c0_per_s: float, v_o_m_s: np.ndarray, a_max_m_s2: float) -> None:
        if not (kp_per_s2 >= 0.0 and kd_per_s >= 0.0 and np.isfinite(kp_per_s2) and np.isfinite(kd_per_s)):
            raise ValueError(f"inner loop gains must be finite and >= 0, got k_p {kp_per_s2!r}, k_d {kd_per_s!r}")
        self.kp, self.kd = float(kp_per_s2), float(kd_per_s)
        self.c0, self.v_o = float(c0_per_s), np.asarray(v_o_m_s, dtype=float).reshape(2)
        self.a_max = float(a_max_m_s2)
        self._start: tuple[float, np.ndarray, np.ndarray] | None = None     # (time s, states (n, 4), commands (n, 2))

    @classmethod
    def for_preset(cls, preset) -> "InnerLoop | None":
        """The preset's inner loop (its TrackingParams' gains, its model's c0 and v_o, its acceleration limit), or None
        if it has none or it is off."""
        tp = getattr(preset, "tracking", None)
        if tp is None or not tp.inner_loop:
            return None
        return cls(tp.inner_kp_per_s2, tp.inner_kd_per_s, preset.cost.c0_per_s, preset.cost.v_o, preset.learner.acc_max_m_s2)

    def start(self, time_s: float, states: np.ndarray, acc_m_s2: np.ndarray) -> None:
        """A control step at time_s: the states it observed (n, 4) and the commands it sent (n, 2)."""
        self._start = (float(time_s), np.array(states, dtype=float).reshape(-1, 4),
                       np.array(acc_m_s2, dtype=float).reshape(-1, 2))

    @property
    def started(self) -> bool:
        return self._start is not None

    @property
    def start_time_s(self) -> float:
        """The time of the last ``start`` (RuntimeError before the first)."""
        if self._start is None:
            raise RuntimeError("InnerLoop.start_time_s before the first start()")
        return self._start[0]

    def acc_m_s2(self, time_s: float, states: np.ndarray, rows: np.ndarray | slice = slice(None)) -> np.ndarray:
        """The commands (n, 2) (or of ``rows`` only: states are then those rows') at time_s from the states now."""
        if self._start is None:
            raise RuntimeError("InnerLoop.acc_m_s2 before the first start()")
        t0, s0, a0 = self._start
        s0, a0 = s0[rows], a0[rows]
        s = np.asarray(states, dtype=float).reshape(-1, 4)
        r_ref, v_ref = reference_state(s0[:, 0:2], s0[:, 2:4], a0, max(0.0, time_s - t0), self.c0, self.v_o)
        return inner_acc_m_s2(a0, r_ref, v_ref, s[:, 0:2], s[:, 2:4], self.kp, self.kd, self.a_max)
