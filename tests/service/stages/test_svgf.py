import numpy as np
import pytest

from service.stages.atrous import edge_guides
from service.stages.svgf import (
    TemporalParams,
    accumulate,
    accumulate_numpy,
    box_mean,
    clamp_history,
    clamp_history_numpy,
    estimate_variance,
    halves_variance,
    luminance_moments,
)


def test_accumulate_blends_with_history_floor_and_restarts_where_invalid():
    h, w = 2, 3
    color = np.full((h, w, 3), 1.0, np.float32)
    prev = np.zeros((h, w, 3), np.float32)
    valid = np.array([[True, True, False], [True, True, True]])
    history = np.array([[1.0, 10.0, 7.0], [2.0, 3.0, 4.0]], np.float32)
    out, moments, hist = accumulate(color, luminance_moments(color), prev, np.zeros((h, w, 2), np.float32),
                                    history, valid, TemporalParams())
    np.testing.assert_array_equal(hist, [[2, 11, 1], [3, 4, 5]])
    expected = np.maximum(0.2, 1 / hist)  # alpha = max(0.2, 1/n), Schied 2017 sec. 4.1
    expected[~valid] = 1.0
    np.testing.assert_allclose(out[..., 0], expected, rtol=1e-6)
    np.testing.assert_allclose(moments[..., 0], expected, rtol=1e-5)


def _variance_inputs(seed: int, h: int = 9, w: int = 10):
    """A random frame's colour and moments, accumulated moments of variance 0.01, flat guides and a history
    of 10 frames: (color, current, moments, guides, history)."""
    color = np.random.default_rng(seed).random((h, w, 3), dtype=np.float32)
    moments = np.stack([np.full((h, w), 0.5), np.full((h, w), 0.5**2 + 0.01)], -1).astype(np.float32)
    guides = edge_guides(np.ones((h, w, 1), np.float32), np.tile(np.float32([0, 0, 1]), (h, w, 1)))
    return color, luminance_moments(color), moments, guides, np.full((h, w), 10.0, np.float32)


def test_variance_is_temporal_with_long_history_and_spatial_otherwise():
    color, current, moments, guides, history = _variance_inputs(0)
    np.testing.assert_allclose(estimate_variance(moments, current, history, color, guides, TemporalParams()), 0.01,
                               rtol=1e-4)
    history[:3] = 2.0
    var = estimate_variance(moments, current, history, color, guides, TemporalParams())
    np.testing.assert_allclose(var[3:], 0.01, rtol=1e-4)
    lum = current[..., 0]
    assert np.all(var[:3] > 0) and np.all(var[:3] < lum.var() * 2)  # about one frame's spatial variance / 2


def test_halves_variance_is_the_means_variance_and_sees_no_edge_both_halves_show():
    """A and B: a picture (a thin bright line on a dark ground) plus independent noise of sd 0.1 each: the mean
    over pixels of the estimate is the variance of (A + B) / 2, 0.1^2 / 2 (grey noise: luminance = value), to
    sampling error; without noise it is 0 on the line, where the spatial estimate counts the line as noise."""
    h, w = 64, 64
    rng = np.random.default_rng(4)
    picture = np.full((h, w, 3), 0.2, np.float32)
    picture[:, 31:33] = 5.0
    noise_a, noise_b = (rng.standard_normal((h, w, 1)).astype(np.float32) * np.float32(0.1) for _ in range(2))
    estimate = halves_variance(picture + noise_a, picture + noise_b)
    assert estimate.dtype == np.float32 and estimate.shape == (h, w)
    assert estimate.mean() == pytest.approx(0.1**2 / 2, rel=0.05)
    np.testing.assert_array_equal(halves_variance(picture, picture), 0.0)
    guides = edge_guides(np.ones((h, w, 1), np.float32), np.tile(np.float32([0, 0, 1]), (h, w, 1)))
    current = luminance_moments(picture)
    history = np.ones((h, w), np.float32)
    spatial = estimate_variance(current, current, history, picture, guides, TemporalParams())
    with_halves = estimate_variance(current, current, history, picture, guides, TemporalParams(),
                                    lambda box: halves_variance(picture[box], picture[box]))
    assert spatial[:, 30:34].min() > 0.1 and np.all(with_halves == 0.0)


def test_the_halves_only_lower_a_short_historys_variance():
    """With the halves' estimate the variance is the lesser of the two where the history is short, and the
    temporal estimate, untouched, where it is long."""
    color, current, moments, guides, history = _variance_inputs(1)
    h, w = history.shape
    history[:3] = 2.0
    plain = estimate_variance(moments, current, history, color, guides, TemporalParams())
    halves = np.where(np.arange(w) % 2 == 0, 0.0, 1e3).astype(np.float32)[None].repeat(h, 0)
    var = estimate_variance(moments, current, history, color, guides, TemporalParams(), lambda box: halves[box])
    np.testing.assert_array_equal(var[3:], plain[3:])
    np.testing.assert_allclose(var[:3], np.minimum(plain[:3], halves[:3] / 2.0), rtol=1e-6)
    assert (var[:3, 0::2] == 0).all() and (var[:3, 1::2] == plain[:3, 1::2]).all()


def test_box_mean_and_clamp():
    values = np.arange(20, dtype=np.float32).reshape(4, 5, 1)
    np.testing.assert_allclose(box_mean(values, 1)[1, 1, 0], values[0:3, 0:3].mean())
    np.testing.assert_allclose(box_mean(values, 1)[0, 0, 0], values[0:2, 0:2].mean())
    color = np.full((5, 5, 3), 0.3, np.float32)
    prev = np.full((5, 5, 3), 2.0, np.float32)
    moments = luminance_moments(prev)
    moments[..., 1] += 0.04
    clamped, shifted = clamp_history(prev, moments, color, 1, 1.0)
    np.testing.assert_allclose(clamped, 0.3, rtol=1e-6)  # zero local spread: history clamped to the frame
    np.testing.assert_allclose(shifted[..., 0], 0.3, rtol=1e-5)
    np.testing.assert_allclose(shifted[..., 1] - shifted[..., 0] ** 2, 0.04, rtol=1e-3)


@pytest.mark.parametrize("shape, radius", [((1, 1), 1), ((3, 5), 1), ((17, 31), 2), ((6, 4), 3)])
def test_compiled_accumulate_and_clamp_match_numpy_references(shape, radius):
    rng = np.random.default_rng(3)
    h, w = shape
    color = rng.lognormal(0, 1, (h, w, 3)).astype(np.float32)
    prev = rng.normal(1, 2, (h, w, 3)).astype(np.float32)  # negative history values too
    moments = luminance_moments(prev)
    moments[..., 1] += 0.1
    args = prev, moments, color, radius, 1.0
    for a, b in zip(clamp_history(*args), clamp_history_numpy(*args), strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6)
    valid = rng.random((h, w)) > 0.3
    history = rng.integers(0, 10, (h, w)).astype(np.float32)
    args = color, luminance_moments(color), prev, moments, history, valid, TemporalParams()
    for a, b in zip(accumulate(*args), accumulate_numpy(*args), strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-7)
