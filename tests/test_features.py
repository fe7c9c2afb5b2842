"""sigma_H (54) and sigma_F (69): counts, exact gradients and second derivatives."""

import numpy as np
import pytest

from mfg_autopilot.paper.features import make_sigma_F, make_sigma_H, sigma_F_exponents, sigma_H_exponents


def test_feature_counts_match_the_paper():
    assert sigma_H_exponents().shape == (54, 4)
    assert sigma_F_exponents().shape == (69, 4)
    for E in (sigma_H_exponents(), sigma_F_exponents()):
        assert len({tuple(r) for r in E}) == E.shape[0], "monomials are distinct"
        assert E.sum(axis=1).min() >= 1, "no constant term"
    eh = sigma_H_exponents()
    # each monomial of sigma_H lives on one axis: (x, v_x) or (y, v_y), degree <= 6
    assert np.all((eh[:, [0, 2]].sum(1) == 0) | (eh[:, [1, 3]].sum(1) == 0))
    assert eh.sum(axis=1).max() == 6
    assert sigma_F_exponents().sum(axis=1).max() == 4


@pytest.mark.parametrize("make,scale", [(make_sigma_H, (200.0, 200.0, 2.0, 2.0)), (make_sigma_F, (10.0, 10.0, 2.0, 2.0))])
def test_gradient_and_hessian_match_finite_differences(make, scale):
    rng = np.random.default_rng(1)
    feats = make(scale)
    s = rng.normal(size=(5, 4)) * np.array(scale)
    sig, J = feats.value_grad(s)
    H = feats.hessian(s)
    h = 1e-5 * np.array(scale)
    for d in range(4):
        e = np.zeros(4); e[d] = h[d]
        sp, Jp = feats.value_grad(s + e)
        sm, Jm = feats.value_grad(s - e)
        fd = (sp - sm) / (2 * h[d])
        np.testing.assert_allclose(J[:, :, d], fd, rtol=1e-6, atol=1e-9 * np.abs(sig).max() / h[d])
        fdH = (Jp - Jm) / (2 * h[d])
        np.testing.assert_allclose(H[:, :, d, :], fdH, rtol=1e-5, atol=1e-7 * np.abs(J).max() / h[d])
    np.testing.assert_allclose(H, np.swapaxes(H, 2, 3))
    _, _, Hv = feats.value_grad_hessvel(s)
    np.testing.assert_array_equal(Hv, H[:, :, 2:4, 2:4])


def test_sigma_H_values_are_the_monomials_of_scaled_state():
    feats = make_sigma_H((200.0, 200.0, 2.0, 2.0))
    s = np.array([[100.0, -50.0, 1.0, 4.0]])
    st = s[0] / feats.scale
    expected = np.prod(st[None, :] ** feats.exponents, axis=1)
    np.testing.assert_allclose(feats.value(s)[0], expected)


def test_bad_shapes_are_rejected():
    feats = make_sigma_H((200.0, 200.0, 2.0, 2.0))
    with pytest.raises(ValueError, match=r"\(n, 4\)"):
        feats.value(np.zeros((3, 3)))
    with pytest.raises(ValueError, match="scale"):
        make_sigma_H((0.0, 1.0, 1.0, 1.0))
