import numpy as np
import pytest

from service.kernels.simd import LANES
from service.regression.block import pad_lanes
from service.regression.planes import from_planes
from service.regression.terms import BlockParams
from service.stages.cross_block import BUFFER_A, BUFFER_B, pack_cross_reference
from service.stages.cross_regression import (
    LOG_MAX,
    CrossRegressionParams,
    cross_regression,
    cross_regression_radiance,
    linear_to_log,
    log_planes_reference,
    log_to_linear,
    pack_buffers,
    pilots_to_radiance,
    pilots_to_radiance_reference,
    pixel_variance_reference,
)
from service.stages.outliers import FIREFLY_K
from service.stages.range_clamp import clamp_to_local_range

PARITY_ATOL = 1e-3  # log units: numba (fast exp, other summation order) vs numpy, float32
LOG1P_ULP = 1.0  # pack_buffers' log1p (musl's log1pf) against float64 log1p, float32 ulp
EXPM1_ULP = 2.0  # pilots_to_radiance's expm1 against float64 expm1, float32 ulp
TWIN_RTOL = 1e-6  # numba kernels vs numpy's SIMD log1p / expm1 (up to ~2.5 ulp each), relative
PACK_RTOL = 1e-5  # pack_buffers vs the numpy twins: variances of logs a few ulp apart (measured 1.3e-6), relative
ODD_SIZES = [(1, 1), (3, 5), (17, 31)]
# thin and tiny frames (a variance with 1-3 neighbours), and whole vector blocks at sparsity 4 with a tail
PACK_SIZES = [(1, 1), (1, 7), (6, 1), (2, 2), (3, 5), (17, 31), (29, 22), (7, 4 * LANES * 2 + 9)]


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
    var = pixel_variance_reference(planes)
    assert var[1, 1] == pytest.approx(3.0)  # 1^2 per channel, neighbours all 0
    assert var[0, 0] == pytest.approx(3 * (1 / 3) ** 2)


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
        assert f.shape == (3, 19, 27) and f.dtype == np.float32
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
        np.testing.assert_allclose(from_planes(pilot)[inner], log_colour[inner], atol=0.02)


def _ulp_error(value: np.ndarray, exact: np.ndarray) -> np.ndarray:
    """|value - exact| in units of the float32 spacing at `exact` (float64)."""
    spacing = np.spacing(np.abs(exact).astype(np.float32)).astype(np.float64)
    return np.abs(value.astype(np.float64) - exact) / spacing


def _radiance(height, width, rng):
    """Lognormal radiance with negative values and a 1e6 firefly (and a -1e6 one on larger frames)."""
    color = rng.lognormal(0.0, 2.0, (height, width, 3)).astype(np.float32)
    color *= np.where(rng.random(color.shape) < 0.2, -1.0, 1.0).astype(np.float32)
    color[height // 2, width // 2, 1] = 1e6
    if height * width > 1:
        color[0, -1, 2] = -1e6
    return color


def _unpack(planes: np.ndarray, first: int, count: int, width: int, params: BlockParams) -> np.ndarray:
    """Planes first ... first + count - 1 of packed phase planes back as (count, H, W) frame planes."""
    s, pad = params.sparsity, pad_lanes(params)
    return np.stack([planes[x % s, first : first + count, :, pad + x // s] for x in range(width)], axis=-1)


def _logs(color: np.ndarray, firefly_k) -> np.ndarray:
    """Buffer A's log planes (3, H, W) as `pack_buffers` takes them."""
    zeros = np.zeros_like(color)
    planes = pack_buffers(color, color, zeros, zeros, firefly_k, BlockParams())
    return _unpack(planes, BUFFER_A, 3, color.shape[1], BlockParams())


@pytest.mark.parametrize("params", [BlockParams(), BlockParams(radius=5, sparsity=3)], ids=["paper", "sparsity3"])
@pytest.mark.parametrize("firefly_k", [FIREFLY_K, 0.5, None])
@pytest.mark.parametrize("size", PACK_SIZES)
def test_pack_buffers_matches_the_numpy_reference(size, firefly_k, params):
    """Log colour within the log1p twins' ulps, variances (and so sigmas) within PACK_RTOL, everything else
    (mask, G-buffers, zeros in the pad lanes) exactly; on radiance with negative values and fireflies."""
    color_a, color_b, albedo, normal = _pack_inputs(size)
    log_a, log_b = log_planes_reference(color_a, firefly_k), log_planes_reference(color_b, firefly_k)
    twin = pack_cross_reference(log_a, pixel_variance_reference(log_a), log_b, pixel_variance_reference(log_b), albedo,
                                normal, params)  # fmt: skip
    fused = pack_buffers(color_a, color_b, albedo, normal, firefly_k, params)
    assert fused.shape == twin.shape and fused.dtype == np.float32 and np.isfinite(fused).all()
    for buffer, log in ((BUFFER_A, log_a), (BUFFER_B, log_b)):
        np.testing.assert_allclose(_unpack(fused, buffer, 3, size[1], params), log, rtol=TWIN_RTOL, atol=0.0)
        np.testing.assert_allclose(fused[:, buffer + 3 : buffer + 5], twin[:, buffer + 3 : buffer + 5], rtol=PACK_RTOL,
                                   atol=1e-6)  # fmt: skip
    np.testing.assert_array_equal(fused[:, :BUFFER_A], twin[:, :BUFFER_A])


def test_pack_buffers_clamps_fireflies_then_takes_the_signed_log():
    color = np.ones((5, 7, 3), np.float32)
    color[2, 3] = [1e6, -1e6, 1.0]
    color[0, 0, 0] = 1e6  # a corner, 3 neighbours
    np.testing.assert_allclose(_logs(color, FIREFLY_K), np.log1p(1.0), rtol=1e-7)  # neighbours all 1
    unclamped = _logs(color, None)
    assert unclamped[0, 2, 3] == unclamped[0, 0, 0] == pytest.approx(np.log1p(1e6), rel=1e-7)
    assert unclamped[1, 2, 3] == pytest.approx(-np.log1p(1e6), rel=1e-7)
    single = np.float32([[[1e6, -3.0, 0.0]]])  # 1x1: no neighbour, nothing clamped
    np.testing.assert_allclose(_logs(single, FIREFLY_K).ravel(), [np.log1p(1e6), -np.log1p(3.0), 0.0], rtol=1e-7)


def test_pack_buffers_log_is_log1p_within_an_ulp_over_the_float32_range():
    rng = np.random.default_rng(6)
    magnitude = np.concatenate(
        [np.float32([0.0, 1e-30, 1e-8, 0.41421354, 0.41421366, 1.0, 3e38]), np.exp(rng.uniform(-30, 88, 30000))]
    ).astype(np.float32)
    values = magnitude * np.where(rng.random(magnitude.size) < 0.5, -1.0, 1.0).astype(np.float32)
    color = values[: values.size // 3 * 3].reshape(1, -1, 3)
    got = _logs(color, None)[:, 0].T.ravel()
    exact = np.sign(color.ravel()) * np.log1p(np.abs(color.ravel().astype(np.float64)))
    assert _ulp_error(got, exact).max() <= LOG1P_ULP


def _pack_inputs(size):
    rng = np.random.default_rng(9)
    return _radiance(*size, rng), _radiance(*size, rng), *_gbuffers(*size, rng)


def test_pack_buffers_refuses_layers_of_other_shapes():
    color = np.ones((4, 6, 3), np.float32)
    shapes = r"pack_buffers: expected \(H, W, 3\) layers of one shape, got .*'color_b': \(4, 5, 3\)"
    with pytest.raises(ValueError, match=shapes):
        pack_buffers(color, color[:, :5], color, color, FIREFLY_K, BlockParams())


@pytest.mark.parametrize("size", PACK_SIZES)
@pytest.mark.parametrize("window", [17, 7])
def test_cross_regression_radiance_is_the_chain_of_its_stages(size, window):
    rng = np.random.default_rng(11)
    color_a, color_b = (rng.exponential(1.0, (*size, 3)).astype(np.float32) for _ in range(2))
    color_a[0, 0] = [1e6, -2.0, 0.0]  # a firefly and negative radiance
    albedo, normal = _gbuffers(*size, rng)
    noisy = 0.5 * (color_a + color_b)
    params = CrossRegressionParams(window=window)
    fused = cross_regression_radiance(color_a, color_b, albedo, normal, noisy, params)
    pilots = cross_regression(color_a, color_b, albedo, normal, params)
    chain = clamp_to_local_range(pilots_to_radiance(*pilots), noisy, window // 2)
    np.testing.assert_array_equal(fused, chain)  # the same float32 operations, fused
    assert fused.dtype == np.float32 and np.isfinite(fused).all()


def test_cross_regression_radiance_refuses_a_noisy_frame_of_another_size():
    color = np.ones((4, 6, 3), np.float32)
    with pytest.raises(ValueError, match=r"cross_regression_radiance: noisy \(4, 5, 3\) != the halves \(4, 6, 3\)"):
        cross_regression_radiance(color, color, color, color, color[:, :5])


@pytest.mark.parametrize("size", ODD_SIZES)
def test_pilots_to_radiance_matches_the_numpy_reference(size):
    rng = np.random.default_rng(7)
    pilot_a, pilot_b = (rng.uniform(-100.0, 100.0, (3, *size)).astype(np.float32) for _ in range(2))
    pilot_a[:, 0, 0] = [LOG_MAX, -1e3, 0.0]  # clipped to +-LOG_MAX, as log_to_linear does
    fast, slow = pilots_to_radiance(pilot_a, pilot_b), pilots_to_radiance_reference(pilot_a, pilot_b)
    assert fast.shape == (*size, 3) and fast.dtype == np.float32 and np.isfinite(fast).all()
    scale = 0.5 * (np.abs(log_to_linear(pilot_a)) + np.abs(log_to_linear(pilot_b))).transpose(1, 2, 0)
    assert (np.abs(fast - slow) <= TWIN_RTOL * scale).all()  # relative to the terms: a + b may cancel


def test_pilots_to_radiance_is_the_mean_radiance_as_pixels():
    radiance_a = np.float32([[[0.0, 2.0]], [[-3.0, 1e6]], [[0.5, -0.25]]])  # (3, 1, 2) planes
    radiance_b = np.float32([[[4.0, 2.0]], [[3.0, 0.0]], [[1.5, -0.75]]])
    out = pilots_to_radiance(linear_to_log(radiance_a), linear_to_log(radiance_b))
    np.testing.assert_allclose(out, (0.5 * (radiance_a + radiance_b)).transpose(1, 2, 0), rtol=1e-6)
    top = pilots_to_radiance(np.full((3, 1, 1), 1e3, np.float32), np.full((3, 1, 1), 1e3, np.float32))
    assert np.isfinite(top).all() and top[0, 0, 0] == pytest.approx(np.expm1(88.0), rel=1e-6)


def test_pilots_to_radiance_is_expm1_within_two_ulp():
    rng = np.random.default_rng(8)
    logs = np.concatenate([np.float32([0.0, 1e-30, 1e-8, 0.34, 0.35, -1.0, 87.9, -88.0]), rng.uniform(-88, 88, 30000)])
    logs = logs.astype(np.float32)[: logs.size // 3 * 3].reshape(3, 1, -1)
    got = pilots_to_radiance(logs, logs)[0].T.ravel()  # the mean of two equal terms is exact
    exact = np.sign(logs.ravel()) * np.expm1(np.abs(logs.ravel().astype(np.float64)))
    assert _ulp_error(got, exact).max() <= EXPM1_ULP
