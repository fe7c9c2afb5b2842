"""The numba kernels (mfg_autopilot/paper/kernels.py) against the numpy code they replaced
(tests/_numpy_reference.py, verbatim from commit c6952e1), and their row independence.

Tolerances (stated in the kernels' docstring and docs/benchmarks.md): feature tables
rtol 1e-13 (integer powers by repeated multiplication, 1/scale multiplied instead of
divided; observed <= 4.5e-16); the fused updates and phi_G rtol 1e-12 on each output,
relative to the magnitude of the terms summed (sums in another order; observed <= 1.1e-14)."""

import subprocess
import sys

import numpy as np
import pytest

import mfg_autopilot.guidance.controller as pd
from mfg_autopilot.paper import kernels
from mfg_autopilot.paper.features import make_sigma_F, make_sigma_H
from mfg_autopilot.paper.learners import hjb_update
from mfg_autopilot.paper.meanfield import MeanField
from mfg_autopilot.paper.model import nominal_drift, optimal_action
from mfg_autopilot.presets import preset_by_name
from mfg_swarm.scenarios import make_scenario

sys.path.insert(0, str(__import__("pathlib").Path(__file__).parent))
import _numpy_reference as ref  # noqa: E402

DEFAULT = preset_by_name("default")
PAPER = preset_by_name("paper")
FEATS = [(make_sigma_H, (200.0, 200.0, 2.0, 2.0), 200.0), (make_sigma_H, (1.0, 1.0, 1.0, 1.0), 0.5),
         (make_sigma_F, (10.0, 10.0, 2.0, 2.0), 10.0)]


@pytest.fixture
def threads_for_every_bank(monkeypatch):
    monkeypatch.setattr(kernels, "PARALLEL_MIN_ROWS", 1)


def _states(rng, n, pos_sd, vel_sd=1.0):
    return np.concatenate([rng.normal(0.0, pos_sd, (n, 2)), rng.normal(0.0, vel_sd, (n, 2))], axis=1)


@pytest.mark.parametrize("make,scale,pos_sd", FEATS)
def test_feature_tables_equal_the_numpy_tables_to_rounding(make, scale, pos_sd):
    # given random states (some exactly 0 in a coordinate: 0^0 = 1 and the e = 0 derivatives)
    rng = np.random.default_rng(11)
    feats, old = make(scale), ref.NumpyFeatures(make(scale))
    s = _states(rng, 300, pos_sd)
    s[:20, 2] = 0.0
    # when the tables are computed by the kernels and by the former numpy code
    sig, J, Hv = feats.value_grad_hessvel(s)
    sig0, J0, Hv0 = old.value_grad_hessvel(s)
    # then they agree to a few ulp, element by element (products only: no cancellation)
    np.testing.assert_allclose(sig, sig0, rtol=1e-13, atol=0)
    np.testing.assert_allclose(J, J0, rtol=1e-13, atol=0)
    np.testing.assert_allclose(Hv, Hv0, rtol=1e-13, atol=0)
    np.testing.assert_allclose(feats.hessian(s), old.hessian(s), rtol=1e-13, atol=0)
    np.testing.assert_array_equal(feats.value(s), sig)
    np.testing.assert_array_equal(feats.value_grad(s)[1], J)
    w = rng.normal(size=(300, feats.M))
    np.testing.assert_allclose(feats.grad_psi(s, w), np.einsum("nmd,nm->nd", J0, w),
                               rtol=0, atol=1e-12 * np.max(np.abs(J0[:, :, :, None] * w[:, :, None, None])))


def _close(new, old, terms_scale, rtol=1e-12):
    """|new - old| <= rtol * (magnitude of the terms that were summed), element-wise."""
    new, old = np.asarray(new, dtype=float), np.asarray(old, dtype=float)
    assert new.shape == old.shape
    err, bound = np.abs(new - old), rtol * np.broadcast_to(terms_scale, new.shape)
    assert np.all(err <= bound), f"worst |new - old| / bound = {np.max(err / bound):.3g} (rtol {rtol})"


@pytest.mark.parametrize("preset,pos_sd", [(PAPER, 150.0), (DEFAULT, 0.3)])
def test_hjb_update_equals_the_numpy_update_to_rounding(preset, pos_sd):
    # given a bank of learners with random weights at random states; for the default preset the
    # tracking cost and leashed errors its controller uses, so that R is active in some rows
    rng = np.random.default_rng(3)
    if preset is DEFAULT:
        preset = pd.DefaultMFGController(DEFAULT, np.zeros((1, 2))).track_preset
    sigma = make_sigma_H(preset.learner.state_scale)
    n = 400
    s = _states(rng, n, pos_sd, 0.5)
    w = rng.normal(size=(n, sigma.M)) * 0.1
    phi = rng.uniform(0.0, 2.0, n)
    # when the kernel and the former numpy code update
    w1, H1, act1, (gp1, lap1) = hjb_update(sigma, w, s, phi, preset)
    w0, H0, act0, (_, J0, Hv0) = ref.hjb_update(sigma, w, s, phi, preset)
    # then residual, activity and weights agree to rounding
    assert act1.any() and (~act1).any(), "both branches of the regulariser should be covered"
    np.testing.assert_array_equal(act1, act0)
    _close(H1, H0, 1.0 + np.abs(H0))
    _close(w1, w0, preset.learner.mu + preset.learner.c_H * np.max(np.abs(w1 - w0), axis=1, keepdims=True))
    # and the returned gradient / velocity Laplacian are those of the new weights at s
    _close(gp1, np.einsum("nmd,nm->nd", J0, w1), np.einsum("nmd,nm->nd", np.abs(J0), np.abs(w1)))
    _close(lap1, np.einsum("nm,nm->n", Hv0[:, :, 0, 0] + Hv0[:, :, 1, 1], w1),
           np.einsum("nm,nm->n", np.abs(Hv0[:, :, 0, 0]) + np.abs(Hv0[:, :, 1, 1]), np.abs(w1)))


def _default_bank(n_uav, rng):
    sc = make_scenario("paper", n_uav)
    s0 = np.concatenate([sc.initial_pos_m, np.tile(DEFAULT.cost.v_o, (n_uav, 1))], axis=1)
    ctrl = pd.DefaultMFGController(DEFAULT, sc.destination_m)
    ctrl.exchange_t0(s0, np.arange(n_uav), np.arange(n_uav), sc.destination_m)
    ctrl.w_F = ctrl.w_F + 0.3 * rng.standard_normal(ctrl.w_F.shape)
    own = s0 + np.concatenate([rng.normal(0.0, 0.5, (n_uav, 2)), rng.normal(0.0, 0.2, (n_uav, 2))], axis=1)
    return ctrl, own


def test_default_fpk_update_equals_the_numpy_update_to_rounding():
    # given a default MFG bank after the t = 0 exchange with per-row FPK weights
    rng = np.random.default_rng(7)
    ctrl, own = _default_bank(81, rng)
    x = ctrl.plan.states
    centroid = x.mean(axis=0)
    rate = nominal_drift(x, ctrl.plan.action(), DEFAULT.cost).mean(axis=0)
    a = rng.normal(0.0, 1.0, (81, 2))
    hv_tr = rng.normal(0.0, 1.0, 81)
    old = ref.DefaultMFGNumpy(ctrl)
    # when both update the FPK weights
    old._fpk_update(own, None, a, centroid, rate, hv_tr)
    w0 = ctrl.w_F.copy()
    ctrl._fpk_update(own, a, centroid, rate, hv_tr)
    # then the new weights agree to rounding (a normalised step of length mu)
    _close(ctrl.w_F, old.w_F, DEFAULT.learner.mu + np.abs(w0))


def test_paper_meanfield_fpk_update_equals_the_numpy_update_to_rounding():
    rng = np.random.default_rng(8)
    n = 9
    sc = make_scenario("paper", n)
    S0 = np.concatenate([sc.initial_pos_m, np.tile(PAPER.cost.v_o, (n, 1))], axis=1)
    mf = MeanField(S0, sc.destination_m, np.arange(n), PAPER)
    sigma_H = make_sigma_H(PAPER.learner.state_scale)
    w_H = rng.normal(size=(n, sigma_H.M))
    mf.begin_step(sigma_H, w_H)
    s_abs = S0 + rng.normal(0.0, 1.0, S0.shape)
    s_rel = s_abs - np.concatenate([sc.destination_m, np.zeros((n, 2))], axis=1)
    feats = ref.NumpyFeatures(sigma_H).value_grad_hessvel(s_rel)
    w_ref, F_ref = ref.meanfield_fpk_update(mf, s_abs, s_rel, w_H, feats)
    J, Hv = feats[1], feats[2]
    post = (np.einsum("nmd,nm->nd", J, w_H), np.einsum("nm,nm->n", Hv[:, :, 0, 0] + Hv[:, :, 1, 1], w_H))
    w_before = mf.w_F.copy()
    mf.fpk_update(s_abs, s_rel, post)
    _close(mf.w_F, w_ref, PAPER.learner.mu + np.abs(w_before))
    _close(mf.last_residual, F_ref, 1e-6 + np.abs(F_ref))


@pytest.mark.parametrize("n_uav", [25, 300])
def test_phi_G_equals_the_numpy_quadrature_to_rounding(n_uav):
    # given a default MFG bank (25: pairs by a scan over the particles; 300: by the cell grid)
    rng = np.random.default_rng(5)
    ctrl, own = _default_bank(n_uav, rng)
    centroid = ctrl.plan.states.mean(axis=0)
    # when phi_G is evaluated by the kernel and by the former k-d tree + numpy code
    phi, npairs = ctrl._phi_G(own, centroid)
    phi0, npairs0 = ref.DefaultMFGNumpy(ctrl)._phi_G(own, centroid)
    # then the same pairs enter and the quadratures agree to rounding
    assert npairs == npairs0 and npairs > n_uav
    _close(phi, phi0, np.abs(phi0))


@pytest.mark.parametrize("n_uav", [25, 300])
def test_every_kernel_row_is_independent_of_the_bank_and_of_the_threads(n_uav, monkeypatch):
    # given a default MFG bank and, for every row, the same row alone (a vehicle's own controller)
    rng = np.random.default_rng(9)
    ctrl, own = _default_bank(n_uav, rng)
    x, centroid = ctrl.plan.states, ctrl.plan.states.mean(axis=0)
    e = own - x
    w_H = ctrl.w_H + 0.05 * rng.standard_normal(ctrl.w_H.shape)
    rows = list(range(0, n_uav, max(1, n_uav // 12)))
    sF, sH, tp = ctrl.sigma_F, ctrl.sigma_H, ctrl.track_preset

    def run(idx):
        phi, _ = kernels.phi_G_plan(own[idx], ctrl.own_index[idx], x, centroid, sF.exponents, sF.scale, ctrl.w_F[idx],
                                    DEFAULT.tracking.phi_g_radius_m, DEFAULT.cost.eps_m2, DEFAULT.cost.beta)
        w1, H, act, (gp, lap) = hjb_update(sH, w_H[idx], e[idx], phi, tp)
        wF, F = kernels.fpk_update_rows(sF.exponents, sF.scale, own[idx] - centroid, own[idx], optimal_action(gp, 1.5),
                                        np.zeros((len(idx), 4)), lap, ctrl.w_F[idx], 0.1, DEFAULT.cost.v_o, 1.5, 0.01,
                                        np.eye(2) * 0.01)
        tab = sF.value_grad_hessvel(own[idx] - centroid)
        return [phi, w1, H, act, gp, lap, wF, F, *tab, sH.grad_psi(e[idx], w_H[idx]), sF.hessian(own[idx] - centroid)]

    all_rows = np.arange(n_uav)
    serial = run(all_rows)
    monkeypatch.setattr(kernels, "PARALLEL_MIN_ROWS", 1)
    threaded = run(all_rows)
    singles = [run(np.array([i])) for i in rows]
    # then the threaded bank equals the single-threaded one, and each row alone equals its row, bit for bit
    for a, b in zip(serial, threaded):
        np.testing.assert_array_equal(a, b)
    for i, single in zip(rows, singles):
        for a, b in zip(serial, single):
            np.testing.assert_array_equal(a[i:i + 1], b)


def test_a_bank_of_one_starts_no_worker_thread():
    # given a fresh process that runs a default MFG controller of one vehicle for a few steps
    code = """
import numpy as np, numba, threading
from mfg_autopilot.interface import Observation
from mfg_autopilot.presets import make_controller
from mfg_autopilot.presets import preset_by_name
from mfg_swarm.scenarios import make_scenario
p = preset_by_name("default"); sc = make_scenario("paper", 25)
s0 = np.concatenate([sc.initial_pos_m, np.tile(p.cost.v_o, (25, 1))], axis=1)
c = make_controller("mfg", p, sc.destination_m[0:1]); c.exchange_t0(s0, np.arange(25), np.array([0]), sc.destination_m)
for k in range(3):
    c.step(Observation(k, k * p.dt_s, s0[0:1].copy(), None, None))
try:
    numba.threading_layer(); print("threads started")
except ValueError:
    print("no threads", threading.active_count())
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    # then numba's threading layer was never started
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip().splitlines()[-1] == "no threads 1"


def test_plan_distance_shortcut_gives_exactly_the_tree_decision():
    # given a default MFG bank and states around the plan particles, many of them near the mismatch threshold
    rng = np.random.default_rng(12)
    ctrl, _ = _default_bank(81, rng)
    x = ctrl.plan.states
    thr = DEFAULT.backstop.plan_mismatch_m
    ps = DEFAULT.backstop.plan_mismatch_s
    u = rng.normal(size=(400, 4))
    u /= np.linalg.norm(u * np.array([1.0, 1.0, ps, ps]), axis=1, keepdims=True)
    hint = rng.integers(0, 81, 400)
    q = x[hint] + u * thr * rng.choice([0.5, 1.0 - 1e-12, 1.0, 1.0 + 1e-12, 3.0], 400)[:, None]
    # when the own-particle shortcut decides (right hint, wrong hint, no hint)
    expected = ctrl._plan_distance(q) > thr
    # then it is the k-d tree's decision for every state
    assert expected.any() and (~expected).any()
    np.testing.assert_array_equal(ctrl._beyond_plan(q, thr, hint), expected)
    np.testing.assert_array_equal(ctrl._beyond_plan(q, thr, (hint + 7) % 81), expected)
    np.testing.assert_array_equal(ctrl._beyond_plan(q, thr), expected)


def test_a_control_step_compiles_nothing_after_the_warm_up():
    """A kernel first called with argument types the warm-up did not use (another array layout, a
    read-only array) compiles again inside a control step - seconds on a flight's clock (seen: a
    real-time flight's first escape stalled its controllers ~14 s). Given a fresh process that builds
    a default MFG controller of one vehicle (which runs kernels.warm_up), when it flies steps whose
    sensed traffic comes through the process path (ADSB_VEHICLE reports decoded by adsb_states) with
    a failed vehicle hovering ahead (the escape acts) and planned neighbours (the half-plane push),
    then no numba dispatcher gained a compiled signature."""
    code = """
import numpy as np, numba
from numba.core.registry import CPUDispatcher
from mavlink_bridge.adsb import adsb_states
from mock_vehicle.proximity import DEFAULT_HOME_DEG, traffic_reports
from mfg_autopilot.safety import kernels as backstop_kernels
from mfg_autopilot.paper import kernels
from mfg_autopilot.interface import Neighbours, Observation
from mfg_autopilot.presets import make_controller
from mfg_autopilot.presets import preset_by_name
from mfg_swarm.scenarios import make_scenario
p = preset_by_name("default"); n = 25; sc = make_scenario("dense", n)
s0 = np.concatenate([sc.initial_pos_m, np.tile(p.cost.v_o, (n, 1))], axis=1)
c = make_controller("mfg", p, sc.destination_m[0:1])
def sigs():
    return {f"{m.__name__}.{k}": len(v.signatures) for m in (kernels, backstop_kernels) for k, v in vars(m).items()
            if isinstance(v, CPUDispatcher)}
before = sigs()
c.exchange_t0(s0, np.arange(n), np.array([0]), sc.destination_m)
home = tuple(DEFAULT_HOME_DEG)
escapes = pushes = 0
for k in range(12):
    x = c.plan.states
    own = x[0:1].copy()
    others = x[1:6].copy()
    others[0, 0:2] = own[0, 0:2] + 2.0 * own[0, 2:4] / max(np.linalg.norm(own[0, 2:4]), 1e-9)   # a failed vehicle ahead
    others[0, 2:4] = 0.0
    others[1, 0:2] = own[0, 0:2] + [0.0, 0.3]                                               # a planned one too close
    ids, st = adsb_states(traffic_reports(np.arange(1, 6), others, 1000 * k, home), home)
    info = c.step(Observation(k, k * p.dt_s, own, None, Neighbours(st, np.zeros(len(ids), dtype=np.int64), ids)))
    escapes += int(c.backstop_active[0])
after = sigs()
print("escapes", escapes)
print("new", sorted(k for k in after if after[k] != before.get(k, 0)))
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-3000:]
    lines = out.stdout.strip().splitlines()
    assert int(lines[-2].split()[1]) > 0            # the backstop acted (the case reaches its kernels)
    assert lines[-1] == "new []"


def test_formation_sums_equal_the_numpy_formulation():
    """safety.kernels.formation_sums (the MFG tracking's formation mean) gives, bit for bit, the sums and counts of
    the numpy code it replaced (selection by id, formation radius and outlier bound; np.bincount sums)."""
    from mfg_autopilot.safety.kernels import formation_sums

    rng = np.random.default_rng(12)
    n, N, m = 7, 40, 300
    plan = np.concatenate([rng.uniform(-5, 5, (N, 2)), rng.normal(0, 1, (N, 2))], axis=1)
    own_index = rng.choice(N, n, replace=False).astype(np.int64)
    e = rng.normal(0, 0.3, (n, 4))
    own = plan[own_index] + e
    owner = np.sort(rng.integers(0, n, m)).astype(np.int64)
    ids = rng.integers(100, 100 + N + 5, m).astype(np.int64)           # a few ids unknown to the plan
    plan_ids = 100 + np.arange(N, dtype=np.int64)
    order = np.argsort(plan_ids)
    sid, spart = plan_ids[order], order.astype(np.int64)
    j_true = np.clip(ids - 100, 0, N - 1)
    states = plan[j_true] + e[owner] + rng.normal(0, 0.4, (m, 4))
    r_max, out_m, ps = 3.0, 1.0, 0.5
    pre_r = r_max + 2 * out_m + 2 * float(np.max(np.linalg.norm(e[:, 0:2], axis=1)))
    sums, cnt = formation_sums(owner, ids, states, own, e, sid, spart, plan, own_index, n, r_max, out_m, ps, pre_r)
    # the numpy formulation
    at = np.minimum(np.searchsorted(sid, ids), sid.size - 1)
    known = sid[at] == ids
    j = spart[at]
    dr = plan[j, 0:2] - plan[own_index[owner], 0:2]
    de = states - plan[j] - e[owner]
    dev2 = de[:, 0] ** 2 + de[:, 1] ** 2 + ps * ps * (de[:, 2] ** 2 + de[:, 3] ** 2)
    sel = np.flatnonzero(known & (dr[:, 0] ** 2 + dr[:, 1] ** 2 <= r_max * r_max) & (dev2 <= out_m * out_m))
    ref_cnt = np.bincount(owner[sel], minlength=n)
    ref = np.stack([np.bincount(owner[sel], weights=states[sel, c] - plan[j[sel], c], minlength=n) for c in range(4)], axis=1)
    assert 0 < sel.size < m
    assert np.array_equal(cnt, ref_cnt) and np.array_equal(sums, ref)


def _distinct_numpy(q, ids):
    """The numpy formulation safety.kernels.distinct_dense replaced (guidance.controller._distinct, dense ids)."""
    present = np.zeros(int(ids.max()) + 1, dtype=bool)
    present[ids] = True
    rep = np.empty(present.size, dtype=np.int64)
    rep[ids] = np.arange(ids.size)
    first = rep[present]
    inv = (np.cumsum(present) - 1)[ids]
    return (first, inv) if np.array_equal(q[first][inv], q) else None


@pytest.mark.parametrize("case", ["same", "one_differs", "nan", "single"])
def test_distinct_dense_equals_the_numpy_formulation(case):
    """safety.kernels.distinct_dense (the MFG backstop's one-entry-per-sensed-vehicle step) decides as the numpy code
    it replaced: None (ok False) exactly when two entries of an id differ or a state is NaN; otherwise the same distinct
    ids in ascending order, the same ranks, the same states (its representative may be another entry of the id)."""
    from mfg_autopilot.safety.kernels import distinct_dense

    rng = np.random.default_rng(31)
    for trial in range(40):
        n_ids = int(rng.integers(1, 60))
        m = 1 if case == "single" else int(rng.integers(1, 400))
        ids = rng.integers(0, n_ids, m).astype(np.int64)
        table = rng.normal(0.0, 3.0, (n_ids, 4))
        q = table[ids].copy()
        if case == "one_differs" and m > 1 and np.unique(ids).size < m:
            dup = np.flatnonzero(np.bincount(ids)[ids] > 1)
            q[rng.choice(dup), rng.integers(4)] += 1e-12
        if case == "nan":
            q[rng.integers(m), rng.integers(4)] = np.nan
        want = _distinct_numpy(q, ids)
        first, inv, ok = distinct_dense(q, ids, int(ids.max()) + 1)
        assert ok == (want is not None), (case, trial)
        if ok:
            assert np.array_equal(ids[first], ids[want[0]]) and np.array_equal(inv, want[1])
            assert np.array_equal(q[first], q[want[0]]) and np.array_equal(q[first][inv], q)
    if case == "one_differs":
        assert not distinct_dense(np.array([[0.0, 0, 0, 0], [0.0, 0, 0, 1e-12]]), np.array([3, 3]), 4)[2]
