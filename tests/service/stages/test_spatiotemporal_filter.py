"""The numpy/numba spatiotemporal filter of crossreg (Choi 2024 eqs. 8-10): hand-computed values, edge
cases, the numba kernels against their plain-numpy twins, and the history screening. Planes (C, H, W).
The torch twin is held to it in tests/models/train/test_filter_parity.py."""

import numpy as np
import pytest

from service.stages.spatiotemporal_filter import (
    MAX_RADIUS,
    PRECISION_EPS,
    pilot_precision_floor,
    screen_history,
    spatiotemporal_filter,
)

EXP_RTOL = 1e-5  # the kernel's polynomial exp: relative error < 5e-6
KERNEL_ATOL = 1e-5  # numba kernel against its numpy twin, O(1) log1p values (polynomial exp, fastmath)


def _inputs(height, width, seed=0):
    rng = np.random.default_rng(seed)
    pa = rng.random((3, height, width), np.float32)
    pb = pa + 0.2 * rng.random((3, height, width), np.float32)
    albedo = rng.random((3, height, width), np.float32)
    normal = rng.standard_normal((3, height, width)).astype(np.float32)
    params = np.concatenate([5 * rng.random((5, height, width)), rng.random((1, height, width))])
    return pa, pb, albedo, normal, params.astype(np.float32)


def test_two_pixels_by_hand():
    """1x2 frame: each pixel sees itself (weight 1) and its neighbour with the eq. 9 weight."""
    pa = np.array([[[0.0, 1.0]], [[0.0, 0.0]], [[0.0, 0.0]]], np.float32)
    pb = np.full((3, 1, 2), 0.5, np.float32)
    albedo = np.array([[[0.2, 0.2]], [[0.2, 0.2]], [[0.2, 0.4]]], np.float32)
    normal = np.zeros((3, 1, 2), np.float32)
    params = np.array([[[2.0, 1.0]], [[3.0, 1.0]], [[10.0, 1.0]], [[1.0, 1.0]], [[4.0, 1.0]], [[0.5, 0.5]]], np.float32)
    out = spatiotemporal_filter(pa, pb, albedo, normal, params)
    # centre (0, 0): |dA|^2 = 1, |d albedo|^2 = 0.04, |dp|^2 / 5^2 = 1/25
    shared = 10.0 * 0.04 + 4.0 / 25.0
    wa, wb = np.exp(-(2.0 * 1.0 + shared)), np.exp(-(3.0 * 0.0 + shared))
    np.testing.assert_allclose(out.weight_a[0, 0], 1 + wa, rtol=EXP_RTOL)
    np.testing.assert_allclose(out.weight_b[0, 0], 1 + wb, rtol=EXP_RTOL)
    np.testing.assert_allclose(out.color_a[:, 0, 0], [wa / (1 + wa), 0, 0], rtol=EXP_RTOL, atol=1e-7)
    np.testing.assert_allclose(out.color_b[:, 0, 0], 0.5, rtol=EXP_RTOL)  # no history: alpha is 1


def test_constant_image_is_returned_and_history_blends_by_alpha():
    pa, pb, albedo, normal, params = _inputs(13, 17)
    const = np.full_like(pa, 0.7)
    out = spatiotemporal_filter(const, const, albedo, normal, params)
    np.testing.assert_allclose(out.color, const, atol=1e-6)
    previous = np.full_like(pa, 0.1)
    valid = np.zeros((13, 17), bool)
    valid[:, :8] = True
    out = spatiotemporal_filter(const, const, albedo, normal, params, previous, valid)
    alpha = params[5:6]
    expected = np.broadcast_to(alpha[:, :, :8] * 0.7 + (1 - alpha[:, :, :8]) * 0.1, (3, 13, 8))
    np.testing.assert_allclose(out.color[:, :, :8], expected, atol=1e-6)
    np.testing.assert_allclose(out.color[:, :, 8:], 0.7, atol=1e-6)  # no history: alpha is 1


def test_combination_is_weighted_by_weight_sums():
    pa, pb, albedo, normal, params = _inputs(9, 11, seed=1)
    out = spatiotemporal_filter(pa, pb, albedo, normal, params)
    wa, wb = out.weight_a, out.weight_b
    np.testing.assert_allclose(out.color, (out.color_a * wa + out.color_b * wb) / (wa + wb), rtol=1e-6)
    assert (out.weight_a >= 1).all() and (out.weight_b >= 1).all()


def test_huge_precisions_and_one_pixel_frames_stay_finite():
    pa, pb, albedo, normal, params = _inputs(1, 1)
    out = spatiotemporal_filter(pa, pb, albedo, normal, params)
    np.testing.assert_allclose(out.color, (pa + pb) / 2, rtol=1e-6)  # alone: equal weights 1
    pa, pb, albedo, normal, params = _inputs(6, 5)
    params[:5] = 1e4  # 1 / eps: every neighbour weight underflows, the centre keeps 1
    out = spatiotemporal_filter(pa, pb, albedo, normal, params)
    assert np.isfinite(out.color).all()
    np.testing.assert_allclose(out.color_a, pa, atol=1e-4)


# Widths around the kernel's tile (288 - pad - radius = 288 - 16 - 5 = 267 pixels at radius 5), heights
# past its band of 48 rows (the ring is filled anew), odd heights, frames smaller than the window, radius 0
# (the centre alone) and a wide radius.
@pytest.mark.parametrize(
    "size, radius",
    [((7, 9), 5), ((3, 2), 5), ((11, 267), 5), ((5, 268), 5), ((97, 268), 5), ((50, 301), 5), ((100, 30), 5),
     ((4, 6), 0), ((9, 40), 17), ((130, 20), 9)],
)  # fmt: skip
def test_kernel_matches_its_numpy_twin(size, radius):
    pa, pb, albedo, normal, params = _inputs(*size, seed=sum(size))
    pa, pb = 3 * pa, 3 * pb + 0.1
    params[:5] = np.exp(np.random.default_rng(3).uniform(-3, 5, (5, *size)))
    previous = np.random.default_rng(4).random((3, *size), np.float32)
    valid = np.random.default_rng(5).random(size) > 0.4
    got = spatiotemporal_filter(pa, pb, albedo, normal, params, previous, valid, radius)
    ref = spatiotemporal_filter(pa, pb, albedo, normal, params, previous, valid, radius, reference=True)
    for name in ("color", "color_a", "color_b"):
        np.testing.assert_allclose(getattr(got, name), getattr(ref, name), atol=KERNEL_ATOL, err_msg=name)
    np.testing.assert_allclose(got.weight_a, ref.weight_a, rtol=EXP_RTOL)
    np.testing.assert_allclose(got.weight_b, ref.weight_b, rtol=EXP_RTOL)


def test_radius_beyond_the_scratch_is_refused():
    pa, pb, albedo, normal, params = _inputs(2, 2)
    with pytest.raises(ValueError, match=rf"filter radius must be in \[0, {MAX_RADIUS}\], got {MAX_RADIUS + 1}"):
        spatiotemporal_filter(pa, pb, albedo, normal, params, radius=MAX_RADIUS + 1)


def test_inputs_of_other_shapes_are_refused_before_the_kernels():
    """The kernels do not check indices: (H, W, 3) pixels where (3, H, W) planes belong are refused."""
    pa, pb, albedo, normal, params = _inputs(4, 6)
    with pytest.raises(ValueError, match="spatiotemporal_filter: inconsistent input shapes"):
        spatiotemporal_filter(pa, pb, albedo.transpose(1, 2, 0), normal, params)
    valid = np.ones((4, 6), bool)
    with pytest.raises(ValueError, match="screen_history: current .* do not agree"):
        screen_history(pa, pb.transpose(1, 2, 0), valid)
    with pytest.raises(ValueError, match="radius must be >= 0"):
        screen_history(pa, pb, valid, radius=-1)


def test_screening_rejects_history_outside_the_current_range():
    current = np.zeros((3, 8, 8), np.float32)
    current[:, :, 4:] = 1.0
    history = current.copy()
    history[:, 1, 1] = 2.0  # brighter than anything around: a moving shadow's old value
    valid = np.ones((8, 8), bool)
    valid[7, 7] = False
    masks, screened = screen_history(current, history, valid)
    assert masks.shape == (1, 8, 8) and not masks[0, 1, 1] and not masks[0, 7, 7]
    assert masks.sum() == 62  # flat regions keep their history (<=, not <)
    np.testing.assert_array_equal(screened[:, 1, 1], current[:, 1, 1])  # rejected: the current value
    np.testing.assert_array_equal(screened[:, 0, 0], history[:, 0, 0])


def test_grouped_screening_equals_one_call_per_group():
    rng = np.random.default_rng(4)
    current = rng.random((9, 9, 11), np.float32)
    history = current + rng.normal(0, 0.3, current.shape).astype(np.float32)
    valid = rng.random((9, 11)) > 0.2
    masks, screened = screen_history(current, history, valid, groups=3)
    for g in range(3):
        part = slice(3 * g, 3 * g + 3)
        mask, alone = screen_history(current[part], history[part], valid)
        np.testing.assert_array_equal(masks[g], mask[0])
        np.testing.assert_array_equal(screened[part], alone)
    with pytest.raises(ValueError, match="9 channels do not split into 2 groups"):
        screen_history(current, history, valid, groups=2)


@pytest.mark.parametrize("size, radius", [((7, 10), 0), ((7, 10), 1), ((9, 31), 3), ((2, 3), 3), ((20, 5), 6)])
def test_screening_kernel_matches_its_numpy_twin(size, radius):
    rng = np.random.default_rng(sum(size) + radius)
    current = rng.random((6, *size), np.float32)
    history = current + rng.normal(0, 0.2, current.shape).astype(np.float32)
    history[:, 0, 0] = current[:, 0, 0]  # exactly on a bound counts as inside
    valid = rng.random(size) > 0.1
    masks, screened = screen_history(current, history, valid, radius, groups=2)
    ref_masks, ref_screened = screen_history(current, history, valid, radius, groups=2, reference=True)
    np.testing.assert_array_equal(masks, ref_masks)
    np.testing.assert_array_equal(screened, ref_screened)
    assert 0 < masks.mean() < 1


def test_the_pilot_precision_floor_by_hand():
    """s^2 is half the 5x5 in-frame mean of the channels' mean squared pilot difference; the floor is
    1 / (b s^2 + eps): at a corner of a 6x6 frame whose pilots differ by 0.3 in one channel at one pixel."""
    pa = np.zeros((3, 6, 6), np.float32)
    pb = pa.copy()
    pb[1, 0, 0] = 0.3
    floor = pilot_precision_floor(pa, pb, 8.0)
    spread = 0.5 * (0.3**2 / 3) / 9  # the corner's window holds 3x3 in-frame pixels
    np.testing.assert_allclose(floor[0, 0], 1.0 / (8.0 * spread + PRECISION_EPS), rtol=1e-5)
    np.testing.assert_allclose(floor[5, 5], 1.0 / PRECISION_EPS, rtol=1e-5)  # beyond the window: pilots agree


def test_the_floor_keeps_an_edge_both_pilots_show_against_wide_bandwidths():
    """A step of 0.5 in log1p (a shadow's edge no G-buffer shows) in both pilots, with noise of 0.02 between
    them, and a network that made every bandwidth wide (precisions 0.1): without the floor the filter blurs
    the edge across its window (0.22 off beside it); with pilot_bandwidth 32 it stays within 4% of the step
    (0.006 off)."""
    rng = np.random.default_rng(3)
    truth = np.zeros((3, 16, 24), np.float32)
    truth[:, :, 12:] = 0.5
    pa = truth + rng.normal(0, 0.02, truth.shape).astype(np.float32)
    pb = truth + rng.normal(0, 0.02, truth.shape).astype(np.float32)
    albedo, normal = np.full_like(truth, 0.5), np.zeros_like(truth)
    normal[2] = 1.0
    params = np.full((6, 16, 24), 0.1, np.float32)
    params[5] = 1.0
    wide = spatiotemporal_filter(pa, pb, albedo, normal, params).color
    kept = spatiotemporal_filter(pa, pb, albedo, normal, params, pilot_bandwidth=32.0).color
    edge = (slice(None), slice(None), slice(10, 14))
    assert np.abs(wide - truth)[edge].max() > 0.15
    assert np.abs(kept - truth)[edge].max() < 0.04 * 0.5
    flat = (slice(None), slice(None), slice(0, 6))
    assert np.abs(kept - truth)[flat].std() < 0.5 * np.abs(pa - truth)[flat].std()  # noise still averaged


def test_pilot_bandwidth_out_of_range_is_refused():
    pa, pb, albedo, normal, params = _inputs(4, 5)
    for bad in (-1.0, 1e5):
        with pytest.raises(ValueError, match="pilot_bandwidth"):
            spatiotemporal_filter(pa, pb, albedo, normal, params, pilot_bandwidth=bad)
