import numpy as np
import pytest

from service.stages.bilateral import BilateralParams, base_weights, guide_features, pair_weight
from service.stages.sample_statistics import box_cox, statistics_from_samples
from service.stages.statistical import (
    StatisticalParams,
    critical_values_squared,
    membership,
    pixel_estimates,
    position_terms,
    statistical_filter,
    statistical_filter_numpy,
)
from service.stages.student_t import critical_value_table
from tests.tolerances import FILTER_ATOL


def _params(radius=3, symmetric=True, **kw):
    return StatisticalParams(base=BilateralParams(radius=radius, sigma2_log_depth=None), symmetric=symmetric, **kw)


def _frame(h, w, spp=16, seed=0, scale=1.0, guides=True):
    """Random radiance samples around a smooth image; statistics, colour, features."""
    rng = np.random.default_rng(seed)
    base = 0.5 + 0.4 * np.sin(np.arange(w) / 3.0)[None, :, None] * np.ones((h, 1, 3))
    samples = (base[None] * rng.lognormal(-0.5 * scale**2, scale, (spp, h, w, 3))).astype(np.float32)
    layers = statistics_from_samples(samples)
    params = _params()
    albedo = rng.random((h, w, 3), dtype=np.float32) if guides else None
    normal = np.tile(np.float32([0, 0, 1]), (h, w, 1)) if guides else None
    features = guide_features(params.base, h, w, albedo, normal)
    est = pixel_estimates(layers["sampleCount"], layers["bcMean"], layers["bcM2"], layers["bcM3"])
    return samples.mean(axis=0), features, est, layers


@pytest.mark.parametrize("symmetric", [True, False])
def test_compiled_kernel_matches_numpy_reference(symmetric):
    color, features, est, _ = _frame(19, 23)
    count = est.count.copy()
    count[3:6, 4:9] = 1  # pixels without a variance estimate, and non-uniform counts
    count[10, :] = 40
    est = type(est)(est.theta, np.where(count[..., None] < 2, np.inf, est.var).astype(np.float32), count)
    params = _params(radius=4, symmetric=symmetric)
    a = statistical_filter(color, features, est, params)
    b = statistical_filter_numpy(color, features, est, params)
    np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6)


def test_pair_weight_is_the_eq16_weight_of_base_weights():
    features = np.random.default_rng(1).random((5, 6, 4), dtype=np.float32)
    terms = position_terms(2, 10.0)
    for centre, neighbour, rho in base_weights(features, 2, 10.0):
        y, x = centre[0].start, centre[1].start
        yn, xn = neighbour[0].start, neighbour[1].start
        value = pair_weight.py_func(features, y, x, yn, xn, terms[yn - y + 2, xn - x + 2])
        np.testing.assert_allclose(value, rho[0, 0], rtol=1e-6)


def test_membership_is_the_welch_test_by_hand():
    """t = |d| / sqrt(V_i + V_j) against t_{0.9975, nu}; eq. 14 tests d^2 + V_j <= (1 + 2 t^2) V_i."""
    crit = critical_value_table(0.005, 64)[18]  # n_i = n_j = 10
    theta_i = np.float32([[1.0, 1.0, 1.0]])
    var_i = np.float32([[0.01, 0.01, 0.01]])
    var_j = np.float32([[0.03, 0.03, 0.03]])
    c2 = np.float32([crit**2])
    limit = crit * np.sqrt(0.04)
    for d, expected in ((0.99 * limit, True), (1.01 * limit, False)):
        theta_j = theta_i + np.float32([[d, 0, 0]])
        assert membership(theta_i, var_i, theta_j, var_j, c2, True)[0] == expected
    # asymmetric: the noisier centre admits more than the cleaner one
    theta_j = theta_i + np.float32(0.3)
    assert membership(var_j * 0 + theta_i, var_j * 10, theta_j, var_i, c2, False)[0]
    assert not membership(theta_i, var_i, theta_j, var_j * 10, c2, False)[0]


def test_pixel_estimates_follow_algorithm_2():
    rng = np.random.default_rng(2)
    samples = rng.gamma(0.7, 1.0, (9, 4, 5, 3)).astype(np.float32)
    layers = statistics_from_samples(samples)
    est = pixel_estimates(layers["sampleCount"], layers["bcMean"], layers["bcM2"], layers["bcM3"])
    x = box_cox(samples).astype(np.float64)
    n = 9
    sigma2 = x.var(axis=0, ddof=1)
    m3 = ((x - x.mean(axis=0)) ** 3).mean(axis=0)
    np.testing.assert_allclose(est.var, sigma2 / n, rtol=1e-4)
    np.testing.assert_allclose(est.theta, x.mean(axis=0) + m3 / (6 * sigma2 * n), rtol=1e-4, atol=1e-5)
    stats = layers["sampleCount"], layers["bcMean"], layers["bcM2"], layers["bcM3"]
    plain = pixel_estimates(*stats, skew_correction=False)
    np.testing.assert_allclose(plain.theta, layers["bcMean"])


def test_zero_variance_and_missing_samples_are_well_defined():
    shape = (4, 4, 3)
    est = pixel_estimates(np.full((4, 4, 1), 5.0), np.ones(shape), np.zeros(shape), np.ones(shape))
    assert np.all(est.var == 0) and np.all(est.theta == 1)  # M3 clamped: zero M2 allows no skew
    est = pixel_estimates(np.ones((4, 4, 1)), np.ones(shape), np.zeros(shape), np.zeros(shape))
    assert np.all(np.isinf(est.var))  # n = 1: no variance estimate, never rejected by the symmetric test
    assert np.isfinite(critical_values_squared(0.005, 1)).all()


@pytest.mark.parametrize("symmetric", [True, False])
def test_constant_image_is_unchanged(symmetric):
    _, features, est, _ = _frame(17, 31)
    color = np.full((17, 31, 3), 0.37, np.float32)
    out = statistical_filter(color, features, est, _params(radius=5, symmetric=symmetric))
    np.testing.assert_allclose(out, 0.37, atol=FILTER_ATOL)


def _step_edge(variance_scale):
    """A radiance step no G-buffer shows: left half 0.2, right half 1.0, samples with given spread."""
    h, w, spp = 12, 16, 32
    rng = np.random.default_rng(5)
    level = np.where(np.arange(w) < w // 2, 0.2, 1.0)[None, :, None] * np.ones((h, 1, 3))
    noise = rng.normal(0, 1, (spp, h, w, 3)) * variance_scale
    samples = (level[None] * (1 + noise)).astype(np.float32)
    layers = statistics_from_samples(samples)
    est = pixel_estimates(layers["sampleCount"], layers["bcMean"], layers["bcM2"], layers["bcM3"])
    features = guide_features(_params().base, h, w)  # no guides: the base filter is a Gaussian
    return samples.mean(axis=0), features, est, level.astype(np.float32)


def test_step_edge_without_gbuffer_is_kept_at_small_variance():
    color, features, est, level = _step_edge(0.05)
    out = statistical_filter(color, features, est, _params(radius=6))
    assert np.abs(out - level).max() < 0.05  # the base filter alone would blur the step by ~0.4
    noisy_err = np.abs(color - level).mean()
    assert np.abs(out - level).mean() < 0.5 * noisy_err  # and it still denoises on either side


def test_converges_to_input_as_variance_vanishes():
    """Sakai eq. 9 (consistency): as Var -> 0 the membership rejects every neighbour that differs."""
    color, features, est, _ = _step_edge(0.05)
    errors = []
    for scale in (1.0, 1e-2, 1e-4, 0.0):
        scaled = type(est)(est.theta, est.var * np.float32(scale), est.count)
        errors.append(np.abs(statistical_filter(color, features, scaled, _params(radius=6)) - color).max())
    assert errors[-1] == 0.0 and errors[0] > errors[1] >= errors[2]


def test_firefly_stays_inside_the_window():
    color, features, est, layers = _frame(30, 30, guides=False)
    color = color.copy()
    color[15, 15] = 1e6
    radius = 4
    out = statistical_filter(color, features, est, _params(radius=radius))
    assert np.isfinite(out).all()
    changed = np.argwhere(np.abs(out - statistical_filter(np.where(color > 1e5, 0, color), features, est,
                                                           _params(radius=radius))).max(axis=-1) > 0)
    assert np.abs(changed - 15).max() <= radius
    assert out.max() <= 1e6


@pytest.mark.parametrize("shape", [(1, 1), (3, 5), (17, 31)])
@pytest.mark.parametrize("symmetric", [True, False])
def test_tiny_and_odd_sizes_negative_radiance_and_float16_inputs(shape, symmetric):
    h, w = shape
    rng = np.random.default_rng(3)
    samples = rng.normal(0.2, 1.0, (6, h, w, 3)).astype(np.float32)  # negative radiance included
    layers = {k: v.astype(np.float16).astype(np.float32) for k, v in statistics_from_samples(samples).items()}
    est = pixel_estimates(layers["sampleCount"], layers["bcMean"], layers["bcM2"], layers["bcM3"])
    assert np.isfinite(est.theta).all()
    color = samples.mean(axis=0).astype(np.float16).astype(np.float32)
    params = _params(radius=6, symmetric=symmetric)
    albedo = rng.random((h, w, 3), dtype=np.float32).astype(np.float16).astype(np.float32)
    features = guide_features(params.base, h, w, albedo)
    out = statistical_filter(color, features, est, params)
    assert out.shape == color.shape and np.isfinite(out).all()
    assert out.min() >= color.min() - 1e-5 and out.max() <= color.max() + 1e-5  # convex combination
    np.testing.assert_allclose(out, statistical_filter_numpy(color, features, est, params), rtol=1e-5, atol=1e-6)


def test_invalid_alpha_is_refused():
    with pytest.raises(ValueError, match="alpha"):
        StatisticalParams(alpha=1.5)


@pytest.mark.parametrize("guides, shape, radius", [(False, (9, 40), 6), (True, (40, 7), 3), (True, (25, 33), 20)])
@pytest.mark.parametrize("symmetric", [True, False])
def test_compiled_kernel_matches_numpy_reference_uniform_counts_and_shapes(guides, shape, radius, symmetric):
    """Uniform sample counts (one critical value), no guide features, windows beyond the frame, strips."""
    color, features, est, _ = _frame(*shape, guides=guides, seed=7)
    assert est.count.min() == est.count.max()
    params = _params(radius=radius, symmetric=symmetric)
    np.testing.assert_allclose(statistical_filter(color, features, est, params),
                               statistical_filter_numpy(color, features, est, params), rtol=1e-5, atol=1e-6)
