"""The eq. 9 plant: OU wind statistics, per-vehicle noise streams, Euler-Maruyama."""

import numpy as np
import pytest

from mock_vehicle.plant import NoiseStream, PlantParams, SwarmPlant, WindParams, euler_maruyama_step, saturate_norm


def test_ou_stationary_velocity_variance():
    # Given 4000 vehicles with a = 0 for 200 s (h = 0.1 s sub-steps), seed 7.
    params = PlantParams(physics_dt_s=0.1)
    plant = SwarmPlant(np.zeros((4000, 2)), params, seed=7)
    for _ in range(200):
        plant.step(np.zeros((4000, 2)), 1.0)
    v = plant.states[:, 2:4]
    w = params.wind
    h = 0.1
    # Euler-Maruyama's stationary variance of eq. 1: V^2 h / (1 - (1 - c0 h)^2) (-> V^2/(2 c0) as h -> 0)
    var_expected = 0.1**2 * h / (1 - (1 - w.c0_per_s * h) ** 2)
    assert abs(var_expected - 0.05) < 0.001
    # Then: the sample variance per axis is within 8 % (~3.6 standard errors for 4000 samples)
    np.testing.assert_allclose(v.var(axis=0), var_expected, rtol=0.08)
    # and the mean is the average wind v_o within 4 standard errors
    np.testing.assert_allclose(v.mean(axis=0), w.v_o, atol=4 * np.sqrt(var_expected / 4000))


def test_a_vehicle_moves_the_same_whichever_process_simulates_it():
    params = PlantParams()
    pos = np.array([[0.0, 0.0], [5.0, 1.0], [9.0, -3.0]])
    swarm = SwarmPlant(pos, params, seed=3)
    alone = SwarmPlant(pos[1:2], params, seed=3, vehicle_ids=np.array([1]))
    rng = np.random.default_rng(0)
    for _ in range(20):
        a = rng.normal(size=(3, 2))
        swarm.step(a, 1.0)
        alone.step(a[1:2], 1.0)
    np.testing.assert_array_equal(swarm.states[1], alone.states[0])


def test_noise_stream_chunking_is_invisible():
    a, b = NoiseStream(5, 2, chunk=7), NoiseStream(5, 2, chunk=1000)
    np.testing.assert_array_equal(np.concatenate([a.normals(3) for _ in range(50)]), b.normals(150))


def test_euler_maruyama_without_noise_is_the_nominal_drift():
    w = WindParams()
    s = np.array([[10.0, 20.0, 1.0, 2.0]])
    a = np.array([[0.5, -0.5]])
    out = euler_maruyama_step(s, a, 0.5, w, np.zeros((1, 2)))
    np.testing.assert_allclose(out[0, :2], [10.5, 21.0])
    np.testing.assert_allclose(out[0, 2:], [1.0 + (0.5 - 0.1 * (1.0 - 1.0)) * 0.5, 2.0 + (-0.5 - 0.1 * (2.0 + 1.0)) * 0.5])


def test_acceleration_is_limited_and_must_be_finite():
    plant = SwarmPlant(np.zeros((1, 2)), PlantParams(acc_limit_m_s2=2.0), seed=0)
    applied = plant.step(np.array([[30.0, 40.0]]), 1.0)
    np.testing.assert_allclose(np.linalg.norm(applied), 2.0)
    np.testing.assert_allclose(saturate_norm(np.array([[0.3, 0.4]]), 1.0), [[0.3, 0.4]])
    with pytest.raises(ValueError, match="finite"):
        plant.step(np.array([[np.nan, 0.0]]), 1.0)
