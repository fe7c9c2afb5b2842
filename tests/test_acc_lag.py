"""The airframe's acceleration response lag (``PlantParams.acc_lag_s``, ``sim --acc-lag-s``, ``mock-vehicle
--acc-lag-s`` / SIM_ACC_TAU): a first-order lag between the command and the acceleration flown, as PX4's attitude
loop makes one (MC_ROLL_P = 6.5 /s: ~0.154 s)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mfg_autopilot.presets import preset_by_name
from mfg_swarm.scenarios import make_scenario
from mfg_swarm.sim import SimConfig, simulate
from mock_vehicle.cli import build_parser, config_from_args
from mock_vehicle.plant import PlantParams, SwarmPlant, WindParams, lag_coefficients

DEFAULT = preset_by_name("default")
CALM = WindParams(c0_per_s=1e-4, mean_wind_m_s=(0.0, 0.0), wind_diffusion_m_s=((0.0, 0.0), (0.0, 0.0)))


def _step_response(lag_s: float, t_s: float = 1.0, dt_s: float = 0.5):
    plant = SwarmPlant(np.zeros((1, 2)), PlantParams(wind=CALM, acc_lag_s=lag_s), seed=0,
                       vehicle_ids=np.array([0]), initial_vel_m_s=np.zeros((1, 2)))
    for _ in range(int(round(t_s / dt_s))):
        plant.step(np.array([[1.0, 0.0]]), dt_s)
    return plant


@pytest.mark.parametrize("lag_s", [0.05, 0.154, 0.3])
def test_a_step_command_is_flown_as_a_first_order_lag(lag_s):
    # Given a vehicle at rest, no wind, a 1 m/s^2 command held for 1 s.
    plant = _step_response(lag_s)
    # Then the acceleration flown is 1 - exp(-t / tau) (exact: the lag is solved over each sub-step) ...
    assert plant.acc_flown_m_s2[0, 0] == pytest.approx(-math.expm1(-1.0 / lag_s), abs=1e-12)
    # ... and the velocity its integral t - tau (1 - exp(-t / tau)), up to the 1e-4 /s drag left in the wind model
    assert plant.states[0, 2] == pytest.approx(1.0 - lag_s * -math.expm1(-1.0 / lag_s), abs=2e-4)
    # which is behind the command's own velocity (1 m/s without the lag) by about tau
    assert _step_response(0.0).states[0, 2] - plant.states[0, 2] == pytest.approx(lag_s, rel=0.05)


def test_no_lag_is_the_paper_plant_bit_for_bit():
    pos = np.array([[0.0, 0.0], [5.0, 1.0], [9.0, -3.0]])
    a, b = SwarmPlant(pos, PlantParams(), seed=3), SwarmPlant(pos, PlantParams(acc_lag_s=0.0), seed=3)
    rng = np.random.default_rng(0)
    for _ in range(20):
        acc = rng.normal(size=(3, 2))
        np.testing.assert_array_equal(a.step(acc, 0.5), b.step(acc, 0.5))
    np.testing.assert_array_equal(a.states, b.states)
    assert lag_coefficients(0.1, 0.0) == (1.0, 1.0)


def test_with_a_lag_a_vehicle_moves_the_same_whichever_process_simulates_it():
    # the mock process's one-vehicle path (Python floats) and the simulator's vectorised one agree bit for bit
    params = PlantParams(acc_lag_s=0.154)
    pos = np.array([[0.0, 0.0], [5.0, 1.0], [9.0, -3.0]])
    swarm = SwarmPlant(pos, params, seed=3)
    alone = [SwarmPlant(pos[i:i + 1], params, seed=3, vehicle_ids=np.array([i])) for i in range(3)]
    rng = np.random.default_rng(1)
    for _ in range(30):
        acc = rng.normal(size=(3, 2)) * 1.5
        swarm.step(acc, 0.5)
        for i in range(3):
            alone[i].step(acc[i:i + 1], 0.5)
    np.testing.assert_array_equal(swarm.states, np.vstack([p.states for p in alone]))
    np.testing.assert_array_equal(swarm.acc_flown_m_s2, np.vstack([p.acc_flown_m_s2 for p in alone]))
    # and the lag changed the flight
    plain = SwarmPlant(pos, PlantParams(), seed=3)
    rng = np.random.default_rng(1)
    for _ in range(30):
        plain.step(rng.normal(size=(3, 2)) * 1.5, 0.5)
    assert np.abs(plain.states - swarm.states).max() > 0.1


@pytest.mark.parametrize("bad", [-0.1, 2.5, math.nan, math.inf])
def test_the_lag_is_checked(bad):
    with pytest.raises(ValueError, match="acc_lag_s"):
        PlantParams(acc_lag_s=bad)
    with pytest.raises(ValueError, match="--acc-lag-s"):
        config_from_args(build_parser().parse_args(["--acc-lag-s", str(bad)]))


def test_the_mock_takes_the_lag_from_its_command_line_and_its_parameter():
    from mock_vehicle.vehicle import MockVehicle
    from mavlink_bridge import ParamSet, Received

    cfg, _ = config_from_args(build_parser().parse_args(["--acc-lag-s", "0.154"]))
    v = MockVehicle(cfg, lambda msg, port: None, clock=lambda: 1000.0)
    assert v.plant.params.acc_lag_s == 0.154 and v.params["SIM_ACC_TAU"] == pytest.approx(0.154)
    v.handle(Received(ParamSet(1, 1, "SIM_ACC_TAU", 0.25), 1, 195))
    assert v.plant.params.acc_lag_s == pytest.approx(0.25)
    v.handle(Received(ParamSet(1, 1, "SIM_ACC_TAU", -1.0), 1, 195))     # out of range: refused, as PX4 refuses
    assert v.plant.params.acc_lag_s == pytest.approx(0.25)


def test_a_swarm_flight_with_the_lag_is_flown_and_named():
    sc = make_scenario("paper", 16, 0)
    m0 = simulate(SimConfig(scenario=sc, mode="mfg", preset=DEFAULT, seed=0, steps=60, acc_lag_s=0.0), progress=False)[1]
    m1 = simulate(SimConfig(scenario=sc, mode="mfg", preset=DEFAULT, seed=0, steps=60), progress=False)[1]
    # the default guidance flies PX4's lag by default, the paper's preset none (sim.airframe_acc_lag_s)
    assert m0["acc_lag_s"] == 0.0 and m1["acc_lag_s"] == 0.154
    assert SimConfig(scenario=sc, mode="mfg", preset=preset_by_name("paper")).acc_lag_s == 0.0
    assert m1["min_separation_m"] != m0["min_separation_m"]     # the lag reached the plant
    assert m1["collision_pairs"] == 0


def test_the_simulator_checks_the_lag_before_flying():
    with pytest.raises(ValueError, match="acc_lag_s"):
        SimConfig(scenario=make_scenario("paper", 4, 0), mode="mfg", preset=DEFAULT, acc_lag_s=-0.5)


def test_a_vehicle_on_the_ground_carries_no_tilt_into_its_next_flight():
    # the lag's state is the acceleration flown (the tilt): landing levels it, so a takeoff does not start tilted
    from mock_vehicle.vehicle import MockVehicle

    cfg, _ = config_from_args(build_parser().parse_args(["--acc-lag-s", "0.154", "--start", "ground"]))
    v = MockVehicle(cfg, lambda msg, port: None, clock=lambda: 1000.0)
    v.plant.acc_flown_m_s2[:] = 1.5                  # as after a flight
    v._touch_down()
    np.testing.assert_array_equal(v.plant.acc_flown_m_s2, np.zeros((1, 2)))
    v.plant.acc_flown_m_s2[:] = 1.5
    v._lift_off()
    np.testing.assert_array_equal(v.plant.acc_flown_m_s2, np.zeros((1, 2)))


@pytest.mark.parametrize("cmd", ["sim", "run"])
def test_the_cli_refuses_a_bad_lag_before_anything_flies(cmd, tmp_path, capsys):
    from mfg_swarm.cli import main

    assert main([cmd, "--n", "4", "--acc-lag-s", "-0.1", "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert "acc-lag-s" in err or "acc_lag_s" in err, err
    assert not (tmp_path / "out").exists()          # refused before any flight (or process) started
