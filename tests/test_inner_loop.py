"""The telemetry-rate inner loop (``mfg_autopilot/guidance/inner_loop.py``, ``TrackingParams.inner_loop``,
``sim --inner-loop``, ``mfg-autopilot --inner-loop``): between control steps each vehicle tracks the trajectory its
period's command promised, against the airframe's acceleration lag."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from mfg_autopilot.guidance.inner_loop import InnerLoop, inner_acc_m_s2, reference_state
from mfg_autopilot.presets import preset_by_name, with_inner_loop
from mfg_autopilot.runtime.config import AutopilotConfig
from mfg_swarm.cli import main as swarm_main
from mfg_swarm.scenarios import make_scenario
from mfg_swarm.sim import GustParams, SimConfig, simulate
from mock_vehicle.plant import PlantParams, SwarmPlant, WindParams

DEFAULT = preset_by_name("default")


def _euler_reference(r0, v0, a, t_s, c0, v_o, h=1e-5):
    r, v = np.array(r0, dtype=float), np.array(v0, dtype=float)
    for _ in range(int(round(t_s / h))):
        r, v = r + v * h, v + (a - c0 * (v - v_o)) * h
    return r, v


@pytest.mark.parametrize("c0", [0.1, 0.0, 2.0])
def test_the_reference_is_eq_9_without_noise_with_the_command_held(c0):
    r0, v0, a, v_o = np.array([[1.0, -2.0]]), np.array([[3.0, 0.5]]), np.array([[-1.5, 0.7]]), np.array([1.0, -1.0])
    r, v = reference_state(r0, v0, a, 0.5, c0, v_o)
    r_e, v_e = _euler_reference(r0, v0, a, 0.5, c0, v_o)
    np.testing.assert_allclose(r, r_e, atol=1e-5)
    np.testing.assert_allclose(v, v_e, atol=1e-5)
    # at t = 0 it is the start state, and a time per row is taken row by row
    r, v = reference_state(np.vstack([r0, r0]), np.vstack([v0, v0]), np.vstack([a, a]), np.array([0.0, 0.5]), c0, v_o)
    np.testing.assert_allclose(r[0], r0[0])
    np.testing.assert_allclose(v[0], v0[0])
    np.testing.assert_allclose(r[1], r_e[0], atol=1e-5)


def test_on_its_reference_the_vehicle_flies_the_command_and_off_it_is_pulled_back_within_the_limit():
    a = np.array([[0.5, -0.25]])
    r, v = np.array([[2.0, 3.0]]), np.array([[1.0, 1.0]])
    np.testing.assert_array_equal(inner_acc_m_s2(a, r, v, r, v, 4.0, 4.0, 2.0), a)
    # 0.1 m behind along x and 0.2 m/s slow: + 4 x 0.1 + 4 x 0.2 = + 1.2 m/s^2
    np.testing.assert_allclose(inner_acc_m_s2(a, r, v, r - [0.1, 0.0], v - [0.2, 0.0], 4.0, 4.0, 10.0), [[1.7, -0.25]])
    far = inner_acc_m_s2(a, r, v, r - [10.0, 0.0], v, 4.0, 4.0, 2.0)
    assert np.linalg.norm(far) == pytest.approx(2.0)


def test_the_inner_loop_needs_a_start_and_sane_gains():
    loop = InnerLoop(4.0, 4.0, 0.1, np.array([1.0, -1.0]), 2.0)
    assert not loop.started
    with pytest.raises(RuntimeError):
        loop.acc_m_s2(0.0, np.zeros((1, 4)))
    loop.start(3.0, np.array([[0.0, 0.0, 1.0, 0.0]]), np.array([[0.3, 0.0]]))
    assert loop.started and loop.start_time_s == 3.0
    # at the step's own sample the command is the step's
    np.testing.assert_allclose(loop.acc_m_s2(3.0, np.array([[0.0, 0.0, 1.0, 0.0]])), [[0.3, 0.0]])
    with pytest.raises(ValueError):
        InnerLoop(-1.0, 4.0, 0.1, np.zeros(2), 2.0)
    with pytest.raises(ValueError, match="inner_kd_per_s"):
        dataclasses.replace(DEFAULT.tracking, inner_kd_per_s=float("nan"))


def _flown_against_a_lag(lag_s: float, inner: bool, periods: int = 40) -> tuple[float, float]:
    """One vehicle, no wind, a command that turns every period (the hardest for a lag): the largest distance and
    velocity difference between the state at each step and the one the model promised the step's command would give."""
    calm = WindParams(c0_per_s=0.1, mean_wind_m_s=(0.0, 0.0), wind_diffusion_m_s=((0.0, 0.0), (0.0, 0.0)))
    plant = SwarmPlant(np.zeros((1, 2)), PlantParams(wind=calm, acc_lag_s=lag_s), seed=0, vehicle_ids=np.array([0]),
                       initial_vel_m_s=np.zeros((1, 2)))
    loop = InnerLoop(4.0, 4.0, 0.1, np.zeros(2), 2.0)
    worst_r = worst_v = 0.0
    dt, h = 0.5, 0.1
    for k in range(periods):
        a = np.array([[np.cos(1.3 * k), np.sin(1.3 * k)]]) * 1.5
        start = plant.states.copy()
        loop.start(k * dt, start, a)
        for j in range(5):
            plant.step(loop.acc_m_s2(k * dt + j * h, plant.states) if inner else a, h)
        r_ref, v_ref = reference_state(start[:, 0:2], start[:, 2:4], a, dt, 0.1, np.zeros(2))
        worst_r = max(worst_r, float(np.linalg.norm(plant.states[0, 0:2] - r_ref[0])))
        worst_v = max(worst_v, float(np.linalg.norm(plant.states[0, 2:4] - v_ref[0])))
    return worst_r, worst_v


def test_against_the_lag_the_vehicle_ends_each_period_at_the_velocity_its_command_promised():
    # Given PX4's nominal lag (0.154 s) and a command that turns by 75 degrees every period
    (held_r, held_v), (tracked_r, tracked_v) = _flown_against_a_lag(0.154, False), _flown_against_a_lag(0.154, True)
    # Then held, each period ends slower than the command promised by ~tau x the change (0.26 m/s here) ...
    assert held_v > 0.2
    # ... and with the inner loop by less than half that; the position is not worse (the deficit of the period's first
    # sub-step, before the loop has a sample, stays: ~0.1 m either way)
    assert tracked_v < 0.5 * held_v and tracked_r <= held_r
    # And without a lag the inner loop changes little: 0.02 m/s is the plant's Euler sub-steps against the exact model
    assert _flown_against_a_lag(0.0, True)[1] < 0.03


def test_in_the_simulator_the_inner_loop_restores_the_tracking_the_lag_took():
    # Given the 0.5 m pad (dense, N = 64) on PX4's lag, calm (seed 41: no test or tuning flew it)
    def fly(inner: bool):
        preset = with_inner_loop(DEFAULT, inner)
        _, m = simulate(SimConfig(make_scenario("dense", 64, 41), "mfg", preset, seed=41, steps=200, acc_lag_s=0.154),
                        progress=False)
        return m
    held, tracked = fly(False), fly(True)
    # Then the UAVs stay closer to their plan particles with the inner loop (largest tracking error over the flight)
    assert tracked["guarantee"]["tracking_error_max_m"] < 0.5 * held["guarantee"]["tracking_error_max_m"]
    assert tracked["collision_pairs"] == 0 and tracked["arrived_fraction"] == 1.0
    # and the metrics say it flew
    assert tracked["inner_loop"] == {"kp_per_s2": 4.0, "kd_per_s": 4.0} and "inner_loop" not in held


def test_with_the_inner_loop_a_gust_is_met_inside_the_period():
    # the gust acts at every physics sub-step (not added after the period): the same total push, the inner loop sees it
    def fly(inner: bool):
        _, m = simulate(SimConfig(make_scenario("paper", 36, 43), "mfg", with_inner_loop(DEFAULT, inner), seed=43,
                                  steps=160, gust=GustParams(), acc_lag_s=0.154), progress=False)
        return m
    held, tracked = fly(False), fly(True)
    assert tracked["collision_pairs"] == 0 and tracked["gust"]["acc_m_s2"] > 0
    # fought at telemetry rate, the gust blows the UAVs off their particles far less (6.4 m held, 0.61 m measured)
    assert tracked["guarantee"]["tracking_error_max_m"] < 0.3 * held["guarantee"]["tracking_error_max_m"]


def test_a_preset_without_the_default_guidance_has_no_inner_loop(tmp_path, capsys):
    with pytest.raises(ValueError, match="no inner loop"):
        with_inner_loop(preset_by_name("paper"))
    # the simulator's command line says so before flying
    assert swarm_main(["sim", "--preset", "paper", "--inner-loop", "--n", "4", "--steps", "2", "--out", str(tmp_path / "s")]) == 2
    assert "no inner loop" in capsys.readouterr().err
    assert not (tmp_path / "s").exists()


class _SubStepLink:
    """What Autopilot._lockstep_inner needs of a VehicleLink: a lockstep vehicle that answers a setpoint stamped t
    with the position at t + step_ms (moving at 1 m/s north), and records the setpoints."""

    def __init__(self, step_ms: int) -> None:
        self.step_ms, self.sent = step_ms, []

    def send_acc_setpoint(self, sp, t_ms, z_m=None):
        self.sent.append((t_ms, sp))
        return 0.0

    def wait_local_position(self, after_ms, timeout_s):
        from mavlink_bridge import LocalPositionNed

        t = after_ms + self.step_ms
        return LocalPositionNed(t, t / 1000.0, 0.0, 0.0, 1.0, 0.0, 0.0)


def _lockstep_autopilot(link):
    import threading

    from mfg_autopilot.runtime.autopilot import Autopilot, ControllerLog

    cfg = AutopilotConfig(instance=0, connect="udpin:127.0.0.1:1", mode="mfg", n=1, lockstep=True, inner_loop=True,
                          sites_m=((100.0, 0.0),))
    return Autopilot(cfg, link, None, ControllerLog(None), threading.Event())


def test_lockstep_sub_steps_get_the_inner_loops_commands_stamped_with_their_own_time():
    # Given a lockstep vehicle stepped by 0.1 s sub-steps, a control step at t = 1.0 s whose command was 0.5 m/s^2 north
    link = _SubStepLink(100)
    ap = _lockstep_autopilot(link)
    state0, acc0 = np.array([1.0, 0.0, 1.0, 0.0]), np.array([0.5, 0.0])
    from mavlink_bridge import LocalPositionNed

    p = ap._lockstep_inner(LocalPositionNed(1100, 1.1, 0.0, 0.0, 1.0, 0.0, 0.0), 1000, 1500, state0, acc0)
    # Then the sub-steps 1.1-1.4 s each got one setpoint stamped with its own time, and the next step's position is back
    assert [t for t, _ in link.sent] == [1100, 1200, 1300, 1400] and p.time_boot_ms == 1500
    assert ap.inner_setpoints == 4
    # each the command corrected towards the reference from (state0, acc0) at that time (the vehicle here holds 1 m/s
    # and is behind the reference, which accelerates): more than the step's 0.5 m/s^2 north, growing
    north = [sp[0] for _, sp in link.sent]
    loop = InnerLoop(4.0, 4.0, DEFAULT.cost.c0_per_s, DEFAULT.cost.v_o, DEFAULT.learner.acc_max_m_s2)
    loop.start(1.0, state0.reshape(1, 4), acc0.reshape(1, 2))
    want = [loop.acc_m_s2(t / 1000.0, np.array([[t / 1000.0, 0.0, 1.0, 0.0]]))[0, 0] for t in (1100, 1200, 1300, 1400)]
    np.testing.assert_allclose(north, want, rtol=1e-12)
    assert all(a > 0.5 for a in north) and north == sorted(north)


def test_a_lockstep_vehicle_stepping_whole_periods_leaves_the_inner_loop_idle_and_says_so():
    link = _SubStepLink(500)
    ap = _lockstep_autopilot(link)
    events = []
    ap.clog.event = lambda what, **kw: events.append(what)
    from mavlink_bridge import LocalPositionNed

    p = ap._lockstep_inner(LocalPositionNed(1500, 1.5, 0.0, 0.0, 1.0, 0.0, 0.0), 1000, 1500, np.zeros(4), np.zeros(2))
    assert p.time_boot_ms == 1500 and link.sent == [] and events == ["inner_loop_idle"]


@pytest.mark.e2e
def test_a_lockstep_process_swarm_with_the_inner_loop_and_the_lag_flies_the_simulators_flight(tmp_path):
    # Given nine default-preset UAVs as processes in lockstep, the mocks with PX4's lag and stepped by sub-steps
    from mfg_swarm.results import load_trajectories

    out = tmp_path / "ls"
    assert swarm_main(["run", "--inner-loop", "--acc-lag-s", "0.154", "--n", "9", "--seed", "3", "--steps", "40",
                       "--out", str(out), "--no-progress", "--no-plot"]) == 0
    flown = load_trajectories(out / "trajectories.npz")
    sim, _ = simulate(SimConfig(make_scenario("paper", 9), "mfg", with_inner_loop(DEFAULT), seed=3, steps=40,
                                acc_lag_s=0.154), progress=False)
    # Then they fly the simulator's flight: within the float32 telemetry's resolution (7.6e-6 m measured), the step's
    # acceleration the mean of its sub-steps' setpoints
    assert np.max(np.abs(flown.pos_m - sim.pos_m)) < 1e-3
    assert np.max(np.abs(flown.vel_m_s - sim.vel_m_s)) < 1e-3
    np.testing.assert_allclose(flown.acc_m_s2, sim.acc_m_s2, atol=1e-6)


@pytest.mark.e2e
def test_a_real_time_process_flies_the_inner_loop_against_the_lag(tmp_path):
    # Given one mock vehicle with PX4's lag and its controller in real time with the inner loop (real processes,
    # MAVLink over loopback UDP)
    import json

    out = tmp_path / "rt"
    rc = swarm_main(["run", "--realtime", "--inner-loop", "--acc-lag-s", "0.154", "--n", "1", "--steps", "30",
                     "--out", str(out), "--no-progress", "--no-plot"])
    assert rc == 0
    recs = [r for r in map(json.loads, (out / "controllers" / "controller0.jsonl").read_text().splitlines())
            if r["type"] == "step"]
    # Then between steps the controller sent setpoints at the telemetry's rate (LOCAL_POSITION_NED at ~30 Hz: ~14 per
    # 0.5 s period; at least 3 counts even a loaded machine) ...
    assert len(recs) >= 25 and np.median([r["inner_setpoints"] for r in recs[:-1]]) >= 3
    # ... and the UAV kept to its plan particle through the departure's acceleration (within the 0.5 m leash)
    err = max(float(np.hypot(r["state"][0] - r["plan_pos_m"][0], r["state"][1] - r["plan_pos_m"][1])) for r in recs)
    assert err < 0.5, err
