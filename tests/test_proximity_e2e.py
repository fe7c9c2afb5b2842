"""The default preset's proximity backstop through `mfg-swarm run --lockstep` (world process,
mock vehicles forwarding ADSB_VEHICLE, controllers over MAVLink and Zenoh) equals
`mfg-swarm sim`: same flight, same sensed sets, same backstop activity (docs/proximity.md)."""

import json
import subprocess
import sys

import numpy as np
import psutil
import pytest

import mfg_swarm.sim as sim_mod
from mfg_autopilot.presets import preset_by_name
from mfg_swarm.results import load_trajectories
from mfg_swarm.scenarios import make_scenario
from mfg_swarm.sim import SimConfig, as_f32, simulate
from mock_vehicle.proximity import sensed_pairs, sensed_rows

pytestmark = pytest.mark.e2e

POS_TOL_M = 1e-3


def _simulate_recording_backstop(monkeypatch, **kw):
    """simulate(), also returning each step's backstop_active (steps, n)."""
    rows = []
    make = sim_mod.make_controller

    def recording(*a, **k):
        ctrl = make(*a, **k)
        step = ctrl.step

        def wrapped(obs):
            info = step(obs)
            rows.append(np.asarray(ctrl.backstop_active, dtype=bool).copy())
            return info

        ctrl.step = wrapped
        return ctrl

    monkeypatch.setattr(sim_mod, "make_controller", recording)
    traj, m = simulate(SimConfig(**kw), progress=False)
    return traj, m, np.array(rows)


# MFG flies a rigid plan in both scenarios (its backstop answers only vehicles off the plan: none here); HJB_0.3 in the
# 0.5 m dense grid hears nobody and senses everybody, so its backstop acts (on the paper's plant: with PX4's lag, the
# default airframe, this flight's backstop does not act in 12 steps, so both paths fly --acc-lag-s 0 here)
@pytest.mark.parametrize("scenario,seed,steps,mode,expect_backstop", [("paper", 0, 16, "mfg", False),
                                                                      ("dense", 3, 12, "hjb", True)])
def test_lockstep_default_preset_with_proximity_sensor_equals_the_simulator(tmp_path, monkeypatch, scenario, seed, steps,
                                                                           mode, expect_backstop):
    n = 9
    out = tmp_path / "run"
    before = {p.pid for p in psutil.Process().children(recursive=True)}
    proc = subprocess.run([sys.executable, "-m", "mfg_swarm.cli", "run", "--out", str(out), "--no-progress", "--no-plot",
                           "--lockstep", "--preset", "default", "--scenario", scenario, "--n", str(n), "--mode", mode,
                           *(["--range-m", "0.3"] if mode == "hjb" else []), "--seed", str(seed), "--steps", str(steps), "--acc-lag-s", "0"], capture_output=True, text=True, timeout=240)
    assert proc.returncode == 0, proc.stderr[-3000:]
    left = [p for p in psutil.Process().children(recursive=True)
            if p.pid not in before and p.is_running() and p.status() != psutil.STATUS_ZOMBIE]
    assert not left, f"processes left behind: {[p.cmdline()[:4] for p in left]}"
    m_p = json.loads((out / "metrics.json").read_text())
    assert not m_p["partial"] and (out / "stderr" / "world.log").exists()

    traj_s, m_s, act_s = _simulate_recording_backstop(monkeypatch, scenario=make_scenario(scenario, n), mode=mode,
                                                      range_m=0.3 if mode == "hjb" else None,
                                                      preset=preset_by_name("default"), seed=seed, steps=steps,
                                                      acc_lag_s=0.0)
    traj_p = load_trajectories(out / "trajectories.npz")
    assert traj_p.pos_m.shape == traj_s.pos_m.shape
    assert np.max(np.abs(traj_p.pos_m - traj_s.pos_m)) < POS_TOL_M
    assert np.max(np.abs(traj_p.vel_m_s - traj_s.vel_m_s)) < POS_TOL_M
    np.testing.assert_allclose(traj_p.acc_m_s2, traj_s.acc_m_s2, atol=1e-6)

    # every controller had the sensor, and sensed at each step exactly the simulator's set
    act_p = np.zeros((steps, n), dtype=bool)
    for i in range(n):
        recs = [json.loads(line) for line in (out / "controllers" / f"controller{i}.jsonl").read_text().splitlines()]
        assert any(r.get("what") == "proximity_sensor" and r.get("present") for r in recs)
        for r in (r for r in recs if r["type"] == "step"):
            k = r["step"]
            obs = as_f32(np.hstack([traj_s.pos_m[k], traj_s.vel_m_s[k]]))
            owner, other = sensed_rows(sensed_pairs(obs, preset_by_name("default").backstop.sensor_range_m))
            assert r["sensed_ids"] == other[owner == i].tolist(), (i, k)
            act_p[k, i] = r["backstop_active"]
    np.testing.assert_array_equal(act_p, act_s)
    assert m_p["backstop_activations"] == m_s["backstop_activations"] == int(act_s.sum())
    assert (m_s["backstop_activations"] > 0) == expect_backstop
    # and the same layer made each command (safety.backstop.Layer: the controllers' logs carry it to the launcher)
    np.testing.assert_array_equal(traj_p.extra["backstop_layer"], traj_s.extra["backstop_layer"])
    assert m_p["safety_interventions_by_layer"] == m_s["safety_interventions_by_layer"]
    assert (m_p["safety_interventions_by_layer"]["planned"] > 0) == expect_backstop     # HJB_d's reciprocal push
    for k in ("collision_pairs", "comm_states_per_uav"):
        assert m_p[k] == m_s[k], k


def test_realtime_swarm_forwards_traffic_to_every_controller(tmp_path):
    """Real time: the world answers from the latest truth; every controller's steps see the
    others (the paper grid lies within the 10 m sensor range)."""
    n, out = 4, tmp_path / "rt"
    before = {p.pid for p in psutil.Process().children(recursive=True)}
    proc = subprocess.run([sys.executable, "-m", "mfg_swarm.cli", "run", "--out", str(out), "--no-progress", "--no-plot",
                           "--realtime", "--preset", "default", "--scenario", "paper", "--n", str(n), "--mode", "mfg",
                           "--steps", "6"], capture_output=True, text=True, timeout=180)
    assert proc.returncode == 0, proc.stderr[-3000:]
    left = [p for p in psutil.Process().children(recursive=True)
            if p.pid not in before and p.is_running() and p.status() != psutil.STATUS_ZOMBIE]
    assert not left, f"processes left behind: {[p.cmdline()[:4] for p in left]}"
    for i in range(n):
        recs = [json.loads(line) for line in (out / "controllers" / f"controller{i}.jsonl").read_text().splitlines()]
        steps = [r for r in recs if r["type"] == "step"]
        assert len(steps) == 6
        assert all(r["sensed_ids"] == [j for j in range(n) if j != i] for r in steps), i
