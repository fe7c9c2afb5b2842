"""The own disturbance observer: the acceleration the controller's model of eq. 9 does not explain (not from the
paper; issue 18).

The controller's model of the plant is eq. 9 without its noise: dv/dt = a - c0 (v - v_o). Over one control period
dt the own vehicle's velocity changes by v_k - v_{k-1}; what the command a_{k-1} it sent and the modelled drag do not
explain is the disturbance it flew through (the wind noise V_o dW, and anything beyond the model - a gust):

    d_k = (v_k - v_{k-1}) / dt - (a_{k-1} - c0 ((v_k + v_{k-1}) / 2 - v_o))          (the residual)

The observer smooths it, d_hat_k = lam d_hat_{k-1} + (1 - lam) d_k, and the controller sends a - shrink(d_hat) so
that the vehicle flies the acceleration it chose (the feedforward). ``shrink`` drops the part of d_hat within the
deadband (a soft threshold): the modelled wind noise alone gives a residual of std |V_o| sqrt(dt) / dt per axis
(0.14 m/s^2 at the paper's V_o = 0.1 m/s per sqrt(s), dt = 0.5 s; 0.08 m/s^2 after lam = 0.5), which the paper's
controller leaves to its feedback; only what stands above it is fed forward. Each vehicle needs only its own
telemetry and its own last command: no communication.

Pure functions; the controller keeps the state (``DefaultMFGController._reject_disturbance``).
"""

from __future__ import annotations

import numpy as np

__all__ = ["disturbance_residual_m_s2", "shrink_m_s2"]


def disturbance_residual_m_s2(v_m_s: np.ndarray, v_prev_m_s: np.ndarray, acc_prev_m_s2: np.ndarray, dt_s: float,
                              c0_per_s: float, v_o_m_s: np.ndarray) -> np.ndarray:
    """(n, 2) the residual d_k above: the velocity change over dt_s (v_m_s now, v_prev_m_s one period before, both
    (n, 2)) less what eq. 9's drift makes of the command acc_prev_m_s2 (n, 2) sent then (drag at the mean velocity)."""
    v, v0 = np.asarray(v_m_s, dtype=float), np.asarray(v_prev_m_s, dtype=float)
    return (v - v0) / dt_s - (np.asarray(acc_prev_m_s2, dtype=float)
                              - c0_per_s * (0.5 * (v + v0) - np.asarray(v_o_m_s, dtype=float)[None, :]))


def shrink_m_s2(d_m_s2: np.ndarray, deadband_m_s2: float) -> np.ndarray:
    """(n, 2) each row of d_m_s2 (n, 2) shortened by deadband_m_s2 in norm (zero within it): the soft threshold."""
    d = np.asarray(d_m_s2, dtype=float)
    norm = np.sqrt(d[:, 0] ** 2 + d[:, 1] ** 2)
    scale = np.where(norm > deadband_m_s2, 1.0 - deadband_m_s2 / np.maximum(norm, 1e-300), 0.0)
    return d * scale[:, None]
