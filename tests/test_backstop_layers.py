"""Which safety layer made each command (safety.backstop.Layer): recorded per UAV and step by the simulator
(``backstop_layer``), counted in metrics.json (``safety_interventions_by_layer``), named by bench/closest_pair.py.

The attribution is bookkeeping only: the commands are the ones the controller flew before it existed (the simulator's
fingerprints, tests/test_sim_fingerprint.py, are unchanged). What is checked here: a row carries a bit exactly when the
backstop changed its command, a failed vehicle's row none from its failure on, each layer is named when it is the one
that acts (by switching the others off), and the per-layer counts are the recorded bits."""

from __future__ import annotations

import dataclasses
import importlib.util
from pathlib import Path

import numpy as np
import pytest

from mfg_autopilot.presets import preset_by_name, with_inner_loop
from mfg_autopilot.safety.backstop import Layer
from mfg_swarm.scenarios import make_scenario
from mfg_swarm.sim import GustParams, SimConfig, simulate

# the held flight (TrackingParams.inner_loop off; on by default since the twenty-eighth session): the crowds these
# layers act in form there. With the inner loop the gust is fought inside the period and this flight has none of them
DEFAULT = with_inner_loop(preset_by_name("default"), False)


def _fly(bp=None, fail: bool = False, mode: str = "mfg", steps: int = 80):
    # crossing --gust N = 137 seed 117: the gust meets a group at its departure, and the escape, the crowd's barrier
    # filter and the gap push all act within 80 steps (~1 s here)
    preset = DEFAULT if bp is None else dataclasses.replace(DEFAULT, backstop=bp)
    cfg = SimConfig(scenario=make_scenario("crossing", 137), mode=mode, preset=preset, seed=117, steps=steps,
                    gust=GustParams(), fail_vehicle=3 if fail else None, fail_at_s=10.0,
                    range_m=100.0 if mode == "hjb" else None)
    return simulate(cfg, progress=False)


def _counts(layer: np.ndarray) -> dict[str, int]:
    # counts_by_layer's job, written out here so that the metric is checked against an independent count
    return {f.name.lower(): int(np.count_nonzero(layer & np.uint8(f))) for f in Layer}


def test_a_row_carries_a_layer_exactly_when_the_backstop_changed_its_command():
    traj, m = _fly(fail=True)
    layer, active = traj.extra["backstop_layer"], traj.extra["backstop_active"]
    assert layer.dtype == np.uint8 and layer.shape == active.shape
    np.testing.assert_array_equal(layer != 0, active)
    assert not layer[20:, 3].any()                  # the failed vehicle (3, at 10 s = step 20) flies its Hold
    assert m["safety_interventions_by_layer"] == _counts(layer)
    # several layers act in this flight, and no row carries a bit no layer has
    seen = {k for k, v in m["safety_interventions_by_layer"].items() if v}
    assert {"escape", "crowd_cbf"} <= seen, seen
    assert not np.any(layer & ~np.uint8(sum(int(f) for f in Layer)))


def test_an_escape_replaces_the_half_plane_pushes_and_a_crowded_rows_filter_too():
    # one bit per row but for the last layer, which filters whatever the others made
    traj, _ = _fly()
    layer = traj.extra["backstop_layer"]
    single = layer & ~np.uint8(Layer.LAST_CBF)
    for lone in (Layer.ESCAPE, Layer.CROWD_CBF):
        rows = (single & np.uint8(lone)) != 0
        assert rows.any()
        assert np.all(single[rows] == np.uint8(lone)), f"{lone.name} shares a row with another layer"


def test_each_layer_is_named_when_it_is_the_one_that_acts():
    base = dataclasses.replace(DEFAULT.backstop, own_disturbance=False)
    # the crowd's half-plane push instead of its barrier filter
    _, m = _fly(dataclasses.replace(base, crowd_cbf=False))
    assert m["safety_interventions_by_layer"]["push"] > 0 and m["safety_interventions_by_layer"]["crowd_cbf"] == 0
    # the barrier filter as the last layer of the rows that neither escape nor are crowded (an option, off)
    _, m = _fly(dataclasses.replace(base, cbf_last_layer=True))
    assert m["safety_interventions_by_layer"]["last_cbf"] > 0
    # no escape: its bit is gone, and the flight still records every intervention under some layer
    _, m = _fly(dataclasses.replace(base, escape=False))
    assert m["safety_interventions_by_layer"]["escape"] == 0
    assert sum(m["safety_interventions_by_layer"].values()) >= m["safety_interventions"] > 0


def test_hjb_records_its_layers_and_orca_records_none():
    traj, m = _fly(mode="hjb", steps=40)
    assert "backstop_layer" in traj.extra and m["safety_interventions_by_layer"] == _counts(traj.extra["backstop_layer"])
    traj, m = _fly(mode="orca", steps=10)
    assert "backstop_layer" not in traj.extra and "safety_interventions_by_layer" not in m


def test_closest_pair_names_the_layers(tmp_path):
    spec = importlib.util.spec_from_file_location("closest_pair", Path(__file__).parents[1] / "bench" / "closest_pair.py")
    cp = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(cp)
    assert cp.layer_names(0) == "-"
    assert cp.layer_names(int(Layer.ESCAPE)) == "escape"
    assert cp.layer_names(int(Layer.CROWD_CBF | Layer.LAST_CBF)) == "crowd_cbf+last_cbf"
    traj, m = _fly(steps=60)
    rows = cp.pair_rows(traj.pos_m, traj.vel_m_s, traj.acc_m_s2, traj.extra["backstop_active"], 0, 1, 0, 59,
                        traj.extra["backstop_layer"])
    assert len(rows) == 60
    for k, r in enumerate(rows):
        assert (r["layer_i"] != "-") == bool(traj.extra["backstop_active"][k, 0])


@pytest.mark.parametrize("flag", list(Layer))
def test_layer_bits_are_distinct_powers_of_two(flag):
    assert int(flag) & (int(flag) - 1) == 0 and int(flag) < 256
