import numpy as np
import pytest

from service.stages.cross_regression import (
    CrossRegressionParams,
    cross_regression,
    linear_to_log,
    log_to_linear,
    pixel_variance,
    pixel_variance_reference,
)

PARITY_ATOL = 1e-3  # log units: numba (fast exp, other summation order) vs numpy, float32


def _gbuffers(height, width, rng):
    albedo = rng.uniform(0.1, 0.9, (height, width, 3)).astype(np.float32)
    normal = rng.standard_normal((height, width, 3)).astype(np.float32)
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    return albedo, normal


def test_log_space_is_log1p_and_round_trips_negative_radiance():
    x = np.array([0.0, 0.5, 3.0, 1e4, -0.5, -7.0], np.float32)
    np.testing.assert_allclose(linear_to_log(x[:4]), np.log1p(x[:4]), rtol=1e-6)
    np.testing.assert_allclose(log_to_linear(linear_to_log(x)), x, rtol=1e-5)
    assert np.isfinite(log_to_linear(np.float32([1e3, -1e3]))).all()


def test_pixel_variance_is_squared_distance_to_the_neighbour_mean():
    planes = np.zeros((3, 3, 3), np.float32)
    planes[:, 1, 1] = 1.0
    var = pixel_variance(planes)
    assert var[1, 1] == pytest.approx(3.0)  # 1^2 per channel, neighbours all 0
    assert var[0, 0] == pytest.approx(3 * (1 / 3) ** 2)


@pytest.mark.parametrize("shape", [(3, 1, 1), (3, 1, 7), (3, 6, 1), (3, 2, 2), (3, 31, 47)])
def test_pixel_variance_matches_the_numpy_reference(shape):
    planes = np.random.default_rng(4).standard_normal(shape).astype(np.float32)
    np.testing.assert_allclose(pixel_variance(planes), pixel_variance_reference(planes), rtol=1e-5, atol=1e-6)


def test_params_are_validated():
    with pytest.raises(ValueError, match="odd"):
        CrossRegressionParams(window=16)
    with pytest.raises(ValueError, match="centre"):
        CrossRegressionParams(window=3, sparsity=4)
    with pytest.raises(ValueError, match="firefly_k must be > 0 or None, got 0.0"):
        CrossRegressionParams(firefly_k=0.0)


def test_pilot_a_is_fitted_to_buffer_b_and_pilot_b_to_buffer_a():
    """Choi eqs. 3-5: pilot_a = f~(x^A) regresses y^B on A's variables; so a constant buffer B gives
    pilot_a = log1p(B) exactly, whatever A holds, and vice versa."""
    rng = np.random.default_rng(0)
    albedo, normal = _gbuffers(21, 26, rng)
    noisy = rng.lognormal(0.0, 1.0, (21, 26, 3)).astype(np.float32)
    flat = np.full((21, 26, 3), 2.0, np.float32)
    pilot_a, pilot_b = cross_regression(noisy, flat, albedo, normal)
    np.testing.assert_allclose(pilot_a, np.log1p(2.0), rtol=1e-5)
    assert np.abs(pilot_b - np.log1p(2.0)).max() > 0.1  # fitted to the noisy buffer A
    pilot_a, pilot_b = cross_regression(flat, noisy, albedo, normal)
    np.testing.assert_allclose(pilot_b, np.log1p(2.0), rtol=1e-5)


def test_numba_matches_the_numpy_reference():
    rng = np.random.default_rng(1)
    albedo, normal = _gbuffers(19, 27, rng)
    a, b = (rng.lognormal(0.0, 1.0, (19, 27, 3)).astype(np.float32) for _ in range(2))
    fast = cross_regression(a, b, albedo, normal)
    slow = cross_regression(a, b, albedo, normal, reference=True)
    for f, s in zip(fast, slow, strict=True):
        assert f.shape == (19, 27, 3) and f.dtype == np.float32
        np.testing.assert_allclose(f, s, atol=PARITY_ATOL)


def test_a_log_colour_linear_in_albedo_and_normal_is_reproduced():
    rng = np.random.default_rng(2)
    albedo, normal = _gbuffers(36, 40, rng)
    mix = np.array([[0.2, -0.1, 0.3], [0.0, 0.4, -0.2], [0.1, 0.1, 0.1]], np.float32)
    log_colour = 0.3 + 1.2 * albedo + normal @ mix
    colour = log_to_linear(log_colour)
    pilot_a, pilot_b = cross_regression(colour, colour, albedo, normal)
    inner = (slice(8, -8), slice(8, -8))
    for pilot in (pilot_a, pilot_b):
        np.testing.assert_allclose(pilot[inner], log_colour[inner], atol=0.02)
