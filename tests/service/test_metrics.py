import numpy as np
import pytest

from service.metrics import (
    SSIM_K1,
    SSIM_K2,
    dssim,
    flip_error,
    rel_l2,
    rel_l2_map,
    ssim_map,
    temporal_rel_l2,
    trimmed_mean,
)
from service.preview import tonemap


def test_rel_l2_by_hand():
    ref = np.full((1, 2, 3), 1.0, np.float32)
    img = ref.copy()
    img[0, 0] = 2.0
    # pixel 0: (1)^2 / (1 + 0.01) per channel; pixel 1: 0
    assert rel_l2(img, ref) == pytest.approx(0.5 / 1.01)
    np.testing.assert_allclose(rel_l2_map(img, ref), [[1 / 1.01, 0.0]])


def test_trim_drops_the_worst_pixels():
    ref = np.zeros((10, 100, 3), np.float32)
    img = ref.copy()
    img[0, 0] = 100.0  # one aliased pixel of 1000
    assert rel_l2(img, ref) > 1.0
    assert rel_l2(img, ref, trim=0.001) == 0.0
    with pytest.raises(ValueError):
        rel_l2(img, ref, trim=1.0)


def test_trimmed_mean_by_hand():
    errors = np.array([[1.0, 2.0], [3.0, 1000.0]])
    assert trimmed_mean(errors, 0.25) == pytest.approx(2.0)  # the worst quarter (one value) dropped
    assert trimmed_mean(errors, 0.0) == pytest.approx(1006.0 / 4)
    assert np.isnan(trimmed_mean(np.zeros(0), 0.001))
    with pytest.raises(ValueError, match="trim must be in"):
        trimmed_mean(errors, -0.1)


# --- 1-SSIM -------------------------------------------------------------------------------------------



def _noisy(shape, sigma, seed):
    rng = np.random.default_rng(seed)
    base = np.linspace(0.1, 2.0, shape[1], dtype=np.float32)[None, :, None] * np.ones(shape, np.float32)
    return base, np.maximum(base + rng.normal(0, sigma, shape).astype(np.float32), 0.0)


def test_dssim_is_zero_for_identical_images_and_symmetric():
    ref, img = _noisy((20, 24, 3), 0.3, 0)
    assert dssim(ref, ref) == pytest.approx(0.0, abs=1e-12)
    assert dssim(img, ref) == pytest.approx(dssim(ref, img), rel=1e-12)


def test_dssim_of_two_constant_images_is_the_luminance_term():
    # No variance or covariance: SSIM reduces to (2 a b + C1) / (a^2 + b^2 + C1) (Wang 2004 eq. 13).
    a_lin, b_lin = np.full((16, 16, 3), 0.2, np.float32), np.full((16, 16, 3), 3.0, np.float32)
    a = tonemap(a_lin[:1, :1])[0, 0, 0] / 255.0
    b = tonemap(b_lin[:1, :1])[0, 0, 0] / 255.0
    c1 = SSIM_K1**2
    expected = 1.0 - (2 * a * b + c1) / (a * a + b * b + c1)
    assert dssim(a_lin, b_lin) == pytest.approx(expected, rel=1e-9)


def test_ssim_of_an_inverted_pattern_is_negative():
    # y = 1 - x around mean 1/2: equal means and variances, covariance = -variance, so SSIM < 0 where the
    # variance dominates C2 (Wang 2004 eq. 13): a structure term of (-2 v + C2) / (2 v + C2).
    x = np.tile(np.array([0.1, 0.9]), (12, 6))[..., None].repeat(3, axis=-1)
    s = ssim_map(x, 1.0 - x)
    v = 0.16  # local variance of a +-0.4 pattern (exact away from the window's reflect padding)
    assert s[6, 6, 0] == pytest.approx((-2 * v + SSIM_K2**2) / (2 * v + SSIM_K2**2), rel=0.05)


def test_dssim_grows_with_noise():
    ref, small = _noisy((32, 32, 3), 0.05, 1)
    _, large = _noisy((32, 32, 3), 0.5, 1)
    assert 0.0 < dssim(small, ref) < dssim(large, ref) <= 2.0


# --- FLIP ---------------------------------------------------------------------------------------------


def test_flip_is_zero_for_identical_images_and_grows_with_noise():
    pytest.importorskip("flip_evaluator")
    ref, small = _noisy((32, 32, 3), 0.05, 2)
    _, large = _noisy((32, 32, 3), 0.6, 2)
    assert flip_error(ref, ref) == pytest.approx(0.0, abs=1e-7)
    assert 0.0 < flip_error(small, ref) < flip_error(large, ref) <= 1.0


def test_flip_handles_a_black_reference_and_negative_values():
    pytest.importorskip("flip_evaluator")
    black = np.zeros((16, 16, 3), np.float32)
    assert flip_error(black, black) == pytest.approx(0.0, abs=1e-7)
    assert flip_error(np.ones_like(black), black) > 0.5  # white against black: near-maximal error
    assert flip_error(-np.ones_like(black), black) == pytest.approx(0.0, abs=1e-7)  # negatives count as 0


# --- temporal stability -------------------------------------------------------------------------------


def test_temporal_rel_l2_ignores_a_static_bias_and_follows_the_reference():
    rng = np.random.default_rng(3)
    r0 = rng.random((8, 8, 3)).astype(np.float32)
    r1 = r0 + 0.2
    bias = 0.3 * rng.random((8, 8, 3)).astype(np.float32)
    assert temporal_rel_l2(r0 + bias, r1 + bias, r0, r1) == pytest.approx(0.0, abs=1e-12)


def test_temporal_rel_l2_of_flicker_by_hand():
    # Constant reference c; output alternates c - e, c + e: the change 2e against 0, relative to c^2 + 0.01.
    c, e = 0.5, 0.05
    ref = np.full((4, 4, 3), c, np.float32)
    value = temporal_rel_l2(ref - e, ref + e, ref, ref)
    assert value == pytest.approx((2 * e) ** 2 / (c * c + 0.01), rel=1e-5)
