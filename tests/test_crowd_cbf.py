"""The crowd's reciprocal barrier filter (backstop.cbf_acc; BackstopParams.crowd_cbf): its constraint is the barrier's
derivative, its solution is the constrained optimum, it keeps a pair apart, and it keeps the crowd of crossing --gust
N = 137 from colliding (3 of 30 seeds collided with the summed half-plane push it replaces)."""

from __future__ import annotations

import dataclasses
import math
from functools import partial

from _traced import TRACED_CRUISE_SPACING_M
import numpy as np
import pytest

from mfg_autopilot.guidance.params import DEFAULT
from mfg_autopilot.presets import with_inner_loop
from mfg_autopilot.safety.backstop import cbf_acc
from mfg_autopilot.safety.params import BackstopParams
from mfg_swarm.scenarios import make_scenario
from mfg_swarm.sim import GustParams, SimConfig, simulate

BP = BackstopParams()
A_MAX = 2.0


def _barrier(own, other, alpha, ds):
    """h = sqrt(4 alpha (d - D_s)) + p . dv, written out again (not the kernel's code)."""
    dp, dv = own[0:2] - other[0:2], own[2:4] - other[2:4]
    d = math.hypot(*dp)
    return math.sqrt(4 * alpha * (d - ds)) + float(dp @ dv) / d


def _constraint(own, other, alpha, gamma, ds):
    """(p, B): p . (a_i - a_j) >= B keeps dh/dt >= -gamma h^3 (Wang, Ames, Egerstedt 2017, eq. for double integrators)."""
    dp, dv = own[0:2] - other[0:2], own[2:4] - other[2:4]
    d = math.hypot(*dp)
    p = dp / d
    rdot = float(p @ dv)
    root = math.sqrt(4 * alpha * (d - ds))
    h = root + rdot
    return p, -gamma * h ** 3 - float(dv @ dv) / d + rdot ** 2 / d - 2 * alpha * rdot / root


def test_the_constraint_is_the_barrier_derivative():
    # dh/dt by a central difference of the pair moved with constant accelerations equals
    # p . (a_i - a_j) - (B + gamma h^3): the constraint p . da >= B is exactly dh/dt >= -gamma h^3
    rng = np.random.default_rng(5)
    for _ in range(50):
        own = np.concatenate([rng.uniform(-1, 1, 2), rng.uniform(-3, 3, 2)])
        other = np.concatenate([rng.uniform(-1, 1, 2) + [3.0, 0.0], rng.uniform(-3, 3, 2)])
        ai, aj = rng.uniform(-2, 2, 2), rng.uniform(-2, 2, 2)
        alpha, gamma, ds = 1.0, 0.7, 0.3

        def at(t):
            move = lambda s, a: np.concatenate([s[0:2] + s[2:4] * t + 0.5 * a * t * t, s[2:4] + a * t])
            return _barrier(move(own, ai), move(other, aj), alpha, ds)

        eps = 1e-6
        dh = (at(eps) - at(-eps)) / (2 * eps)
        p, B = _constraint(own, other, alpha, gamma, ds)
        h = _barrier(own, other, alpha, ds)
        assert dh == pytest.approx(float(p @ (ai - aj)) - B - gamma * h ** 3, rel=1e-5, abs=1e-5)


def _row_case(rng, k):
    own = np.array([[0.0, 0.0, *rng.uniform(-3, 3, 2)]])
    ang = rng.uniform(0, 2 * np.pi, k)
    r = rng.uniform(0.5, 2.5, k)
    sensed = np.column_stack([r * np.cos(ang), r * np.sin(ang), rng.uniform(-3, 3, (k, 2))])
    a_nom = rng.uniform(-1.4, 1.4, (1, 2))
    return own, a_nom, sensed


def test_the_filter_returns_the_nominal_command_when_it_is_safe_and_else_the_constrained_optimum():
    # reference: every constraint written out again, and the nearest feasible command on a fine polar grid
    rng = np.random.default_rng(11)
    ds, share = 0.3, BP.crowd_cbf_share
    r_g, t_g = np.meshgrid(np.linspace(0, A_MAX, 201), np.linspace(0, 2 * np.pi, 721), indexing="ij")
    grid = np.column_stack([(r_g * np.cos(t_g)).ravel(), (r_g * np.sin(t_g)).ravel()])
    seen = {"kept": 0, "optimum": 0, "least": 0}
    for _ in range(120):
        own, a_nom, sensed = _row_case(rng, int(rng.integers(1, 5)))
        a, act = cbf_acc(own, a_nom, sensed, np.zeros(len(sensed), dtype=int), np.array([0]), BP, ds, A_MAX)
        cons = [_constraint(own[0], s, BP.crowd_cbf_alpha_m_s2, BP.crowd_cbf_gamma, ds) for s in sensed]
        P = np.array([c[0] for c in cons])
        b = share * np.array([c[1] for c in cons])
        slack = P @ a_nom[0] - b
        if np.all(slack >= 0):
            assert not act[0] and np.array_equal(a[0], a_nom[0])
            seen["kept"] += 1
            continue
        assert act[0] and np.linalg.norm(a[0]) <= A_MAX * (1 + 1e-9)
        feasible = np.all(grid @ P.T - b >= 0, axis=1)
        if np.all(P @ a[0] - b >= -1e-9):
            # no feasible grid command is nearer to a_nom (up to the grid's resolution)
            assert feasible.any()
            best = np.min(np.linalg.norm(grid[feasible] - a_nom[0], axis=1))
            assert np.linalg.norm(a[0] - a_nom[0]) <= best + 1e-9
            seen["optimum"] += 1
        else:
            # nothing meets every constraint: the command misses the most violated one by no more than any grid command
            assert not feasible.any()
            worst = np.max(b - P @ a[0])
            assert worst <= np.min(np.max(b[None, :] - grid @ P.T, axis=1)) + 1e-9
            seen["least"] += 1
    assert min(seen.values()) >= 5, seen          # every branch is exercised


def _fly_pair(v_closing, offset_m, dt_s, T_s=6.0, ds=0.3, gust_m_s2=0.0, aware=False):
    """Two vehicles whose nominal commands drive them into each other at a_max, both filtered; the smallest distance.
    gust_m_s2: each is also blown towards the other at this acceleration (it flies command + gust); aware: each filter
    is given its own gust (BackstopParams.own_disturbance)."""
    s = np.array([[0.0, 0.0, v_closing / 2, 0.0], [4.0, offset_m, -v_closing / 2, 0.0]])
    g = np.array([[gust_m_s2, 0.0], [-gust_m_s2, 0.0]])
    dmin = np.inf
    for _ in range(int(T_s / dt_s)):
        d = s[1, 0:2] - s[0, 0:2]
        a_nom = np.array([d, -d]) / np.linalg.norm(d) * A_MAX
        a = np.empty((2, 2))
        for i in (0, 1):
            a[i], _ = cbf_acc(s[i:i + 1], a_nom[i:i + 1], s[1 - i:2 - i], np.zeros(1, dtype=int), np.array([0]), BP, ds, A_MAX,
                              None, g[i:i + 1] if aware else None)
        a = a + g
        # exact motion over the step, and the smallest distance along it (relative motion is a parabola: sample finely)
        for t in np.linspace(0, dt_s, 21):
            pos = s[:, 0:2] + s[:, 2:4] * t + 0.5 * a * t * t
            dmin = min(dmin, float(np.linalg.norm(pos[1] - pos[0])))
        s[:, 0:2] += s[:, 2:4] * dt_s + 0.5 * a * dt_s ** 2
        s[:, 2:4] += a * dt_s
    return dmin


@pytest.mark.parametrize("v_closing", [1.0, 2.0, 3.0])
@pytest.mark.parametrize("offset_m", [0.0, 0.4])
def test_a_filtered_pair_never_closes_below_the_safe_distance(v_closing, offset_m):
    # the barrier's guarantee: the pair starts inside the safe set (h >= 0: both braking at alpha stop before D_s)
    # and each meets its half of the constraint, so h stays >= 0 and the distance >= D_s - in continuous time. At
    # 100 Hz the pair keeps D_s to within 1 %; at the 0.5 s control period the held command overshoots the barrier,
    # and the pair still keeps half of it (the flight below is where the period is tested)
    ds = 0.3
    own, other = np.array([0.0, 0.0, v_closing / 2, 0.0]), np.array([4.0, offset_m, -v_closing / 2, 0.0])
    assert _barrier(own, other, BP.crowd_cbf_alpha_m_s2, ds) >= 0
    assert _fly_pair(v_closing, offset_m, 0.01, ds=ds) >= 0.99 * ds
    assert _fly_pair(v_closing, offset_m, 0.5, ds=ds) >= 0.5 * ds


@pytest.mark.parametrize("gust", [0.5, 0.9])
def test_the_barrier_filter_that_knows_its_own_gust_keeps_the_safe_distance(gust):
    # a pair closing head-on at 2 m/s, each blown towards the other: with its own gust in the constraint,
    # p . (a_i + d_i) >= B / 2 holds for what each flies (100 Hz: within 1 % of D_s); the gust leaves each vehicle
    # a_max - gust >= the barrier's braking authority alpha (1 m/s^2). Unaware, the constraint holds for the command only
    assert _fly_pair(2.0, 0.0, 0.01, gust_m_s2=gust, aware=True) >= 0.99 * 0.3
    assert _fly_pair(2.0, 0.0, 0.01, gust_m_s2=gust, aware=False) < 0.9 * 0.3


def test_without_the_filter_the_nominal_commands_collide():
    # the pair test is not vacuous: unfiltered, the commands above drive the pair together
    s = np.array([[0.0, 0.0, 1.0, 0.0], [4.0, 0.0, -1.0, 0.0]])
    dmin = np.inf
    for _ in range(600):
        d = s[1, 0:2] - s[0, 0:2]
        dmin = min(dmin, float(np.linalg.norm(d)))
        a = np.array([d, -d]) / max(np.linalg.norm(d), 1e-9) * A_MAX
        s[:, 0:2] += s[:, 2:4] * 0.01 + 0.5 * a * 1e-4
        s[:, 2:4] += a * 0.01
    assert dmin < 0.1


# the backstop as it was before the escape's braking hypothesis was measured (twenty-fourth session), the filter's
# clamp inside the safe distance and the hover latch (twenty-fifth): the counterfactual flights of the mechanisms that
# came before them isolate them on the flights they were measured on
THREAT = dataclasses.replace(DEFAULT.backstop, escape_brake_hypothesis="threat",
                             crowd_cbf_inside_no_approach=False, hover_latch_s=0.0)


# the failed vehicle's Hold the failure flights below were measured with: the PD Hold, the simulator's default until
# the twenty-fifth session. Each mechanism's counterfactual is flown with it (a different Hold is a different flight);
# each test also flies the default backstop with the default Hold, PX4's trajectory (hold_model "px4")
MEASURED_HOLD = "pd"

# ... and without the telemetry-rate inner loop (TrackingParams.inner_loop, the default since the twenty-eighth
# session): every mechanism below was measured on the held flight, where a gust is fought once per period and the
# crowds these tests stage form. With the inner loop none of the counterfactual flights below collides (measured
# when it became the default); each test's everything-default flight (``_default_hold_flight``) flies it
MEASURED_INNER_LOOP = False


def _gust_flight(family: str, n: int, seed: int, steps: int, fail: bool, bp: BackstopParams,
                 hold: str = MEASURED_HOLD, inner_loop: bool = MEASURED_INNER_LOOP) -> dict:
    """metrics.json of a --gust flight of the default preset with backstop bp (fail: vehicle 10 failing at 20.15 s,
    inside the gust, into the Hold ``hold``), with or without the inner loop."""
    # flown on the plan these flights were traced on (tests/_traced.py)
    preset = with_inner_loop(dataclasses.replace(DEFAULT, backstop=bp, cruise_spacing_m=TRACED_CRUISE_SPACING_M), inner_loop)
    cfg = SimConfig(scenario=make_scenario(family, n, seed), mode="mfg", preset=preset,
                    seed=seed, steps=steps, gust=GustParams(),
                    **({"fail_vehicle": 10, "fail_at_s": 20.15, "hold_model": hold} if fail else {}),
                    acc_lag_s=0.0)     # the paper's plant, as measured (held flights cannot fly PX4's lag)
    return simulate(cfg, progress=False)[1]


def _default_hold_flight(family: str, n: int, seed: int, steps: int) -> dict:
    """The failure flight with everything default: the default backstop, PX4's Hold, the inner loop."""
    assert SimConfig(scenario=make_scenario(family, 4), mode="mfg", preset=DEFAULT).hold_model == "px4"
    assert DEFAULT.tracking.inner_loop
    return _gust_flight(family, n, seed, steps, True, DEFAULT.backstop, "px4", inner_loop=True)


@pytest.mark.parametrize("seed", [120, 123])
def test_a_crowd_blown_off_its_plan_at_departure_does_not_collide(seed):
    # crossing --gust N = 137: the gust (20-25 s) blows a group just as it departs (~21 s); nearly every UAV falls 2-5 m
    # behind its particle and chases it at a_max, so their rows are crowded (most sensed vehicles off the plan). With the
    # summed half-plane push these two seeds (of 30 flown, 3 collided) had 1 collided pair each (0.027 m, 0.077 m).
    # Elsewhere (docs/benchmarks.md, twentieth round): N = 213 seed 95, 1 pair (0.015 m) with the push, 0.384 m with the
    # filter, whose constants were not tuned on any of these flights
    fly = partial(_gust_flight, "crossing", 137, seed, 120, False)
    m = fly(DEFAULT.backstop)
    assert m["collision_pairs"] == 0, m["collided_pairs_list"]
    assert m["min_separation_m"] >= 0.2, m["min_separation_m"]
    assert m["safety_interventions"] > 0
    # the filter alone (without the own disturbance in the backstop's predictions, BackstopParams.own_disturbance, and
    # the hover escape in a crowd, escape_hover_in_crowd, which came later and also fly these two seeds without a pair)
    # is what separates them from the push
    alone = dataclasses.replace(DEFAULT.backstop, own_disturbance=False, escape_hover_in_crowd=False,
                                escape_brake_hypothesis="threat",
                                crowd_cbf_inside_no_approach=False, hover_latch_s=0.0)
    assert fly(alone)["collision_pairs"] == 0
    off = fly(dataclasses.replace(alone, crowd_cbf=False))
    assert off["collision_pairs"] >= 1


@pytest.mark.parametrize("field,value", [("crowd_cbf_alpha_m_s2", 0.0), ("crowd_cbf_gamma", -1.0), ("crowd_cbf_safe_fraction", 1.0),
                                         ("crowd_cbf_share", 0.0), ("crowd_cbf_max_constraints", 0),
                                         ("crowd_cbf_alpha_m_s2", float("nan"))])
def test_a_filter_parameter_out_of_range_is_refused_naming_it(field, value):
    with pytest.raises(ValueError, match=field):
        BackstopParams(**{field: value})


def test_a_vehicle_failed_in_hold_inside_a_gust_gets_the_full_constraint():
    # crossing --gust N = 300 seed 76 with vehicle 10 failing into Hold at 20.15 s, inside the gust: UAV 12's row is
    # crowded and the failed vehicle, hovering where the plan flies at 4 m/s, takes no half of the constraint. With the
    # half (the reciprocal share) UAV 12 braked 1.4 m/s^2 at 0.57 m closing at 1.4 m/s and met it (0.078 m, 1 pair)
    fly = partial(_gust_flight, "crossing", 300, 76, 60, True)
    m = fly(DEFAULT.backstop)
    assert m["collision_pairs"] == 0, m["collided_pairs_list"]
    m = _default_hold_flight("crossing", 300, 76, 60)
    assert m["collision_pairs"] == 0, m["collided_pairs_list"]
    # the full share alone (without BackstopParams.own_disturbance and escape_hover_in_crowd, which came later; the
    # first also flies it without a pair)
    alone = dataclasses.replace(DEFAULT.backstop, own_disturbance=False, escape_hover_in_crowd=False,
                                escape_brake_hypothesis="threat",
                                crowd_cbf_inside_no_approach=False, hover_latch_s=0.0)
    assert fly(alone)["collision_pairs"] == 0
    off = fly(dataclasses.replace(alone, crowd_cbf_hover_full_share=False))
    assert [10, 12] in off["collided_pairs_list"], off["collided_pairs_list"]


def _fly_at_obstacle(share, v0=3.0, dt_s=0.01, T_s=5.0, ds=0.3):
    """One vehicle driven at a_max into a vehicle that hovers and does not filter; the smallest distance."""
    s = np.array([[0.0, 0.0, v0, 0.0]])
    obstacle = np.array([[4.0, 0.0, 0.0, 0.0]])
    dmin = np.inf
    for _ in range(int(T_s / dt_s)):
        d = obstacle[0, 0:2] - s[0, 0:2]
        dmin = min(dmin, float(np.linalg.norm(d)))
        a_nom = (d / np.linalg.norm(d) * A_MAX)[None]
        a, _ = cbf_acc(s, a_nom, obstacle, np.zeros(1, dtype=int), np.array([0]), BP, ds, A_MAX, np.array([share]))
        s[0, 0:2] += s[0, 2:4] * dt_s + 0.5 * a[0] * dt_s ** 2
        s[0, 2:4] += a[0] * dt_s
    return dmin


def test_against_a_vehicle_that_takes_no_half_the_full_share_keeps_the_safe_distance():
    # the barrier's forward invariance needs both halves; a hovering (failed) vehicle gives none, so the row takes all
    assert _fly_at_obstacle(1.0) >= 0.99 * 0.3
    assert _fly_at_obstacle(0.5) < 0.99 * 0.3          # with only its half it comes closer than D_s


def test_every_other_row_takes_its_half_as_the_last_layer():
    # crossing --gust N = 1,000 seed 77 with vehicle 10 failing into Hold at 20.15 s, inside the gust: UAVs 63 and 87,
    # beside the failed vehicle, closed at 1.7 m/s while 63's row switched between the escape, the crowd's filter and
    # the push, and 87's was not crowded - the crowd's constraint assumed 87 took the other half; it took none (0.012 m).
    # With the filter as the last layer of the rows that sense a vehicle off the plan (BackstopParams.cbf_last_layer; an
    # option, off by default: docs/benchmarks.md, twenty-first round) the flight keeps 0.2 m (measured 0.230 m over the
    # whole 400-step flight)
    fly = partial(_gust_flight, "crossing", 1000, 77, 56, True)
    # (without BackstopParams.own_disturbance, which came later and flies it without a pair by itself:
    # tests/test_own_disturbance.py, nor escape_hover_in_crowd, later still)
    base = dataclasses.replace(DEFAULT.backstop, own_disturbance=False, escape_hover_in_crowd=False,
                                escape_brake_hypothesis="threat",
                                crowd_cbf_inside_no_approach=False, hover_latch_s=0.0)
    m = fly(dataclasses.replace(base, cbf_last_layer=True))
    assert m["collision_pairs"] == 0, m["collided_pairs_list"]
    assert m["min_separation_m"] >= 0.2, m["min_separation_m"]
    off = fly(base)
    assert [63, 87] in off["collided_pairs_list"], off["collided_pairs_list"]


def test_a_crowded_row_still_escapes_a_vehicle_hovering_in_the_stream():
    # paper --gust N = 300 seed 76 with vehicle 10 failing into Hold at 20.15 s: UAV 48 escaped it, swerved 1.2 m off its
    # particle, and its row became crowded (its blown neighbours no longer cleared as common mode); the crowd's filter,
    # braking along each line of sight among 16 constraints, met the failed vehicle at 0.052 m (closing at 1.9 m/s from
    # 1.7 m: braking at 2 m/s^2 after one period needs 1.8 m). The default keeps the escape against a vehicle hovering where
    # the plan flies for a row at stream speed that cannot brake short of it (BackstopParams.escape_hover_in_crowd and its
    # gates): 0.220 m over 400 steps
    fly = partial(_gust_flight, "paper", 300, 76, 60, True)
    # (the default flight; with the PD Hold and the default backstop it collided from the hover latch to the thirtieth
    # session: test_with_the_pd_hold_the_hover_latch_flight_passes_since_the_braking_flag_is_kept)
    m = _default_hold_flight("paper", 300, 76, 60)
    assert m["collision_pairs"] == 0, m["collided_pairs_list"]
    assert m["min_separation_m"] >= 0.2, m["min_separation_m"]
    # the mechanism, on the flight it was measured on (the PD Hold, and no hover latch nor the braking-as-hover rules,
    # which came later; with those two rules this held flight passes closer, 0.187 m, no pair)
    m = fly(dataclasses.replace(DEFAULT.backstop, hover_latch_s=0.0, escape_braking_as_hover=False,
                                common_mode_keeps_braking=False))
    assert m["collision_pairs"] == 0 and m["min_separation_m"] >= 0.2, (m["collided_pairs_list"], m["min_separation_m"])
    # (both with every off-plan vehicle predicted braking to a stop, as when the option was measured: escape_brake_hypothesis)
    off = fly(dataclasses.replace(THREAT, escape_hover_in_crowd=False))
    assert [10, 48] in off["collided_pairs_list"], off["collided_pairs_list"]


@pytest.mark.parametrize("family,n,seed,pair", [("circle", 300, 77, [3, 10]), ("paper", 1000, 78, [10, 565])])
def test_the_hover_escape_in_a_crowd_on_flights_it_was_not_written_for(family, n, seed, pair):
    # the other two failed-vehicle encounters of the twenty-second session's sweep (a crowded row braking at the failed
    # vehicle at 3-4 m/s closing from 3.4-3.8 m: its braking distance is 4 m), which the gates were not tuned on
    fly = partial(_gust_flight, family, n, seed, 62, True)
    m = fly(DEFAULT.backstop)
    assert m["collision_pairs"] == 0, m["collided_pairs_list"]
    assert m["min_separation_m"] >= 0.15, m["min_separation_m"]
    # with PX4's Hold (the default) no pair either (circle: 0.115 m, the failed vehicle drifting back after the gust)
    m = _default_hold_flight(family, n, seed, 62)
    assert m["collision_pairs"] == 0, m["collided_pairs_list"]
    # (both with every off-plan vehicle predicted braking to a stop, as when the option was measured: escape_brake_hypothesis)
    off = fly(dataclasses.replace(THREAT, escape_hover_in_crowd=False))
    assert pair in off["collided_pairs_list"], off["collided_pairs_list"]


def test_the_hover_escape_in_a_crowd_leaves_a_slow_departure_to_the_filter():
    # crossing --gust N = 137 seed 117 (no failure): the gust pins a group at its departure, its UAVs hover 5 m behind
    # their particles where the plan already flies. Ungated, the hover escape fired in the crowded rows there and UAVs
    # 115 / 124 swerved into each other (0.114 m); with the gates (row speed > 2 m/s, cannot brake short) it does not
    fly = partial(_gust_flight, "crossing", 137, 117, 60, False)
    m = fly(DEFAULT.backstop)
    assert m["collision_pairs"] == 0 and m["min_separation_m"] >= 0.25, m["min_separation_m"]
    ungated = fly(dataclasses.replace(THREAT, escape_hover_in_crowd_min_speed_m_s=0.0,
                                      escape_hover_in_crowd_brake_gate=False))
    assert ungated["min_separation_m"] < 0.15, ungated["min_separation_m"]

def test_cannot_brake_short_is_the_braking_distance_after_one_period():
    from mfg_autopilot.safety.backstop import cannot_brake_short

    a_max, react = 2.0, 0.5
    own = np.array([[0.0, 0.0, 4.0, 0.0]])
    # a hovering vehicle ahead: 4 m/s needs 4 m of braking + 2 m of reaction; the clearance 0.5 m is added to both cases
    at = lambda d: np.array([[d, 0.0, 0.0, 0.0]])   # noqa: E731
    zero = np.zeros(1, dtype=np.int64)
    assert cannot_brake_short(own, at(6.4), zero, np.array([0.5]), a_max, react)[0]        # 6.5 m needed
    assert not cannot_brake_short(own, at(6.6), zero, np.array([0.5]), a_max, react)[0]
    # opening, or passing abeam: no closing speed along the line of sight
    assert not cannot_brake_short(own, np.array([[-1.0, 0.0, 0.0, 0.0]]), zero, np.array([0.5]), a_max, react)[0]
    assert not cannot_brake_short(own, np.array([[0.0, 1.0, 0.0, 0.0]]), zero, np.array([0.5]), a_max, react)[0]
    # the same closing speed from the other vehicle's motion
    still = np.array([[0.0, 0.0, 0.0, 0.0]])
    assert cannot_brake_short(still, np.array([[6.4, 0.0, -4.0, 0.0]]), zero, np.array([0.5]), a_max, react)[0]
    assert cannot_brake_short(own, np.zeros((0, 4)), np.zeros(0, dtype=np.int64), np.zeros(0), a_max, react).shape == (0,)


def test_the_hover_escape_gate_is_validated():
    with pytest.raises(ValueError, match="escape_hover_in_crowd_min_speed_m_s"):
        dataclasses.replace(DEFAULT.backstop, escape_hover_in_crowd_min_speed_m_s=-1.0)


def test_inside_the_safe_distance_the_filter_accelerates_no_closer():
    # a pair 0.25 m apart, inside D_s = 0.3 m, where the barrier is undefined; the row's nominal command is the airframe's
    # 2 m/s^2 straight at the other vehicle (p = (-1, 0): accelerating towards it is a_x > 0)
    other = np.array([[0.25, 0.0, 0.0, 0.0]])
    a_nom = np.array([[A_MAX, 0.0]])
    for opening_m_s in (0.3, 0.0, -0.3):
        own = np.array([[0.0, 0.0, -opening_m_s, 0.0]])
        a, act = cbf_acc(own, a_nom, other, np.zeros(1, dtype=int), np.array([0]), BP, 0.3, A_MAX)
        # then, opening or closing, the command does not accelerate towards it
        assert act[0] and a[0, 0] <= 1e-9, (opening_m_s, a)
    # before (crowd_cbf_inside_no_approach off), a pair opening inside D_s had no constraint: the nominal went through
    own = np.array([[0.0, 0.0, -0.3, 0.0]])
    a, act = cbf_acc(own, a_nom, other, np.zeros(1, dtype=int), np.array([0]),
                     dataclasses.replace(BP, crowd_cbf_inside_no_approach=False, hover_latch_s=0.0), 0.3, A_MAX)
    assert not act[0] and np.array_equal(a, a_nom)


def _fly_inside_the_safe_distance(bp: BackstopParams) -> float:
    """One vehicle hovering (it does not filter), the other 0.25 m from it (inside D_s = 0.3 m), opening at 0.2 m/s,
    its nominal command 2 m/s^2 at the hovering one, filtered with the full share every control period (0.5 s, the
    command held in between, integrated every 0.01 s), for 10 s: the smallest distance."""
    s = np.array([[0.0, 0.0, -0.2, 0.1]])
    obstacle = np.array([[0.25, 0.0, 0.0, 0.0]])
    dmin = 0.25
    for _ in range(20):
        d = obstacle[0, 0:2] - s[0, 0:2]
        a, _ = cbf_acc(s, (d / np.linalg.norm(d) * A_MAX)[None], obstacle, np.zeros(1, dtype=int), np.array([0]), bp, 0.3,
                       A_MAX, np.array([1.0]))
        for _ in range(50):
            s[0, 0:2] += s[0, 2:4] * 0.01 + 0.5 * a[0] * 1e-4
            s[0, 2:4] += a[0] * 0.01
            dmin = min(dmin, float(np.linalg.norm(obstacle[0, 0:2] - s[0, 0:2])))
    return dmin


def test_inside_the_safe_distance_a_pair_that_opens_is_not_driven_back_in():
    # with the clamp it is not driven back in: it opens out past D_s, and the (continuous-time) barrier sampled every
    # 0.5 s lets it back to 0.241 m (measured), against 0.25 m at the start; without the clamp (the barrier undefined
    # inside D_s, no constraint while the pair opens) the held nominal command drives it into the other vehicle
    assert _fly_inside_the_safe_distance(BP) >= 0.2
    assert _fly_inside_the_safe_distance(dataclasses.replace(BP, crowd_cbf_inside_no_approach=False)) < 0.1


def test_a_row_inside_the_safe_distance_of_a_failed_vehicle_stops_driving_into_it():
    # merge --gust N = 300 seed 86, vehicle 10 failing into PX4's Hold (the default) at 20.15 s: UAV 38's crowded row,
    # 0.3 m from the failed vehicle (inside the filter's D_s = 0.35 m), was let through towards it whenever the pair
    # opened for a sample and pushed out when it closed, and met it at 0.065 m at 28 s. With the clamp: no pair
    fly = partial(_gust_flight, "merge", 300, 86, 60, True, hold="px4")
    m = fly(DEFAULT.backstop)
    assert m["collision_pairs"] == 0, m["collided_pairs_list"]
    off = fly(dataclasses.replace(DEFAULT.backstop, crowd_cbf_inside_no_approach=False))
    assert [10, 38] in off["collided_pairs_list"], off["collided_pairs_list"]


def test_with_the_pd_hold_the_hover_latch_flight_passes_since_the_braking_flag_is_kept():
    # paper --gust N = 300 seed 76, vehicle 10 failing at 20.15 s into the PD Hold, the default backstop, no inner loop:
    # before the thirtieth session UAV 88 escaped the failed vehicle, still hovering by the latch, on the side its row
    # chose, at 0.4-0.6 m from UAV 89 (six periods accelerating 0.7-1.9 m/s^2 towards it), 0.059 m (a strict xfail
    # here until then). Without the latch 0.256 m; with PX4's Hold (the default) 0.255 m; with the inner loop (the
    # default): the next test. Since the thirtieth session a vehicle the braking test flagged is not cleared as common
    # mode (BackstopParams.common_mode_keeps_braking): no pair, 0.187 m (0.251 m with that rule alone)
    m = _gust_flight("paper", 300, 76, 60, True, DEFAULT.backstop, "pd")
    assert m["collision_pairs"] == 0, m["collided_pairs_list"]
    before = _gust_flight("paper", 300, 76, 60, True, dataclasses.replace(
        DEFAULT.backstop, escape_braking_as_hover=False, common_mode_keeps_braking=False), "pd")
    assert [88, 89] in before["collided_pairs_list"], before["collided_pairs_list"]


def test_with_the_inner_loop_the_pd_hold_flight_keeps_its_rows_apart():
    # the previous flight with the inner loop (the default): the gust is fought inside the period, UAV 88's row is not
    # pushed onto the failed vehicle's side and no escape meets UAV 89
    m = _gust_flight("paper", 300, 76, 60, True, DEFAULT.backstop, "pd", inner_loop=True)
    assert m["collision_pairs"] == 0, m["collided_pairs_list"]
    assert m["min_separation_m"] >= 0.2, m["min_separation_m"]
