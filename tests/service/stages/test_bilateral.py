import numpy as np
import pytest

from service.stages.bilateral import BilateralParams, base_weights, guide_features, joint_bilateral
from tests.tolerances import FILTER_ATOL


def _features(params, h, w, rng=None, albedo=None):
    rng = rng or np.random.default_rng(0)
    albedo = rng.random((h, w, 3), dtype=np.float32) if albedo is None else albedo
    normal = rng.normal(size=(h, w, 3)).astype(np.float32)
    depth = (1 + rng.random((h, w, 1))).astype(np.float32)
    return guide_features(params, h, w, albedo, normal, depth)


def test_constant_image_is_unchanged():
    params = BilateralParams(radius=4)
    color = np.full((17, 31, 3), 0.37, np.float32)
    out = joint_bilateral(color, _features(params, 17, 31), params)
    np.testing.assert_allclose(out, 0.37, atol=FILTER_ATOL)


def test_weights_match_eq16_by_hand():
    """Two pixels: rho = exp(-1/2 (dx^2/10 + |da|^2/0.02 + |dn|^2/0.1)) (Sakai eq. 16)."""
    params = BilateralParams(radius=1, sigma2_log_depth=None)
    albedo = np.array([[[0.5, 0.5, 0.5], [0.6, 0.5, 0.4]]], np.float32)
    normal = np.array([[[0, 0, 1], [0, 0.6, 0.8]]], np.float32)
    feats = guide_features(params, 1, 2, albedo, normal)
    weights = [rho for _, _, rho in base_weights(feats, 1, params.sigma2_position)]
    expected = np.exp(-0.5 * (1 / 10 + 0.02 / 0.02 + (0.36 + 0.04) / 0.1))
    assert len(weights) == 1
    np.testing.assert_allclose(weights[0][0, 0], expected, rtol=1e-5)
    out = joint_bilateral(np.array([[[1.0] * 3, [0.0] * 3]], np.float32), feats, params)
    np.testing.assert_allclose(out[0, 0], 1 / (1 + expected), rtol=1e-5)
    np.testing.assert_allclose(out[0, 1], expected / (1 + expected), rtol=1e-5)


def test_without_guides_it_is_a_normalised_gaussian():
    params = BilateralParams(radius=2)
    color = np.zeros((9, 9, 1), np.float32)
    color[4, 4] = 1.0
    out = joint_bilateral(color, guide_features(params, 9, 9), params)
    d2 = np.add.outer(np.arange(-2, 3) ** 2, np.arange(-2, 3) ** 2)
    kernel = np.exp(-0.5 * d2 / params.sigma2_position)
    np.testing.assert_allclose(out[4, 4, 0], 1 / kernel.sum(), rtol=1e-5)
    assert out.sum() == pytest.approx(1.0, rel=1e-5)  # interior: energy preserved


def test_albedo_edge_is_preserved():
    params = BilateralParams(radius=5)
    albedo = np.zeros((16, 16, 3), np.float32)
    albedo[:, 8:] = 1.0
    color = albedo.copy()
    feats = guide_features(params, 16, 16, albedo)
    out = joint_bilateral(color, feats, params)
    assert np.abs(out - color).max() < 1e-6  # exp(-0.5 * 3 / 0.02) ~ 1e-33


def test_firefly_stays_inside_the_window_and_output_is_finite():
    params = BilateralParams(radius=3)
    color = np.zeros((20, 20, 3), np.float32)
    color[10, 10] = 1e6
    out = joint_bilateral(color, guide_features(params, 20, 20), params)
    assert np.isfinite(out).all()
    touched = np.argwhere(out[..., 0] > 0)
    assert np.abs(touched - 10).max() <= 3
    assert out.max() <= 1e6


@pytest.mark.parametrize("shape", [(1, 1), (2, 2), (3, 5), (7, 13), (17, 31)])
def test_odd_and_tiny_sizes(shape):
    params = BilateralParams(radius=6)
    rng = np.random.default_rng(1)
    color = rng.normal(size=(*shape, 3)).astype(np.float32)  # negative radiance included
    out = joint_bilateral(color, _features(params, *shape, rng), params)
    assert out.shape == color.shape and np.isfinite(out).all()
    assert out.max() <= color.max() + 1e-5 and out.min() >= color.min() - 1e-5  # convex combination


def test_huge_radiance_stays_finite():
    params = BilateralParams(radius=3)
    color = np.full((8, 8, 3), 1e20, np.float32)
    out = joint_bilateral(color, _features(params, 8, 8), params)
    assert np.isfinite(out).all()
    np.testing.assert_allclose(out, 1e20, rtol=1e-5)


def test_invalid_params_are_refused():
    with pytest.raises(ValueError, match="radius"):
        BilateralParams(radius=-1)
    with pytest.raises(ValueError, match="sigma2_albedo"):
        BilateralParams(sigma2_albedo=0)


def test_neg_exp_matches_exp_over_its_range():
    from service.stages.bilateral import NEG_EXP_MAX, neg_exp

    x = np.concatenate([np.linspace(0, float(NEG_EXP_MAX), 20001), [0.125, 0.375, 86.9, 1e-30]]).astype(np.float32)
    got = np.array([neg_exp(v) for v in x], np.float32)
    np.testing.assert_allclose(got, np.exp(-x.astype(np.float64)), rtol=3e-7, atol=0)
    for beyond in (NEG_EXP_MAX * np.float32(1.0001), np.float32(1e30), np.float32(np.inf), np.float32(np.nan)):
        assert neg_exp(beyond) == 0.0  # nothing subnormal, no NaN
    assert neg_exp(np.float32(-1.0)) == 1.0  # negative arguments count as 0
