"""The backstop predicts the own vehicle with its own disturbance (BackstopParams.own_disturbance): the escape's tracks
and the barrier filter's constraints carry the acceleration the vehicle flies beyond its command (a gust), which its own
telemetry gives (guidance/disturbance.py). Without it, a gust across the line of sight eats the swerve the escape chose
(swap4 --gust with vehicle 10 failing, N = 1,000 seed 78: UAV 20 swerved at 1.79 m/s^2, the gust pushed 1.38 m/s^2 the
other way, and it met the failed vehicle at 0.028 m)."""

from __future__ import annotations

import dataclasses

from _traced import TRACED_CRUISE_SPACING_M
import numpy as np
import pytest

from mfg_autopilot.guidance.params import DEFAULT
from mfg_autopilot.presets import with_inner_loop
from mfg_autopilot.safety.backstop import cbf_acc, escape_acc
from mfg_autopilot.safety.params import BackstopParams
from mfg_swarm.metrics import segment_min_distance
from mfg_swarm.scenarios import make_scenario
from mfg_swarm.sim import GustParams, SimConfig, simulate

BP = BackstopParams()
A_MAX = 2.0


def _fly_escape(gust_m_s2, aware, v_m_s, offset_m, dt_s=0.5, T_s=6.0):
    """A UAV at v_m_s along +x towards a hovering threat 6 m ahead (offset_m across), its nominal command the
    tracking's answer to a steady gust (-gust: it holds its line), the escape applied at every control period, the
    vehicle flying command + gust. The smallest distance to the threat along the flight (exact parabolas, sampled)."""
    s = np.array([[0.0, 0.0, v_m_s, 0.0]])
    threat = np.array([[6.0, offset_m, 0.0, 0.0]])
    dmin = np.inf
    for _ in range(int(T_s / dt_s)):
        a, _ = escape_acc(s, -gust_m_s2[None, :], threat, np.array([0]), np.array([True]), np.array([0.6]),
                          np.array([0.8]), BP, dt_s, None, np.array([True]), gust_m_s2[None, :] if aware else None)
        flown = a[0] + gust_m_s2
        for t in np.linspace(0.0, dt_s, 51):
            p = s[0, 0:2] + s[0, 2:4] * t + 0.5 * flown * t * t
            dmin = min(dmin, float(np.linalg.norm(p - threat[0, 0:2])))
        s[0, 0:2] += s[0, 2:4] * dt_s + 0.5 * flown * dt_s ** 2
        s[0, 2:4] += flown * dt_s
    return dmin


@pytest.mark.parametrize("gust", [1.0, 1.4])
@pytest.mark.parametrize("offset_m", [0.0, 0.3, -0.3])
@pytest.mark.parametrize("v_m_s", [2.0, 3.0, 4.0])
def test_the_escape_keeps_half_its_clearance_when_it_knows_the_gust_across_its_track(gust, offset_m, v_m_s):
    # the escape's safety-first rule takes a command whose prediction keeps escape_hard_fraction x the clearance
    # (0.5 x 0.8 m); with the own disturbance in the prediction, the flight keeps it to within 0.05 m (the prediction
    # holds the second phase's command, the flight decides again every period)
    g = np.array([0.0, gust])
    assert _fly_escape(g, True, v_m_s, offset_m) >= BP.escape_hard_fraction * 0.8 - 0.05


@pytest.mark.parametrize("gust", [1.0, 1.4])
def test_without_the_gust_in_its_prediction_the_escape_meets_the_threat(gust):
    # the test above is not vacuous: head-on, the same escape predicting the own vehicle by its command alone passes
    # within 0.12 m (the swerve it chose against the gust's side is eaten by the gust)
    g = np.array([0.0, gust])
    assert max(_fly_escape(g, False, v, 0.0) for v in (2.0, 3.0, 4.0)) < 0.12


def test_a_zero_disturbance_changes_no_command():
    rng = np.random.default_rng(3)
    own = np.column_stack([rng.uniform(-5, 5, (6, 2)), rng.uniform(-3, 3, (6, 2))])
    sensed = np.column_stack([own[:, 0:2] + rng.uniform(-2, 2, (6, 2)), rng.uniform(-3, 3, (6, 2))])
    owner = np.arange(6)
    a_nom = rng.uniform(-1.4, 1.4, (6, 2))
    threat = np.ones(6, dtype=bool)
    args = (own, a_nom, sensed, owner, threat, np.full(6, 0.6), np.full(6, 0.8), BP, 0.5)
    a0, act0 = escape_acc(*args)
    a1, act1 = escape_acc(*args, None, None, np.zeros((6, 2)))
    assert act0.any() and np.array_equal(act0, act1) and np.array_equal(a0, a1)
    c0, k0 = cbf_acc(own, a_nom, sensed, owner, np.arange(6), BP, 0.3, A_MAX)
    c1, k1 = cbf_acc(own, a_nom, sensed, owner, np.arange(6), BP, 0.3, A_MAX, None, np.zeros((6, 2)))
    assert k0.any() and np.array_equal(k0, k1) and np.array_equal(c0, c1)


def test_the_deadband_must_not_be_negative():
    with pytest.raises(ValueError, match="own_disturbance_deadband_m_s2"):
        dataclasses.replace(DEFAULT.backstop, own_disturbance_deadband_m_s2=-0.1)


@pytest.mark.parametrize("family,seed,pair", [("swap4", 78, [10, 20]), ("crossing", 77, [63, 87])])
def test_a_failure_inside_a_gust_is_passed_with_the_own_gust_in_the_backstop(family, seed, pair):
    # N = 1,000 with vehicle 10 failing into Hold at 20.15 s, inside the gust (20-25 s). Without the own disturbance:
    # swap4 seed 78, UAV 20 met the failed vehicle at 0.028 m (the swerve eaten by the gust, the module docstring);
    # crossing seed 77, UAVs 63 / 87 beside the failed vehicle at 0.012 m. With it: 0.206 / 0.254 m over the whole
    # 400-step flights (docs/benchmarks.md, twenty-second round)
    # (measured with the PD Hold, the simulator's default until the twenty-fifth session, which these flights keep; with
    # PX4's Hold, the default now, crossing passes too; swap4 needed the hover latch: tests/test_hover_latch.py)
    # (held, without the inner loop, the default since the twenty-eighth session: with it the counterfactual without
    # the own disturbance does not meet the failed vehicle either; the default flight, PX4's Hold and the inner loop,
    # is flown too)
    def fly(bp, hold="pd", inner=False, failed_pass=False):
        # (the paper's plant, as this was measured: with PX4's lag crossing seed 77 collides, UAV 61 and the failed 10 at 0.073 m; issue 18)
        # (the plan these flights were traced on: tests/_traced.py)
        traj, m = simulate(SimConfig(scenario=make_scenario(family, 1000, seed), mode="mfg",
                                     preset=with_inner_loop(dataclasses.replace(DEFAULT, backstop=bp, cruise_spacing_m=TRACED_CRUISE_SPACING_M),
                                                            inner), seed=seed,
                                     steps=56, gust=GustParams(),
                                     fail_vehicle=10, fail_at_s=20.15, hold_model=hold, acc_lag_s=0.0), progress=False)
        if failed_pass:
            # the failed vehicle's closest neighbour over the flight, along the step segments (as collision_pairs)
            d = traj.pos_m - traj.pos_m[:, 10:11]
            d = np.delete(d, 10, axis=1)
            m["failed_pass_m"] = float(segment_min_distance(d[:-1].reshape(-1, 2), d[1:].reshape(-1, 2)).min())
        return m
    assert DEFAULT.backstop.own_disturbance
    for m in (fly(DEFAULT.backstop, failed_pass=True), fly(DEFAULT.backstop, "px4", inner=True, failed_pass=True)):
        # the failed vehicle is passed at 0.15 m or more, and nobody collides (with DetourParams.side_from_escape, the
        # thirty-first session, the closest pair of swap4's PD-Hold flight is two UAVs swerving round it, 0.148 m;
        # before, UAV 20 and the failed vehicle, 0.177 m)
        assert m["collision_pairs"] == 0, m["collided_pairs_list"]
        assert m["failed_pass_m"] >= 0.15, m["failed_pass_m"]
    if family == "crossing":
        m = fly(DEFAULT.backstop, "px4")
        assert m["collision_pairs"] == 0 and m["min_separation_m"] >= 0.15, (m["collided_pairs_list"], m["min_separation_m"])
    # the own gust alone: with and without it, both without the hover escape in a crowd (escape_hover_in_crowd, which
    # came later) and with every off-plan vehicle predicted braking to a stop (escape_brake_hypothesis, later still)
    on = dataclasses.replace(DEFAULT.backstop, escape_hover_in_crowd=False, escape_brake_hypothesis="threat",
                             crowd_cbf_inside_no_approach=False, hover_latch_s=0.0)
    m = fly(on)
    assert m["collision_pairs"] == 0 and m["min_separation_m"] >= 0.15, (m["collided_pairs_list"], m["min_separation_m"])
    off = fly(dataclasses.replace(on, own_disturbance=False))
    assert pair in off["collided_pairs_list"], off["collided_pairs_list"]

