"""Simulator scaling (issue 8): the shortcuts that make N = 10,000 tractable give what the
plain all-pairs computations give (exactly, or within the stated tolerance)."""

from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial import cKDTree

import mfg_swarm.sim as sim
from mfg_autopilot.interface import HeardSummary, Neighbours
from mfg_autopilot.paper.features import make_sigma_F
from mfg_autopilot.paper.meanfield import KDE_TRUNCATION_TOL, fit_initial_fpk_weights, kde_at
from mfg_autopilot.presets import make_controller, preset_by_name, with_inner_loop
from mfg_swarm.scenarios import make_scenario
from mfg_swarm.sim import SimConfig, heard_summary_by_tree, simulate

DEFAULT = preset_by_name("default")


def _t0_states(n: int, seed: int) -> np.ndarray:
    """A paper grid with jittered positions and wind-like velocities, relative to the centroid."""
    rng = np.random.default_rng(seed)
    pos = make_scenario("paper", n).initial_pos_m + 0.2 * rng.standard_normal((n, 2))
    vel = np.array([1.0, -1.0]) + 0.1 * rng.standard_normal((n, 2))
    X = np.concatenate([pos, vel], axis=1)
    return X - X.mean(axis=0)


@pytest.mark.parametrize("n,seed", [(200, 0), (700, 1)])
def test_truncated_kde_is_within_its_bound_of_the_exact_one(n, seed):
    # given t = 0 states and the default bandwidth
    X = _t0_states(n, seed)
    h = np.asarray(DEFAULT.learner.fpk_kde_bandwidth)
    Y = np.concatenate([X, X + 0.5 * h], axis=0)
    # when the density is computed exactly and with the k-d tree cut-off
    exact = kde_at(Y, X, h, exact_max_points=10**9)
    trunc = kde_at(Y, X, h, exact_max_points=0)
    # then they differ by less than the stated bound, relative to the peak (plus rounding)
    assert np.max(np.abs(trunc - exact)) <= (KDE_TRUNCATION_TOL + 1e-14) * exact.max()
    # and so does the fitted w_F(0)
    sF = make_sigma_F(DEFAULT.learner.fpk_scale)
    w_exact = fit_initial_fpk_weights(sF, X, h, exact_max_points=10**9)
    w_trunc = fit_initial_fpk_weights(sF, X, h, exact_max_points=0)
    assert np.max(np.abs(w_trunc - w_exact)) <= 1e-8 * np.max(np.abs(w_exact))


def test_small_swarms_keep_the_exact_kde():
    X = _t0_states(50, 2)
    h = np.asarray(DEFAULT.learner.fpk_kde_bandwidth)
    z = (X[:, None, :] - X[None, :, :]) / h
    np.testing.assert_array_equal(kde_at(X, X, h), np.exp(-0.5 * np.sum(z * z, axis=2)).mean(axis=1))


@pytest.mark.parametrize("seed", [0, 1])
def test_heard_summary_by_tree_equals_the_one_from_the_complete_list(seed):
    # given scattered vehicles (some coincident) and a radio range covering part of them
    rng = np.random.default_rng(seed)
    pts = rng.uniform(0.0, 60.0, (1300, 2))
    pts[5] = pts[6]
    obs = np.concatenate([pts, rng.standard_normal((1300, 2))], axis=1)
    tree = cKDTree(pts)
    full = Neighbours.from_pairs(obs, tree.query_pairs(20.0, output_type="ndarray"))
    ref = HeardSummary.of(obs, full, 1300)
    counts = tree.query_ball_point(pts, 20.0, return_length=True) - 1
    got = heard_summary_by_tree(tree, pts, 20.0, counts)
    np.testing.assert_array_equal(got.count, ref.count)
    np.testing.assert_allclose(got.pos_sum_m, ref.pos_sum_m, rtol=1e-12)
    np.testing.assert_allclose(got.nearest_m, ref.nearest_m, rtol=1e-12)
    assert got.nearest_m[5] == 0.0


@pytest.mark.parametrize("scenario,n,range_m,extra", [("crossing", 36, 100.0, {}), ("dense", 49, 100.0, {}),
                                                      ("paper", 25, 100.0, {"fail_vehicle": 3, "fail_at_s": 10.0}),
                                                      ("paper", 144, 6.0, {})])     # d below the swarm's extent: local slots
def test_hjb_delivering_only_heard_states_within_the_cutoff_flies_the_same(monkeypatch, scenario, n, range_m, extra):
    # given HJB_d with the default controller (its heard_cutoff_m reach is well below d)
    cfg = SimConfig(scenario=make_scenario(scenario, n), mode="hjb", preset=DEFAULT, seed=4, steps=120, range_m=range_m, **extra)
    # when the simulator delivers every heard state, and when it delivers the cut-off list + summary
    monkeypatch.setattr(sim, "FULL_HEARD_MAX_STATES", 10**12)
    t_full, m_full = simulate(cfg, progress=False)
    monkeypatch.setattr(sim, "FULL_HEARD_MAX_STATES", 0)
    t_cut, m_cut = simulate(cfg, progress=False)
    # then the communication count is exact and the flight the same (up to the summation order of the
    # first step's centroid: equal to rounding)
    np.testing.assert_array_equal(t_cut.comm_states, t_full.comm_states)
    np.testing.assert_allclose(t_cut.pos_m, t_full.pos_m, rtol=0, atol=1e-9)
    assert m_cut["collision_pairs"] == m_full["collision_pairs"]


def test_heard_reach_bounds_the_repulsion_reach():
    # given a default HJB_d bank and states with one fast vehicle
    sc = make_scenario("paper", 9)
    ctrl = make_controller("hjb", DEFAULT, sc.destination_m)
    obs = np.concatenate([sc.initial_pos_m, np.zeros((9, 2))], axis=1)
    obs[4, 2:4] = [3.0, 4.0]
    base, extra, horizon_s = ctrl.heard_cutoff_m(0, obs)
    rp = DEFAULT.hjb_repulsion
    # then every pair's reach covers the repulsion radius plus the horizon at their relative speed
    rel = np.linalg.norm(obs[:, None, 2:4] - obs[None, :, 2:4], axis=2)
    assert np.all(base + extra[:, None] + extra[None, :] >= rp.radius_m + rp.horizon_s * rel)
    assert base >= rp.radius_m and horizon_s >= rp.horizon_s


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_pairs_within_reach_are_exactly_the_brute_force_ones(seed):
    # given scattered vehicles, a few of them with a large reach
    rng = np.random.default_rng(seed)
    pts = rng.uniform(0.0, 80.0, (900, 2))
    extra = np.abs(rng.standard_normal(900)) * 0.5
    extra[rng.integers(0, 900, 12)] = 6.0
    base = 1.0
    got = sim.pairs_within_reach(cKDTree(pts), pts, (base, extra), 100.0)
    # then they are the pairs i < j with |r_j - r_i| <= base + extra_i + extra_j, sorted
    d = np.linalg.norm(pts[:, None] - pts[None, :], axis=2)
    i, j = np.nonzero(np.triu(d <= base + extra[:, None] + extra[None, :], k=1))
    np.testing.assert_array_equal(got, np.stack([i, j], axis=1))
    assert sim.pairs_within_reach(cKDTree(pts), pts, (base, extra), 12.0) is None       # reaches the cap


@pytest.mark.parametrize("mode,scenario,n,extra", [("mfg", "dense", 49, {"fail_vehicle": 24, "fail_at_s": 10.0}), ("mfg", "paper", 25, {"fail_vehicle": 7, "fail_at_s": 20.0}),
                                                   ("mfg", "crossing", 50, {"fail_vehicle": 27, "fail_at_s": 15.0}),
                                                   # (a failure in the gust: with the 2.1 m cruise spacing, the
                                                   # thirty-third session's, the gust alone no longer wakes the backstop)
                                                   ("mfg", "swap4", 144, {"gust": sim.GustParams(), "fail_vehicle": 70,
                                                                          "fail_at_s": 20.15}),
                                                   ("mfg", "swap4", 100, {}),
                                                   ("mfg", "paper", 400, {"fail_vehicle": 0, "fail_at_s": 20.0}),
                                                   ("hjb", "crossing", 36, {"fail_vehicle": 3, "fail_at_s": 5.0})])
def test_sensing_only_within_the_sensed_cutoff_flies_bit_identically(monkeypatch, mode, scenario, n, extra):
    # given runs in which the backstop acts (dense formation, a failed vehicle)
    import mfg_autopilot.guidance.controller as pd
    cfg = SimConfig(scenario=make_scenario(scenario, n), mode=mode, preset=DEFAULT, seed=0, steps=160,
                    range_m=1.0 if mode == "hjb" else None, **extra)       # HJB_1: sensed but not heard vehicles
    # when the simulator delivers what the sensor sees within its range, and only within sensed_cutoff_m
    t_cut, m_cut = simulate(cfg, progress=False)
    monkeypatch.setattr(pd._DefaultBase, "sensed_cutoff_m", lambda self, states, sensed_states=None: None)
    monkeypatch.setattr(pd.DefaultMFGController, "sensed_cutoff_m", lambda self, states, sensed_states=None: None)
    t_all, m_all = simulate(cfg, progress=False)
    # then the flights are the same bit for bit
    assert m_all["backstop_activations"] > 0
    assert m_cut["backstop_activations"] == m_all["backstop_activations"]
    np.testing.assert_array_equal(t_cut.acc_m_s2, t_all.acc_m_s2)
    np.testing.assert_array_equal(t_cut.pos_m, t_all.pos_m)


@pytest.mark.parametrize("scenario,n,range_m,extra", [("dense", 49, 12.0, {"fail_vehicle": 3, "fail_at_s": 5.0}),
                                                      ("crossing", 36, 100.0, {})])
def test_hjb_without_sensing_when_every_sensed_vehicle_is_heard_flies_bit_identically(monkeypatch, scenario, n, range_m, extra):
    # given HJB_d with a radio range covering the 10 m sensor range (every sensed vehicle is also heard)
    import mfg_autopilot.guidance.controller as pd
    cfg = SimConfig(scenario=make_scenario(scenario, n), mode="hjb", preset=DEFAULT, seed=1, steps=120, range_m=range_m, **extra)
    assert DEFAULT.backstop.sensor_range_m <= range_m
    # when the simulator skips sensing (the controller ignores sensed vehicles it heard) and when it senses
    t_skip, m_skip = simulate(cfg, progress=False)
    monkeypatch.setattr(pd.DefaultHJBController, "ignores_sensed_if_heard", False)
    t_sense, m_sense = simulate(cfg, progress=False)
    # then the flights are the same bit for bit
    np.testing.assert_array_equal(t_skip.acc_m_s2, t_sense.acc_m_s2)
    np.testing.assert_array_equal(t_skip.pos_m, t_sense.pos_m)
    np.testing.assert_array_equal(t_skip.comm_states, t_sense.comm_states)
    assert m_skip["backstop_activations"] == m_sense["backstop_activations"] == 0


def test_phi_G_equals_a_per_row_brute_force_quadrature():
    # given a default MFG bank of 25 after the t = 0 exchange, with FPK weights that differ per row
    import mfg_autopilot.guidance.controller as pd
    from mfg_autopilot.paper.costs import cs_kernel
    sc = make_scenario("paper", 25)
    s0 = np.concatenate([sc.initial_pos_m, np.tile(DEFAULT.cost.v_o, (25, 1))], axis=1)
    ctrl = pd.DefaultMFGController(DEFAULT, sc.destination_m)
    ctrl.exchange_t0(s0, np.arange(25), np.arange(25), sc.destination_m)
    rng = np.random.default_rng(5)
    ctrl.w_F = ctrl.w_F + 0.3 * rng.standard_normal(ctrl.w_F.shape)
    own = s0 + np.concatenate([rng.normal(0.0, 0.5, (25, 2)), rng.normal(0.0, 0.2, (25, 2))], axis=1)
    x = ctrl.plan.states
    centroid = x.mean(axis=0)
    # when phi_G is evaluated (k-d tree pairs, FPK weights summed feature by feature)
    phi, npairs = ctrl._phi_G(own, centroid)
    # then it is eq. 11's FPK-weighted quadrature over the other particles within phi_g_radius_m, row by row
    ref, count = np.zeros(25), 0
    sig = ctrl.sigma_F.value(x - centroid[None, :])
    for i in range(25):
        j = np.flatnonzero(np.linalg.norm(x[:, 0:2] - own[i, 0:2], axis=1) <= DEFAULT.tracking.phi_g_radius_m)
        j = j[j != ctrl.own_index[i]]
        count += j.size
        w = np.maximum(sig[j] @ ctrl.w_F[i], 0.0)
        w = w / w.sum() if w.sum() > 0 else np.full(j.size, 1.0 / max(j.size, 1))
        ref[i] = np.sum(w * cs_kernel(np.repeat(own[i:i + 1], j.size, axis=0), x[j], DEFAULT.cost))
    assert npairs == count and count > 25
    np.testing.assert_allclose(phi, ref, rtol=1e-12, atol=1e-15)


def test_mfg_sensed_cutoff_covers_the_escape_once_a_vehicle_leaves_the_plan():
    # given a default MFG bank after the t = 0 exchange, everyone on the plan
    import mfg_autopilot.guidance.controller as pd
    sc = make_scenario("paper", 9)
    s0 = np.concatenate([sc.initial_pos_m, np.tile(DEFAULT.cost.v_o, (9, 1))], axis=1)
    ctrl = pd.DefaultMFGController(DEFAULT, sc.destination_m)
    ctrl.exchange_t0(s0, np.arange(9), np.arange(9), sc.destination_m)
    # then the simulator may cut the sensed set to the trigger reach
    reach = ctrl.sensed_cutoff_m(ctrl.plan.states.copy())
    assert reach is not None and reach[0] < DEFAULT.backstop.sensor_range_m
    # when one vehicle hovers while the plan moves on (a failed vehicle: the escape may act and then weighs
    # every sensed vehicle under candidate accelerations up to a_max), the whole sensor range is needed
    off = ctrl.plan.states.copy()
    off[4, 2:4] = 0.0
    assert ctrl.sensed_cutoff_m(off) is None


def test_mfg_sensed_cutoff_widens_only_the_rows_within_the_sensor_range_of_a_vehicle_off_the_plan():
    # given a default MFG bank of 400 (28 m across) after the t = 0 exchange
    import mfg_autopilot.guidance.controller as pd
    sc = make_scenario("paper", 400)
    s0 = np.concatenate([sc.initial_pos_m, np.tile(DEFAULT.cost.v_o, (400, 1))], axis=1)
    ctrl = pd.DefaultMFGController(DEFAULT, sc.destination_m)
    ctrl.exchange_t0(s0, np.arange(400), np.arange(400), sc.destination_m)
    bp = DEFAULT.backstop
    on_plan = ctrl.sensed_cutoff_m(ctrl.plan.states.copy())
    # when one vehicle at the swarm's edge hovers while the plan moves on, or one row is blown 1.1 m off its particle
    # to 0.3 m from its neighbour's (on the plan, but it may yield: its escape weighs every vehicle it senses)
    for bad, change in ((0, "hover"), (399, "blown")):
        x = ctrl.plan.states.copy()
        if change == "hover":
            x[bad, 2:4] = 0.0
        else:
            x[bad, 0:2] = x[398, 0:2] + 0.3 * (x[bad, 0:2] - x[398, 0:2]) / np.linalg.norm(x[bad, 0:2] - x[398, 0:2])
        base, extra, horizon_s, wide_rows = ctrl.sensed_cutoff_m(x)
        # then the rows within the sensor range of the hovering vehicle (or the blown row alone) get the whole range,
        # exempt from the closest-approach test, and every other row the reach it has while everyone flies the plan
        d = np.linalg.norm(x[:, 0:2] - x[bad, 0:2], axis=1)
        wide = d <= bp.sensor_range_m if change == "hover" else np.arange(400) == bad
        np.testing.assert_array_equal(wide_rows, wide)
        assert not np.any(on_plan[3]) and horizon_s == on_plan[2] == max(bp.horizon_s, bp.gap_push_horizon_s)
        assert base == on_plan[0]
        assert np.all(extra[wide] >= bp.sensor_range_m)
        np.testing.assert_array_equal(extra[~wide], on_plan[1][~wide])
        assert 0 < wide.sum() < 400 and np.all(extra[~wide] < bp.sensor_range_m / 2)
    # when the plan has parked every particle in its slot and vehicle 5 sits 0.1 m from vehicle 6's parked particle
    # (on the plan; to row 6 it claims its slot: unplanned, own_slot_claim)
    while np.any(np.hypot(ctrl.plan.states[:, 2], ctrl.plan.states[:, 3]) > 0.0):
        ctrl.plan.advance()
    ctrl._cutoff_hist.clear()            # the braking test has no previous sample here: not this case
    x = ctrl.plan.states.copy()
    x[5, 0:2] = x[6, 0:2] + np.array([0.1, 0.0])
    b = replace(DEFAULT.backstop, plan_mismatch_brake_m_s2=0.0)
    ctrl.preset = replace(DEFAULT, backstop=b)
    base, extra, _, wide_rows = ctrl.sensed_cutoff_m(x)
    # then row 6 (its slot claimed) and row 5 (1.4 m off its particle: it may yield) get the whole range, no other
    assert set(np.flatnonzero(extra >= bp.sensor_range_m)) == {5, 6} == set(np.flatnonzero(wide_rows))


# the gust flights are held (no inner loop, the default since the twenty-eighth session): with the inner loop no row
# flags a vehicle braking in them, and the test would not be exercised
@pytest.mark.parametrize("scenario,n,seed,extra,inner", [("swap4", 144, 3, {"gust": sim.GustParams()}, False),
                                                         ("crossing", 100, 7, {"fail_vehicle": 10, "fail_at_s": 20.0}, True),
                                                         ("paper", 100, 4, {"fail_vehicle": 10, "fail_at_s": 20.0}, True),
                                                         ("dense", 144, 2, {"gust": sim.GustParams()}, False),
                                                         ("circle", 100, 4, {"fail_vehicle": 3, "fail_at_s": 12.0}, True)])
def test_the_cutoffs_braking_superset_holds_every_vehicle_a_row_flags(monkeypatch, scenario, n, seed, extra, inner):
    """sensed_cutoff_m's _braking_superset evaluates the braking test on the states as sensed, with the w_H of every row
    within the sensor range and a bound on act()'s model update in between: every vehicle that a row's braking test
    flags at a step (_unplanned_by_braking, in the flight itself) is in it. The old test (true states, the
    quantisation's margins, no tracking residual) flagged many more: that difference is what widened the rows."""
    import mfg_autopilot.guidance.controller as pd

    sup_at, flagged_at, old_count = {}, {}, [0]
    orig_sup, orig_flag = pd.DefaultMFGController._braking_superset, pd.DefaultMFGController._unplanned_by_braking

    def sup(self, states, q, prev, a_plan, k):
        out = orig_sup(self, states, q, prev, a_plan, k)
        sup_at[k] = set(np.flatnonzero(out).tolist())
        bp, dt = self.preset.backstop, self.preset.dt_s
        a_marg = 2.0 * self._SENSED_VEL_MARGIN_M_S / dt
        m2 = self._SENSED_POS_MARGIN_M + bp.plan_mismatch_s * self._SENSED_VEL_MARGIN_M_S \
            + (0.5 * dt * dt + bp.plan_mismatch_s * dt) * a_marg
        hint = np.arange(states.shape[0])
        old = pd.braking_off_plan(states, prev[:, 2:4], a_plan, dt, bp.plan_mismatch_brake_m_s2 - a_marg,
                                  lambda x, rows: self._beyond_plan(x, bp.plan_mismatch_m - m2, hint[rows]))
        old_count[0] += int(old.sum())
        return out

    def flag(self, sn, step, unplanned, own):
        out = orig_flag(self, sn, step, unplanned, own)
        flagged_at.setdefault(step, set()).update(np.asarray(sn.ids)[out].tolist())
        return out

    monkeypatch.setattr(pd.DefaultMFGController, "_braking_superset", sup)
    monkeypatch.setattr(pd.DefaultMFGController, "_unplanned_by_braking", flag)
    cfg = SimConfig(scenario=make_scenario(scenario, n), mode="mfg", preset=with_inner_loop(DEFAULT, inner), seed=seed,
                    steps=120, **extra, acc_lag_s=0.0)     # staged on the paper's plant: with PX4's lag no row flags braking
    simulate(cfg, progress=False)
    n_flagged = sum(len(v) for v in flagged_at.values())
    assert n_flagged > 0                                   # the test is exercised: rows did flag by braking
    for k, ids in flagged_at.items():
        assert ids <= sup_at.get(k, set()), (k, ids - sup_at.get(k, set()))
    n_sup = sum(len(v) for v in sup_at.values())
    assert n_sup < old_count[0]


def test_the_cutoffs_braking_superset_flags_nothing_in_calm_cruise(monkeypatch):
    """Calm swap4 (four streams through the middle): the old margin test flagged vehicles at most steps (their tracking
    jitter looked like braking within its margins), each widening every row within 10 m; the superset flags none."""
    import mfg_autopilot.guidance.controller as pd

    counts, orig = [], pd.DefaultMFGController._braking_superset

    def sup(self, states, q, prev, a_plan, k):
        out = orig(self, states, q, prev, a_plan, k)
        counts.append(int(out.sum()))
        return out

    monkeypatch.setattr(pd.DefaultMFGController, "_braking_superset", sup)
    simulate(SimConfig(scenario=make_scenario("swap4", 400), mode="mfg", preset=DEFAULT, seed=1, steps=100), progress=False)
    assert len(counts) == 99 and sum(counts) == 0


def test_the_model_update_bound_holds_for_every_rows_hjb_step_in_a_flight(monkeypatch):
    """_braking_superset's delta_i: act()'s change of each row's w_H (hjb_update, after the cutoff) is at most
    _model_update_bound's figure for that row, computed at the cutoff from the states and the plan (a gust and a failed
    vehicle, so that rows are detoured and errors are large); and the leash-box bound is above |e_v| |J_v(e)|_F at
    seeded random errors in the box."""
    import mfg_autopilot.guidance.controller as pd

    bound_at, step_of, checked, worst = {}, [None], [0], [0.0]
    orig_cut, orig_hjb = pd.DefaultMFGController.sensed_cutoff_m, pd.hjb_update

    def cut(self, states, sensed_states=None):
        out = orig_cut(self, states, sensed_states)
        bound_at[self.plan.k] = self._model_update_bound(np.asarray(states, dtype=float), np.arange(self.n))
        step_of[0] = self.plan.k
        return out

    def hjb(sigma, w, e, phi_g, preset):
        res = orig_hjb(sigma, w, e, phi_g, preset)
        d = bound_at.get(step_of[0])
        if d is not None:
            step = np.linalg.norm(res[0] - w, axis=1)
            assert np.all(step <= d + 1e-12), (step_of[0], np.max(step - d))
            checked[0] += step.size
            worst[0] = max(worst[0], float(np.max(step / d)))
        return res

    monkeypatch.setattr(pd.DefaultMFGController, "sensed_cutoff_m", cut)
    monkeypatch.setattr(pd, "hjb_update", hjb)
    simulate(SimConfig(scenario=make_scenario("crossing", 100), mode="mfg", preset=DEFAULT, seed=4, steps=80,
                       fail_vehicle=10, fail_at_s=20.0, gust=sim.GustParams()), progress=False)
    assert checked[0] > 50 * 100 and worst[0] > 0.5          # the bound is met and not vacuous
    ctrl = pd.DefaultMFGController(DEFAULT, make_scenario("paper", 4).destination_m)
    tp = DEFAULT.tracking
    rng = np.random.default_rng(7)
    e = np.concatenate([rng.uniform(-1, 1, (2000, 2)) * tp.e_pos_max_m, rng.uniform(-1, 1, (2000, 2)) * tp.e_vel_max_m_s],
                       axis=1)
    e = ctrl._leash(e)
    jv = np.sqrt(np.einsum("kmd,kmd->k", ctrl._feature_grad_v(e), ctrl._feature_grad_v(e)))
    assert np.all(np.linalg.norm(e[:, 2:4], axis=1) * jv <= ctrl._box_grad_bound())
