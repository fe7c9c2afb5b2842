"""The own disturbance observer (guidance/disturbance.py): its residual is what the plant did beyond the controller's
model of eq. 9, and its deadband lets the modelled wind noise through untouched."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from mfg_autopilot.guidance.disturbance import disturbance_residual_m_s2, shrink_m_s2
from mfg_autopilot.guidance.params import DEFAULT
from mfg_swarm.scenarios import make_scenario
from mfg_swarm.sim import GustParams, SimConfig, simulate
from mock_vehicle.plant import WindParams, euler_maruyama_step

DT_S, SUB_S = 0.5, 0.1          # the control period and the simulator's physics sub-step
WIND = WindParams()
C = DEFAULT.cost


def _plant(states, acc, normals_per_sub):
    """One control period of the simulator's plant: SUB_S Euler-Maruyama sub-steps under a held acceleration."""
    s = states
    for k in range(int(round(DT_S / SUB_S))):
        s = euler_maruyama_step(s, acc, SUB_S, WIND, normals_per_sub[k])
    return s


def _random_case(rng, n):
    states = np.concatenate([rng.uniform(-50, 50, (n, 2)), rng.uniform(-5, 5, (n, 2))], axis=1)
    acc = rng.uniform(-1.0, 1.0, (n, 2))
    return states, acc


def test_the_residual_of_a_noise_free_period_is_zero():
    rng = np.random.default_rng(11)
    s0, acc = _random_case(rng, 200)
    s1 = _plant(s0, acc, np.zeros((5, 200, 2)))
    r = disturbance_residual_m_s2(s1[:, 2:4], s0[:, 2:4], acc, DT_S, C.c0_per_s, C.v_o)
    # the model's trapezoidal drag against the plant's five Euler sub-steps: (0.95122 - 0.95099) |v - v_o - a / c0| / dt,
    # 0.007 m/s^2 for these states (|a| / c0 up to 14 m/s); allowed 0.02 m/s^2, < 7 % of the 0.3 m/s^2 deadband
    assert np.max(np.abs(r)) < 0.02, np.max(np.abs(r))


def test_the_residual_recovers_an_acceleration_beyond_the_model():
    # a gust: an extra constant acceleration g the command does not hold; the residual is g
    rng = np.random.default_rng(12)
    s0, acc = _random_case(rng, 200)
    g = rng.uniform(-1.5, 1.5, (200, 2))
    s1 = _plant(s0, acc + g, np.zeros((5, 200, 2)))
    r = disturbance_residual_m_s2(s1[:, 2:4], s0[:, 2:4], acc, DT_S, C.c0_per_s, C.v_o)
    assert np.max(np.abs(r - g)) < 0.02        # as above (measured 0.013: |a + g| / c0 up to 25 m/s)


def test_the_modelled_wind_noise_alone_stays_inside_the_deadband():
    # V_o's noise alone, smoothed as the controller smooths it: std per axis |V_o| sqrt(dt) / dt sqrt((1 - lam) / (1 + lam))
    # = 0.0816 m/s^2 (lam = 0.5), so the feedforward is almost never engaged (fixed seed; tolerances stated below)
    tp = DEFAULT.tracking
    lam, band = tp.disturbance_smoothing, tp.disturbance_deadband_m_s2
    rng = np.random.default_rng(13)
    n, steps = 400, 200
    s = np.concatenate([np.zeros((n, 2)), rng.uniform(-3, 3, (n, 2))], axis=1)
    d_hat = np.zeros((n, 2))
    hat_all, engaged = [], 0
    for _ in range(steps):
        acc = np.zeros((n, 2))
        s1 = _plant(s, acc, rng.standard_normal((5, n, 2)))
        d_hat = lam * d_hat + (1 - lam) * disturbance_residual_m_s2(s1[:, 2:4], s[:, 2:4], acc, DT_S, C.c0_per_s, C.v_o)
        hat_all.append(d_hat.copy())
        engaged += int(np.count_nonzero(np.any(shrink_m_s2(d_hat, band) != 0, axis=1)))
        s = s1
    std = float(np.std(np.concatenate(hat_all[5:])))
    assert std == pytest.approx(0.1 * np.sqrt(DT_S) / DT_S * np.sqrt((1 - lam) / (1 + lam)), rel=0.05)
    # Rayleigh tail exp(-band^2 / (2 std^2)) = 1.2e-3 of the vehicle-steps; allowed: 3e-3
    assert engaged / (n * steps) < 3e-3, engaged / (n * steps)


def test_shrink_drops_the_deadband_and_keeps_the_direction():
    d = np.array([[0.0, 0.0], [0.1, -0.2], [3.0, 4.0], [-0.3, 0.0]])
    out = shrink_m_s2(d, 0.3)
    assert np.all(out[[0, 1, 3]] == 0.0)
    np.testing.assert_allclose(out[2], np.array([3.0, 4.0]) * (4.7 / 5.0))


def test_a_smoothing_or_deadband_out_of_range_is_refused_naming_it():
    with pytest.raises(ValueError, match="disturbance_smoothing"):
        dataclasses.replace(DEFAULT.tracking, disturbance_smoothing=1.0)
    with pytest.raises(ValueError, match="disturbance_deadband_m_s2"):
        dataclasses.replace(DEFAULT.tracking, disturbance_deadband_m_s2=-0.1)


def test_the_feedforward_holds_the_vehicles_nearer_their_particles_in_a_gust():
    # paper N = 64 --gust (1 m/s^2 +- 50 %, 20-25 s), 60 steps: the largest tracking error of any UAV (metrics
    # "guarantee"), measured 3.45 m without the feedforward, 2.14 m with it; asserted: at most 3/4 of it. (It is off by
    # default: the same flight's smallest separation fell 1.04 -> 0.76 m; TrackingParams.disturbance_feedforward.)
    def fly(on):
        # held (no inner loop), as measured: the inner loop fights the gust inside the period itself (largest tracking
        # error 0.73 m with or without the feedforward)
        pre = dataclasses.replace(DEFAULT, tracking=dataclasses.replace(DEFAULT.tracking, disturbance_feedforward=on,
                                                                        inner_loop=False))
        # (the paper's plant, as this was measured: with PX4's lag the feedforward's comparison does not hold (tracking errors 8.5 and 9.8 m); issue 18)
        return simulate(SimConfig(scenario=make_scenario("paper", 64), mode="mfg", preset=pre, seed=3, steps=60,
                                  gust=GustParams(), acc_lag_s=0.0), progress=False)[1]
    off, on = fly(False), fly(True)
    assert on["collision_pairs"] == 0
    assert on["guarantee"]["tracking_error_max_m"] <= 0.75 * off["guarantee"]["tracking_error_max_m"], (on["guarantee"], off["guarantee"])
