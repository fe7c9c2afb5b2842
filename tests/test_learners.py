"""Algorithms 3 and 4: the LQR closed form, exact weight gradients, the mean field."""

from dataclasses import replace

import numpy as np
import pytest

from mfg_autopilot.paper.costs import phi_L_state
from mfg_autopilot.paper.features import make_sigma_H
from mfg_autopilot.paper.learners import HJBLearner, MFGLearner, hjb_update, policy_action
from mfg_autopilot.paper.model import lqr_riccati_axis, lqr_value_weights
from mfg_autopilot.paper.params import PAPER, CostParams, LearnerParams


def _lq_preset(V=0.0, v_o=(0.0, 0.0)):
    cost = CostParams(mean_wind_m_s=v_o, wind_diffusion_m_s=((V, 0.0), (0.0, V)))
    return replace(PAPER, cost=cost, learner=LearnerParams(mu=0.0, c_H=0.0, acc_max_m_s2=1e9))


def _states(n=6, seed=0):
    rng = np.random.default_rng(seed)
    return np.column_stack([rng.uniform(-150, 150, (n, 2)), rng.uniform(-3, 3, (n, 2))])


def test_lqr_value_solves_the_lq_part_of_the_hjb_exactly():
    # Given the Riccati value of the LQ part of the paper's cost, represented by sigma_H,
    preset = _lq_preset()
    sigma = make_sigma_H(preset.learner.state_scale)
    w = np.tile(lqr_value_weights(sigma, preset.cost), (6, 1))
    s = _states()
    # the value model is s^T P s per axis,
    P = lqr_riccati_axis(preset.cost)
    psi = np.einsum("nm,nm->n", sigma.value(s), w)
    psi_ref = sum(np.einsum("ni,ij,nj->n", s[:, [p, v]], P, s[:, [p, v]]) for p, v in ((0, 2), (1, 3)))
    np.testing.assert_allclose(psi, psi_ref, rtol=1e-10)
    # and the HJB residual is only the non-LQ term v.r/|r| (no wind, no interaction): H_LQ = 0.
    _, H_hat, _, _ = hjb_update(sigma, w, s, np.zeros(6), preset)
    r, v = s[:, :2], s[:, 2:]
    proj = np.einsum("nd,nd->n", v, r) / np.linalg.norm(r, axis=1)
    np.testing.assert_allclose(H_hat - proj, 0.0, atol=1e-6 * np.abs(phi_L_state(s, preset.cost)).max())


def test_lqr_residual_with_wind_noise_is_the_trace_constant():
    V = 0.1
    preset = _lq_preset(V=V)
    sigma = make_sigma_H(preset.learner.state_scale)
    w = np.tile(lqr_value_weights(sigma, preset.cost), (6, 1))
    s = _states()
    _, H_hat, _, _ = hjb_update(sigma, w, s, np.zeros(6), preset)
    proj = np.einsum("nd,nd->n", s[:, 2:], s[:, :2]) / np.linalg.norm(s[:, :2], axis=1)
    P = lqr_riccati_axis(preset.cost)
    # 1/2 tr(G G^T hess psi) = 1/2 * V^2 * (2 P22 + 2 P22)
    np.testing.assert_allclose(H_hat - proj, 2 * V**2 * P[1, 1], rtol=1e-6)


def test_lqr_action_is_the_riccati_gain_with_the_minus_sign():
    preset = _lq_preset()
    sigma = make_sigma_H(preset.learner.state_scale)
    w = np.tile(lqr_value_weights(sigma, preset.cost), (6, 1))
    s = _states()
    a = policy_action(sigma, w, s, preset)
    P = lqr_riccati_axis(preset.cost)
    expected = -(P[0, 1] * s[:, :2] + P[1, 1] * s[:, 2:]) / preset.cost.c3
    np.testing.assert_allclose(a, expected, rtol=1e-9)
    # SPEC section 7: gains ~8.2 s^-2 and ~4.1 s^-1
    assert 8.0 < P[0, 1] / preset.cost.c3 < 8.4 and 3.9 < P[1, 1] / preset.cost.c3 < 4.3


def test_weight_gradients_match_finite_differences():
    # Normalised step of Algorithm 3: with mu = 1 and c_H = 0 the step is -g/|g| where
    # g = H_hat dH_hat/dw. Check dH_hat/dw and grad R by finite differences.
    preset = replace(PAPER, learner=LearnerParams(mu=1.0, c_H=0.0))
    sigma = make_sigma_H(preset.learner.state_scale)
    rng = np.random.default_rng(3)
    s = _states(4, 1) / 3
    w = rng.normal(size=(4, sigma.M)) * 0.5
    phi = rng.uniform(0, 1, 4)
    w_new, H0, _, _ = hjb_update(sigma, w, s, phi, preset)
    step = w_new - w
    eps = 1.0      # H_hat is quadratic in w: central differences are exact at any eps
    fd = np.empty_like(w)
    for m in range(sigma.M):
        e = np.zeros(sigma.M); e[m] = eps
        _, Hp, _, _ = hjb_update(sigma, w + e, s, phi, preset)
        _, Hm, _, _ = hjb_update(sigma, w - e, s, phi, preset)
        fd[:, m] = (Hp - Hm) / (2 * eps)
    g = H0[:, None] * fd
    np.testing.assert_allclose(step, -g / np.linalg.norm(g, axis=1, keepdims=True), atol=1e-5)


def test_regulariser_gradient_matches_finite_differences():
    preset = replace(PAPER, learner=LearnerParams(mu=0.0, c_H=1.0, acc_max_m_s2=1e9))
    sigma = make_sigma_H(preset.learner.state_scale)
    rng = np.random.default_rng(5)
    s = np.array([[100.0, -50.0, 1.0, -1.0]])     # flying away from the origin with the wind: R > 0
    w = rng.normal(size=(1, sigma.M)) * 1e-3

    def R(wv):
        from mfg_autopilot.paper.model import nominal_drift
        a = policy_action(sigma, wv, s, preset)
        st = s / sigma.scale
        return float(np.sum(st * nominal_drift(s, a, preset.cost) / sigma.scale))

    w_new, _, active, _ = hjb_update(sigma, w, s, np.zeros(1), preset)
    assert active[0] and R(w) > 0
    fd = np.array([(R(w + e) - R(w - e)) / 2e-6 for e in np.eye(sigma.M)[:, None, :] * 1e-6])
    np.testing.assert_allclose(-(w_new - w)[0], fd, rtol=1e-5, atol=1e-9)


def test_paper_preset_first_step_from_zero_weights_is_finite_and_bounded():
    learner = HJBLearner(3, PAPER)
    s = np.array([[150.0, 100.0, 1.0, -1.0]] * 3)
    info = learner.step(s, np.zeros(3))
    assert np.all(np.isfinite(info.acc_m_s2)) and np.all(np.linalg.norm(info.acc_m_s2, axis=1) <= 2.0 + 1e-12)
    assert info.grad_evals.min() >= 1


def test_mfg_needs_the_t0_exchange_and_trains_its_fpk_model():
    preset = PAPER
    n = 9
    rng = np.random.default_rng(0)
    S0 = np.column_stack([150 + rng.normal(size=n) * 2, 100 + rng.normal(size=n) * 2, 1 + 0.2 * rng.normal(size=n), -1 + 0.2 * rng.normal(size=n)])
    mfg = MFGLearner(n, preset)
    with pytest.raises(RuntimeError, match="t = 0 exchange"):
        mfg.step(S0)
    mfg.initialise(S0, np.zeros((n, 2)), np.arange(n))
    w_F0 = mfg.mean_field.w_F.copy()
    assert np.linalg.norm(w_F0) > 0, "w_F(0) fitted to the t = 0 states, not the zero fixed point"
    info = mfg.step(S0)
    assert np.all(info.grad_evals >= 2 * preset.learner.K)
    assert np.all(info.mf_evals == n * (1 + preset.learner.K))
    assert not np.allclose(mfg.mean_field.w_F, w_F0), "the FPK model trains"
    # particles moved one period along their drift, own particle excluded from quadrature
    assert not np.allclose(mfg.mean_field.particles[0], S0)
    wts = mfg.mean_field.weights()
    np.testing.assert_allclose(wts.sum(axis=1), 1.0)
    assert np.all(wts[np.arange(n), np.arange(n)] == 0)


def test_bank_of_one_equals_a_row_of_a_bank():
    # A controller process runs a bank of one; the simulator a bank of N. Same numbers.
    rng = np.random.default_rng(2)
    s = _states(5, 2)
    phi = rng.uniform(0, 1, 5)
    big = HJBLearner(5, PAPER)
    one = HJBLearner(1, PAPER)
    for _ in range(5):
        a_big = big.step(s, phi).acc_m_s2
        a_one = one.step(s[3:4], phi[3:4]).acc_m_s2
        np.testing.assert_array_equal(a_big[3], a_one[0])
        s = s + 0.1
