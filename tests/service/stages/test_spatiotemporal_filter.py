"""The numpy/numba spatiotemporal filter of crossreg (Choi 2024 eqs. 8-10): hand-computed values, edge
cases, and the history screening. The torch twin is held to it in tests/models/train/test_filter_parity.py."""

import numpy as np
import pytest

from service.stages.spatiotemporal_filter import (
    _window_extrema,
    cross_bilateral_sums,
    screen_history,
    spatiotemporal_filter,
)

EXP_RTOL = 1e-5  # the kernel's polynomial exp: relative error < 5e-6


def _inputs(height, width, seed=0):
    rng = np.random.default_rng(seed)
    pa = rng.random((height, width, 3), np.float32)
    pb = pa + 0.2 * rng.random((height, width, 3), np.float32)
    albedo = rng.random((height, width, 3), np.float32)
    normal = rng.standard_normal((height, width, 3)).astype(np.float32)
    params = np.concatenate([5 * rng.random((height, width, 5)), rng.random((height, width, 1))], -1)
    return pa, pb, albedo, normal, params.astype(np.float32)


def test_two_pixels_by_hand():
    """1x2 frame: each pixel sees itself (weight 1) and its neighbour with the eq. 9 weight."""
    pa = np.array([[[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]]], np.float32)
    pb = np.array([[[0.5, 0.5, 0.5], [0.5, 0.5, 0.5]]], np.float32)
    albedo = np.array([[[0.2, 0.2, 0.2], [0.2, 0.2, 0.4]]], np.float32)
    normal = np.zeros((1, 2, 3), np.float32)
    prec = np.array([[[2.0, 3.0, 10.0, 1.0, 4.0], [1.0, 1.0, 1.0, 1.0, 1.0]]], np.float32)
    sum_a, w_a, sum_b, w_b = cross_bilateral_sums(pa, pb, albedo, normal, prec)
    # centre (0, 0): |dA|^2 = 1, |d albedo|^2 = 0.04, |dp|^2 / 5^2 = 1/25
    shared = 10.0 * 0.04 + 4.0 / 25.0
    wa, wb = np.exp(-(2.0 * 1.0 + shared)), np.exp(-(3.0 * 0.0 + shared))
    np.testing.assert_allclose(w_a[0, 0], 1 + wa, rtol=EXP_RTOL)
    np.testing.assert_allclose(w_b[0, 0], 1 + wb, rtol=EXP_RTOL)
    np.testing.assert_allclose(sum_a[0, 0], [wa * 1.0, 0, 0], rtol=EXP_RTOL, atol=1e-7)
    np.testing.assert_allclose(sum_b[0, 0], (1 + wb) * 0.5 * np.ones(3), rtol=EXP_RTOL)


def test_constant_image_is_returned_and_history_blends_by_alpha():
    pa, pb, albedo, normal, params = _inputs(13, 17)
    const = np.full_like(pa, 0.7)
    out = spatiotemporal_filter(const, const, albedo, normal, params)
    np.testing.assert_allclose(out.color, const, atol=1e-6)
    previous = np.full_like(pa, 0.1)
    valid = np.zeros((13, 17), bool)
    valid[:, :8] = True
    out = spatiotemporal_filter(const, const, albedo, normal, params, previous, valid)
    alpha = params[..., 5:6]
    expected = np.broadcast_to(alpha[:, :8] * 0.7 + (1 - alpha[:, :8]) * 0.1, (13, 8, 3))
    np.testing.assert_allclose(out.color[:, :8], expected, atol=1e-6)
    np.testing.assert_allclose(out.color[:, 8:], 0.7, atol=1e-6)  # no history: alpha is 1


def test_combination_is_weighted_by_weight_sums():
    pa, pb, albedo, normal, params = _inputs(9, 11, seed=1)
    out = spatiotemporal_filter(pa, pb, albedo, normal, params)
    wa, wb = out.weight_a[..., None], out.weight_b[..., None]
    np.testing.assert_allclose(out.color, (out.color_a * wa + out.color_b * wb) / (wa + wb), rtol=1e-6)
    assert (out.weight_a >= 1).all() and (out.weight_b >= 1).all()


def test_huge_precisions_and_one_pixel_frames_stay_finite():
    pa, pb, albedo, normal, params = _inputs(1, 1)
    out = spatiotemporal_filter(pa, pb, albedo, normal, params)
    np.testing.assert_allclose(out.color, (pa + pb) / 2, rtol=1e-6)  # alone: equal weights 1
    pa, pb, albedo, normal, params = _inputs(6, 5)
    params[..., :5] = 1e4  # 1 / eps: every neighbour weight underflows, the centre keeps 1
    out = spatiotemporal_filter(pa, pb, albedo, normal, params)
    assert np.isfinite(out.color).all()
    np.testing.assert_allclose(out.color_a, pa, atol=1e-4)


@pytest.mark.parametrize("radius", [0, 1, 3])
def test_window_extrema_match_a_brute_force(radius):
    from numpy.lib.stride_tricks import sliding_window_view

    x = np.random.default_rng(2).random((7, 10, 3)).astype(np.float32)
    lo, hi = _window_extrema(x, radius)
    padded = np.pad(x, ((radius, radius), (radius, radius), (0, 0)), mode="edge")  # edge copies: same extrema
    view = sliding_window_view(padded, (2 * radius + 1, 2 * radius + 1), axis=(0, 1))
    np.testing.assert_array_equal(lo, view.min(axis=(-2, -1)))
    np.testing.assert_array_equal(hi, view.max(axis=(-2, -1)))


def test_screening_rejects_history_outside_the_current_range():
    current = np.zeros((8, 8, 3), np.float32)
    current[:, 4:] = 1.0
    history = current.copy()
    history[1, 1] = 2.0  # brighter than anything around: a moving shadow's old value
    valid = np.ones((8, 8), bool)
    valid[7, 7] = False
    out = screen_history(current, history, valid)
    assert not out[1, 1] and not out[7, 7]
    assert out.sum() == 62  # flat regions keep their history (<=, not <)


def test_grouped_screening_equals_one_call_per_group():
    rng = np.random.default_rng(4)
    current = rng.random((9, 11, 9), np.float32)
    history = current + rng.normal(0, 0.3, current.shape).astype(np.float32)
    valid = rng.random((9, 11)) > 0.2
    masks = screen_history(current, history, valid, groups=3)
    for g in range(3):
        part = slice(3 * g, 3 * g + 3)
        np.testing.assert_array_equal(masks[..., g], screen_history(current[..., part], history[..., part], valid))
    with pytest.raises(ValueError, match="9 channels do not split into 2 groups"):
        screen_history(current, history, valid, groups=2)
