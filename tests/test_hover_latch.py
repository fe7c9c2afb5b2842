"""A vehicle that hovered off the plan keeps counting as hovering while it drifts back (BackstopParams.hover_latch_s).

A vehicle failed into PX4's Hold fights a gust with its position loop's integrator; when the gust ends it flies back
towards its Hold point at up to 1-3 m/s, accelerating at the airframe's limit. Past hover_max_speed_m_s (1 m/s) it lost
the rules the backstop keeps for a hovering vehicle in the middle of an encounter (swap4 --gust N = 1,000 seed 78: UAV
17's crowded row stopped escaping it and met it at 0.093 m). docs/default_controller.md, "PX4's trajectory is the
default Hold".
"""
from __future__ import annotations

import dataclasses

from _traced import TRACED_CRUISE_SPACING_M
import numpy as np
import pytest

from mfg_autopilot.guidance.controller import DefaultMFGController
from mfg_autopilot.guidance.params import DEFAULT
from mfg_autopilot.presets import with_inner_loop
from mfg_autopilot.interface import Neighbours
from mfg_autopilot.safety.params import BackstopParams
from mfg_swarm.scenarios import make_scenario
from mfg_swarm.sim import GustParams, SimConfig, simulate


def _controller(preset=DEFAULT) -> DefaultMFGController:
    pos = np.array([[0.5 * i, 0.5 * j] for i in range(3) for j in range(3)], dtype=float)
    sites = pos + np.array([200.0, 0.0])
    c = DefaultMFGController(preset, sites)
    c.exchange_t0(np.concatenate([pos, np.zeros_like(pos)], axis=1), np.arange(9), np.arange(9), sites)
    return c


def _one(speed_m_s: float, vid: int = 4) -> Neighbours:
    return Neighbours(np.array([[1.0, 1.0, speed_m_s, 0.0]]), np.zeros(1, dtype=np.int64), np.array([vid]))


def _latched(c, step, speed_m_s, unplanned=True, vid=4):
    sn = _one(speed_m_s, vid)
    hover = np.array([unplanned and speed_m_s < c.preset.backstop.hover_max_speed_m_s])
    return bool(c._hover_latched(sn, step, np.array([unplanned]), hover)[0])


def test_a_vehicle_that_hovered_keeps_hovering_while_it_drifts_back_off_the_plan():
    c = _controller()
    bp = c.preset.backstop
    k_latch = int(round(bp.hover_latch_s / c.preset.dt_s))
    assert not _latched(c, 10, 2.0)                   # never hovered: 2 m/s off the plan is not hovering
    assert _latched(c, 11, 0.5)                       # hovers (below hover_max_speed_m_s)
    assert _latched(c, 12, 2.5)                       # then drifts back at 2.5 m/s: still hovering
    assert not _latched(c, 13, 3.5)                   # faster than hover_latch_max_speed_m_s: not
    assert _latched(c, 12 + k_latch, 2.0)             # within hover_latch_s of the last step it counted
    assert not _latched(c, 13 + 2 * k_latch, 2.0)     # beyond it
    assert not _latched(c, 14 + 2 * k_latch, 0.5, unplanned=False)     # on the plan: never hovering
    assert not _latched(c, 11, 2.0, vid=5)            # by id: another vehicle has its own record
    assert _latched(c, 40, 0.5, vid=6)
    # flying at 2 m/s towards its own plan particle (vehicle 6's, 1 m south of it): a UAV recovering its plan, not a
    # Hold drifting back
    sn = Neighbours(np.array([[1.0, 1.0, 0.1, -2.0]]), np.zeros(1, dtype=np.int64), np.array([6]))
    to_p = c.plan.states[6, 0:2] - sn.states[0, 0:2]
    assert float(sn.states[0, 2:4] @ to_p) / np.linalg.norm(to_p) >= 0.5 * np.linalg.norm(sn.states[0, 2:4])
    assert not c._hover_latched(sn, 41, np.array([True]), np.array([False]))[0]


def test_the_latch_off_is_the_speed_alone():
    c = _controller(dataclasses.replace(DEFAULT, backstop=dataclasses.replace(DEFAULT.backstop, hover_latch_s=0.0)))
    assert _latched(c, 1, 0.5) and not _latched(c, 2, 1.5)


@pytest.mark.parametrize("field", ["hover_latch_s", "hover_latch_max_speed_m_s", "hover_latch_max_towards_plan"])
def test_the_latch_parameters_are_validated(field):
    for bad in (-1.5, float("nan")):
        with pytest.raises(ValueError, match=field):
            BackstopParams(**{field: bad})


def test_a_hold_drifting_back_after_the_gust_is_passed():
    # swap4 --gust N = 1,000 seed 78, vehicle 10 failing into PX4's Hold (the default) at 20.15 s: when the gust ended
    # it flew back towards its Hold point at up to 1.41 m/s, accelerating at 2 m/s^2 across UAV 17's lane; past 1 m/s it
    # no longer counted as hovering, 17's crowded row stopped escaping it and met it at 0.093 m. With the latch: 0.217 m
    # (held, as measured: with the inner loop, the default, the flight without the latch has no pair; the default is
    # flown too)
    def fly(latch_s, inner=False):
        bp = dataclasses.replace(DEFAULT.backstop, hover_latch_s=latch_s)
        # (the paper's plant, as this was measured: with PX4's lag one of its flights keeps 0.13 m, the test's bound 0.2 m; issue 18)
        # (the plan these flights were traced on: tests/_traced.py)
        return simulate(SimConfig(scenario=make_scenario("swap4", 1000, 78), mode="mfg",
                                  preset=with_inner_loop(dataclasses.replace(DEFAULT, backstop=bp, cruise_spacing_m=TRACED_CRUISE_SPACING_M),
                                                         inner), seed=78,
                                  steps=56, gust=GustParams(),
                                  fail_vehicle=10, fail_at_s=20.15, acc_lag_s=0.0), progress=False)[1]
    for m in (fly(DEFAULT.backstop.hover_latch_s), fly(DEFAULT.backstop.hover_latch_s, inner=True)):
        assert m["collision_pairs"] == 0 and m["min_separation_m"] >= 0.2, (m["collided_pairs_list"], m["min_separation_m"])
    assert [10, 17] in fly(0.0)["collided_pairs_list"]


def test_bench_hold_drift_reads_the_drift_after_the_first_stop(tmp_path):
    import importlib.util
    import json
    from pathlib import Path

    spec = importlib.util.spec_from_file_location("hold_drift", Path(__file__).parents[1] / "bench" / "hold_drift.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    # vehicle 1 fails at 1 s, slows to 0.2 m/s at 2 s, drifts back at up to 1.5 m/s at 3 s
    t = np.arange(6) * 0.5
    vel = np.zeros((6, 2, 2))
    vel[:, 1, 0] = [4.0, 3.0, 1.0, 0.5, 0.2, 1.5][:6]
    vel[:, 0, 0] = 4.0
    assert mod.hold_drift(vel, t, 1, 1.0, 0.3) == (2.0, 1.5, 2.5)
    assert mod.hold_drift(vel, t, 0, 1.0, 0.3) is None             # never stopped
    run = tmp_path / "one"
    run.mkdir()
    (run / "metrics.json").write_text(json.dumps({"fail_vehicle": 1, "fail_at_s": 1.0, "hold_model": "px4"}))
    np.savez(run / "trajectories.npz", vel_m_s=vel, t_s=t)
    import contextlib
    import io
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        mod.main([str(tmp_path)])
    assert "| one | px4 | 2.0 | 1.50 | 2.5 |" in out.getvalue() and "above 1 m/s: 1" in out.getvalue()


def test_a_healthy_uav_recovering_its_plan_after_the_gust_is_not_latched():
    # crossing --gust N = 137 seed 125 (no failure): the gust pins a group at its departure; its UAVs hover behind their
    # particles, then accelerate back into the stream. Latched as hovering while they did, they kept the hover rules
    # (0.433 -> 0.198 m); gated by their heading to their own particle they do not (0.352 m). Held (no inner loop), as
    # measured: with the inner loop the flight keeps 0.48 m with the gate off too
    def fly(towards):
        bp = dataclasses.replace(DEFAULT.backstop, hover_latch_max_towards_plan=towards)
        # (the paper's plant, as this was measured: with PX4's lag 0.17 m, the test's bound 0.3 m; issue 18)
        return simulate(SimConfig(scenario=make_scenario("crossing", 137, 125), mode="mfg",
                                  preset=with_inner_loop(dataclasses.replace(DEFAULT, backstop=bp), False), seed=125, steps=160,
                                  gust=GustParams(), acc_lag_s=0.0), progress=False)[1]
    assert fly(DEFAULT.backstop.hover_latch_max_towards_plan)["min_separation_m"] >= 0.3
    assert fly(1.0)["min_separation_m"] < 0.25          # the gate off: every latched vehicle
