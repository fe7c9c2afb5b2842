"""`mfg-swarm sim`: files, keys, determinism, and the paper's communication counts."""

import json
import subprocess
import sys

import numpy as np
import pytest

from mfg_swarm.results import METRIC_KEYS, load_trajectories


def _run(tmp_path, *args):
    out = tmp_path / "out"
    proc = subprocess.run([sys.executable, "-m", "mfg_swarm.cli", "sim", "--out", str(out), *args],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    return out, json.loads((out / "metrics.json").read_text())


@pytest.mark.parametrize("args,comm", [
    (["--mode", "mfg"], lambda m: m == 24.0),                        # N - 1 at t = 0, nothing after
    (["--mode", "hjb", "--range-m", "1"], lambda m: m < 24.0 * 201),
    (["--mode", "hjb", "--range-m", "100"], lambda m: m == 24.0 * 200),   # everyone in range at every step
])
def test_paper_scenario_n25_writes_metrics_and_trajectories(tmp_path, args, comm):
    out, m = _run(tmp_path, "--scenario", "paper", "--n", "25", "--seed", "0", *args)
    assert set(METRIC_KEYS) <= set(m)
    assert m["n"] == 25 and m["steps"] == 200 and m["seed"] == 0
    assert comm(m["comm_states_per_uav"]), m["comm_states_per_uav"]
    traj = load_trajectories(out / "trajectories.npz")
    assert traj.pos_m.shape == (201, 25, 2) and traj.acc_m_s2.shape == (200, 25, 2)
    assert np.all(np.isfinite(traj.pos_m))
    assert np.all(np.linalg.norm(traj.acc_m_s2, axis=2) <= 2.0 + 1e-6)
    # the file and the metrics agree
    assert m["regularizer_activations"] == int(traj.reg_active.sum())


def test_same_seed_same_flight_and_other_seed_other_wind(tmp_path):
    a = tmp_path / "a"; b = tmp_path / "b"; c = tmp_path / "c"
    from mfg_swarm.cli import main
    for out, seed in ((a, 1), (b, 1), (c, 2)):
        assert main(["sim", "--n", "9", "--mode", "hjb", "--range-m", "5", "--steps", "30", "--seed", str(seed), "--out", str(out), "--no-progress"]) == 0
    ta, tb, tc = (load_trajectories(p / "trajectories.npz") for p in (a, b, c))
    np.testing.assert_array_equal(ta.pos_m, tb.pos_m)
    assert not np.array_equal(ta.pos_m, tc.pos_m)


def test_power_gives_the_radio_range_and_bad_input_is_a_clear_error(tmp_path, capsys):
    from mfg_swarm.cli import main
    assert main(["sim", "--n", "4", "--mode", "hjb", "--power-mw", "10", "--steps", "2", "--out", str(tmp_path / "p"), "--no-progress"]) == 0
    m = json.loads((tmp_path / "p" / "metrics.json").read_text())
    assert abs(m["range_m"] - 70.71) < 0.01
    assert main(["sim", "--n", "4", "--mode", "hjb", "--steps", "2", "--out", str(tmp_path / "q")]) == 2
    assert "radio range" in capsys.readouterr().err
    assert main(["sim", "--n", "0", "--steps", "2", "--out", str(tmp_path / "r")]) == 2


def test_repeated_fail_flags_fail_several_vehicles(tmp_path):
    from mfg_swarm.cli import main
    out = tmp_path / "f"
    assert main(["sim", "--scenario", "paper", "--n", "25", "--steps", "40", "--seed", "1", "--fail-vehicle", "3",
                 "--fail-vehicle", "12", "--fail-at", "5", "--fail-at", "8", "--out", str(out), "--no-progress"]) == 0
    m = json.loads((out / "metrics.json").read_text())
    assert m["fail_vehicle"] == [3, 12] and m["fail_at_s"] == [5.0, 8.0]
    assert main(["sim", "--n", "25", "--steps", "4", "--fail-vehicle", "3", "--fail-vehicle", "3",
                 "--out", str(tmp_path / "g"), "--no-progress"]) == 2
