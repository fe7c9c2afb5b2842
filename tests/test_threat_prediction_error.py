"""bench/threat_prediction_error.py: the escape's two hypotheses of a sensed vehicle (constant velocity; braking to a
stop at a_max) against a flown track - exact where the track is one of them, and the other off by the closed form."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest


def _tool():
    spec = importlib.util.spec_from_file_location("tpe", Path(__file__).parents[1] / "bench" / "threat_prediction_error.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


DT_S, A_MAX = 0.5, 2.0


def _braking_track(v0_m_s: float, steps: int) -> tuple[np.ndarray, np.ndarray]:
    """A vehicle that brakes along +x at A_MAX from v0 at t = 0 and then holds, sampled every DT_S."""
    t = np.arange(steps + 1) * DT_S
    tb = np.minimum(t, v0_m_s / A_MAX)
    x = v0_m_s * tb - 0.5 * A_MAX * tb ** 2
    v = v0_m_s - A_MAX * tb
    return np.stack([x, np.zeros_like(x)], axis=1), np.stack([v, np.zeros_like(v)], axis=1)


def test_a_vehicle_braking_at_a_max_is_the_braking_hypothesis():
    # given a vehicle braking from 3 m/s at a_max (it stops after 1.5 s, 2.25 m on)
    pos, vel = _braking_track(3.0, 10)
    # when the tool compares both hypotheses from step 0, 2 s ahead
    (row,) = _tool().prediction_errors(pos, vel, DT_S, range(0, 1), 4, A_MAX)
    # then the braking one is exact and the constant-velocity one is off by v0 t - x(t)
    assert np.allclose(row["braking_m"], 0.0, atol=1e-12)
    t = np.array(row["t_s"])
    tb = np.minimum(t, 1.5)
    assert np.allclose(row["const_vel_m"], 3.0 * t - (3.0 * tb - tb ** 2), atol=1e-12)
    assert row["const_vel_m"][-1] == pytest.approx(6.0 - 2.25)


def test_a_vehicle_at_constant_velocity_is_the_constant_velocity_hypothesis(tmp_path, capsys):
    # given a flight file with one vehicle at constant velocity (and a second one at rest)
    t = np.arange(11) * DT_S
    pos = np.zeros((11, 2, 2))
    pos[:, 0, 0], pos[:, 0, 1] = 1.0 * t, -2.0 * t
    vel = np.zeros((11, 2, 2))
    vel[:, 0] = [1.0, -2.0]
    np.savez(tmp_path / "trajectories.npz", pos_m=pos, vel_m_s=vel, dt_s=np.float64(DT_S))
    # when the tool runs on it as a user would, near the end of the flight
    rows = _tool().main([str(tmp_path), "--vehicle", "0", "--steps", "5-9", "--horizon", "4"])
    # then the constant-velocity hypothesis is exact, the braking one off by 0.5 a t^2 until the stop, and each row has
    # only the horizons the flight still covers
    assert [len(r["t_s"]) for r in rows] == [4, 4, 3, 2, 1]
    for r in rows:
        assert np.allclose(r["const_vel_m"], 0.0, atol=1e-12)
        tb = np.minimum(np.array(r["t_s"]), np.sqrt(5.0) / A_MAX)
        v0 = np.sqrt(5.0)
        assert np.allclose(r["braking_m"], v0 * np.array(r["t_s"]) - (v0 * tb - 0.5 * A_MAX * tb ** 2), atol=1e-12)
    assert "| 5 | 2.5 | 2.24 |" in capsys.readouterr().out


def test_px4_hold_hypothesis_stays_on_its_hold_point_and_brings_a_moving_vehicle_back_to_it():
    tool = _tool()
    from mock_vehicle.plant import WindParams, braking_stop_m
    calm = WindParams(mean_wind_m_s=(0.0, 0.0))
    t = np.arange(0, 41) * 0.5
    # given a vehicle at rest on its Hold point in calm air, then one entering Hold at 4 m/s along +x
    still = tool.hold_hypothesis_m(np.array([3.0, -1.0]), np.zeros(2), np.zeros(2), np.array([3.0, -1.0]), t, wind=calm)
    hold = braking_stop_m(np.array([[0.0, 0.0, 4.0, 0.0]]))[0]
    moving = tool.hold_hypothesis_m(np.zeros(2), np.array([4.0, 0.0]), np.zeros(2), hold, t, wind=calm)
    # then the first stays there, and the second (PX4's jerk-limited stop, not an a_max one) is still ahead of the a_max
    # stop 1.5 s on, passes it, and holds within 5 cm of its Hold point 20 s on, never going sideways
    assert np.abs(still - [3.0, -1.0]).max() < 1e-12
    _, braking = tool.hypotheses_m(np.zeros(2), np.array([4.0, 0.0]), t, A_MAX)
    assert moving[3, 0] > braking[3, 0] + 0.1
    assert moving[:, 0].max() > 4.0 ** 2 / (2 * A_MAX) + 0.5
    assert np.linalg.norm(moving[-1] - hold) < 0.05
    assert np.abs(moving[:, 1]).max() < 1e-12
