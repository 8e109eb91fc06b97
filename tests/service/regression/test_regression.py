import numpy as np
import pytest

from service.kernels.simd import LANES
from service.regression.block import (
    block_moments_reference,
    block_reconstruct,
    block_reconstruct_reference,
    block_regression,
    block_solve,
    normalise_phases,
)
from service.regression.planes import neighbour_mean, standardise
from service.regression.solve import solve_ridge, solve_ridge_reference
from service.regression.terms import BlockParams, PairTerms, plain_terms
from service.stages.outliers import (
    _log_fast,
    clamp_fireflies,
    clamp_fireflies_reference,
    clamp_outlier_clusters,
    clamp_outlier_clusters_reference,
)

PARITY_RTOL = 2e-4  # numba (fast exp, other summation order) vs numpy, float32


def _random_terms(rng: np.random.Generator, height: int, width: int) -> tuple[PairTerms, np.ndarray]:
    """Cross-regression-shaped terms: 3 groups, 2 grouped features (one scaled), 3 weight guides."""
    colour = rng.random((3, height, width), dtype=np.float32)
    terms = PairTerms(
        shared=rng.standard_normal((3, height, width), dtype=np.float32),
        grouped=np.ascontiguousarray(np.stack([colour, rng.random((3, height, width), dtype=np.float32)], axis=1)),
        scaled=np.array([True, False]),
        sigma=rng.random((height, width), dtype=np.float32),
        weight_guide=colour,
        weight_variance=rng.random((height, width), dtype=np.float32) * 0.2,
    )
    return terms, rng.standard_normal((3, height, width), dtype=np.float32)


def test_solve_ridge_matches_an_exact_solve_on_a_well_posed_system():
    rng = np.random.default_rng(0)
    x = rng.standard_normal((50, 40, 4))
    x[..., 0] = 1.0
    y = rng.standard_normal((50, 40, 2))
    gram, rhs = np.einsum("nik,nil->nkl", x, x), np.einsum("nik,nim->nkm", x, y)
    beta = solve_ridge(gram, rhs, ridge_relative=0.0, ridge_absolute=1e-12)
    np.testing.assert_allclose(beta, np.linalg.solve(gram, rhs), rtol=1e-4, atol=1e-5)
    assert beta.dtype == np.float32


def test_solve_ridge_never_gives_nan_on_singular_systems():
    zeros = solve_ridge(np.zeros((7, 3, 3)), np.zeros((7, 3, 2)))
    assert np.isfinite(zeros).all() and not zeros.any()
    # A constant feature column (column 2 == 0 after centring) and a duplicated column.
    gram = np.array([[10.0, 2.0, 0.0, 2.0], [2.0, 4.0, 0.0, 4.0], [0.0, 0.0, 0.0, 0.0], [2.0, 4.0, 0.0, 4.0]])
    beta = solve_ridge(gram[None], np.array([[[5.0], [3.0], [0.0], [3.0]]]))
    assert np.isfinite(beta).all() and beta[0, 2, 0] == 0.0
    huge = solve_ridge(gram[None] * 1e30, np.array([[[5.0], [3.0], [0.0], [3.0]]]) * 1e30)
    assert np.isfinite(huge).all()


def test_solve_ridge_matches_the_numpy_reference():
    rng = np.random.default_rng(5)
    x = rng.standard_normal((6, 7, 30, 5)).astype(np.float32)
    x[..., 0] = 1.0
    x[0, 0, :, 3] = x[0, 0, :, 2]  # one singular system
    y = rng.standard_normal((6, 7, 30, 3)).astype(np.float32)
    gram, rhs = np.einsum("...ik,...il->...kl", x, x), np.einsum("...ik,...im->...km", x, y)
    np.testing.assert_allclose(solve_ridge(gram, rhs), solve_ridge_reference(gram, rhs), rtol=1e-5, atol=1e-6)
    sums = np.full((6, 7), 30.0)
    np.testing.assert_allclose(solve_ridge(gram[..., 1:, 1:], rhs[..., 1:, :], 1e-2, 1e-3, weight_sum=sums),
                               solve_ridge_reference(gram[..., 1:, 1:], rhs[..., 1:, :], 1e-2, 1e-3, weight_sum=sums),
                               rtol=1e-5, atol=1e-6)  # fmt: skip


def test_neighbour_mean_excludes_the_pixel_and_handles_borders_and_1x1():
    planes = np.arange(9, dtype=np.float32).reshape(1, 3, 3)
    mean = neighbour_mean(planes)
    assert mean[0, 1, 1] == pytest.approx((36 - 4) / 8)
    assert mean[0, 0, 0] == pytest.approx((1 + 3 + 4) / 3)
    np.testing.assert_array_equal(neighbour_mean(np.full((2, 1, 1), 5.0, np.float32)), 5.0)


def test_clamp_fireflies_removes_an_isolated_outlier_and_keeps_constants():
    planes = np.ones((3, 9, 11), np.float32)
    np.testing.assert_array_equal(clamp_fireflies(planes), planes)
    rng = np.random.default_rng(1)
    noisy = (1.0 + 0.2 * rng.standard_normal((3, 9, 11))).astype(np.float32)
    noisy[:, 4, 5] = 1e6
    noisy[1, 2, 2] = -1e6
    out = clamp_fireflies(noisy)
    assert out[:, 4, 5].max() < 5.0 and out[1, 2, 2] > -3.0
    np.testing.assert_array_equal(np.delete(out[0].ravel(), 4 * 11 + 5), np.delete(noisy[0].ravel(), 4 * 11 + 5))
    np.testing.assert_array_equal(out, clamp_fireflies_reference(noisy))
    single = np.array([[[7.0]]], np.float32)
    np.testing.assert_array_equal(clamp_fireflies(single), single)


def test_clamp_fireflies_matches_its_twin_across_bands_with_nan_and_inf():
    """Several bands of rows (BAND_ROWS), 1-pixel sides, infinities; a NaN takes no part in its neighbours'
    ranges (the twin's `excluded`) and stays NaN."""
    rng = np.random.default_rng(3)
    for shape in ((2, 37, 21), (1, 33, 1), (3, 1, 40), (1, 2, 2)):
        planes = (rng.lognormal(0, 2, shape) * rng.choice([-1, 1], shape)).astype(np.float32)
        mask = rng.random(shape)
        planes[mask < 0.03] = np.nan
        planes[(mask > 0.03) & (mask < 0.05)] = np.inf
        planes[(mask > 0.05) & (mask < 0.06)] = -np.inf
        planes[..., shape[1] // 2, :] = np.nan  # a whole row at a band's edge or inside one
        for k in (2.0, 0.5):
            expected = clamp_fireflies_reference(planes, k, excluded=np.isnan(planes))
            np.testing.assert_array_equal(clamp_fireflies(planes, k), expected)


def test_standardise_puts_planes_on_unit_scale_and_zeroes_constant_ones():
    planes = np.stack([np.full((4, 5), 3.0), np.arange(20.0).reshape(4, 5) * 1e4]).astype(np.float32)
    out = standardise(planes)
    assert not out[0].any()
    assert out[1].mean() == pytest.approx(0.0, abs=1e-6) and out[1].std() == pytest.approx(1.0, rel=1e-5)


def test_standardise_matches_the_numpy_reference():
    from service.regression.planes import standardise_reference

    rng = np.random.default_rng(6)
    planes = (rng.standard_normal((4, 13, 17)) * [[[1.0]], [[1e3]], [[0.0]], [[1e-3]]] + 5.0).astype(np.float32)
    np.testing.assert_allclose(standardise(planes), standardise_reference(planes), rtol=1e-5, atol=1e-5)
    assert standardise(np.zeros((0, 3, 4), np.float32)).shape == (0, 3, 4)


@pytest.mark.parametrize("size", [(1, 1), (3, 5), (17, 31), (29, 22), (4, 1600)])  # 1600: more centres than LANE_CHUNK
def test_block_kernels_match_the_numpy_reference(size):
    rng = np.random.default_rng(2)
    terms, target = _random_terms(rng, *size)
    params = BlockParams(radius=5, sparsity=3, sigma_position=4.0)
    beta_ref = solve_ridge_reference(*block_moments_reference(terms, target, params))
    beta = block_solve(terms, target, params)
    assert beta.shape == beta_ref.shape and beta.dtype == np.float32
    np.testing.assert_allclose(beta, beta_ref, rtol=PARITY_RTOL, atol=PARITY_RTOL * np.abs(beta_ref).max())
    beta = beta_ref
    out, out_ref = block_reconstruct(terms, beta, params), block_reconstruct_reference(terms, beta, params)
    assert out.shape == (3, *size) and out.dtype == np.float32
    np.testing.assert_allclose(out, out_ref, rtol=1e-3, atol=1e-3 * np.abs(out_ref).max())


@pytest.mark.parametrize("size", [(1, 1), (17, 31)])
def test_block_solve_matches_the_reference_on_bmfr_terms(size):
    """BMFR-style terms: shared features only, no grouped ones, flat weights."""
    rng = np.random.default_rng(8)
    terms = plain_terms(rng.standard_normal((5, *size), dtype=np.float32), groups=3)
    target = rng.standard_normal((3, *size), dtype=np.float32)
    params = BlockParams(radius=4, sparsity=2, sigma_position=3.0)
    beta_ref = solve_ridge_reference(*block_moments_reference(terms, target, params))
    np.testing.assert_allclose(
        block_solve(terms, target, params), beta_ref, rtol=PARITY_RTOL, atol=PARITY_RTOL * np.abs(beta_ref).max()
    )


@pytest.mark.parametrize("size", [(1, 1), (3, 5), (29, 22)])
def test_pack_planes_matches_the_numpy_phase_split(size):
    from service.regression.block import MomentLayout, pack_planes, phase_planes

    terms, target = _random_terms(np.random.default_rng(5), *size)
    params = BlockParams(radius=5, sparsity=3)
    expected = phase_planes(MomentLayout.of(terms, 3).pack(terms, target), params)
    np.testing.assert_array_equal(pack_planes(terms, target, params), expected)


@pytest.mark.parametrize("size", [(1, 1), (3, 5), (29, 22), (7, 300), (13, 1400)])  # 1400: 2-4 column tiles
@pytest.mark.parametrize("radius, sparsity", [(5, 3), (6, 6), (4, 3), (5, 2)])  # (2r+1) mod s head rows: 2, 1, 0, 1
def test_box_regression_matches_the_pair_by_pair_reference(size, radius, sparsity):
    from service.regression.box import box_regression

    rng = np.random.default_rng(7)
    y, x = np.mgrid[0 : size[0], 0 : size[1]].astype(np.float32)
    features = standardise(np.concatenate([rng.standard_normal((3, *size), dtype=np.float32), x[None], y[None]]))
    target = rng.standard_normal((3, *size), dtype=np.float32)
    albedo = rng.random((*size, 3), dtype=np.float32)
    params = BlockParams(radius=radius, sparsity=sparsity)
    for factor in (None, albedo):  # remodulated in the last pass, or not
        out = box_regression(features, target, params, albedo=factor)
        ref = box_regression(features, target, params, albedo=factor, reference=True)
        assert out.shape == (3, *size) and out.dtype == np.float32
        np.testing.assert_allclose(out, ref, rtol=1e-4, atol=1e-4 * np.abs(ref).max())
    with pytest.raises(ValueError, match="flat weights"):
        box_regression(features, target, BlockParams(radius=5, sparsity=3, sigma_position=2.0))


def test_block_regression_reproduces_an_exact_linear_function_of_the_features():
    rng = np.random.default_rng(3)
    height, width = 40, 44
    y, x = np.mgrid[0:height, 0:width].astype(np.float32)
    shared = np.stack([np.sin(x / 5.0), np.cos(y / 7.0), (x * y) / 500.0 + rng.random((height, width)) * 0.3])
    shared = shared.astype(np.float32)
    coef = np.array([[0.5, -2.0, 1.0], [1.5, 0.3, -0.7], [-1.0, 0.0, 2.0]], np.float32)
    target = np.einsum("ck,khw->chw", coef, shared) + np.array([1.0, -3.0, 0.2], np.float32)[:, None, None]
    out = block_regression(plain_terms(standardise(shared)), target.astype(np.float32), BlockParams())
    np.testing.assert_allclose(out, target, atol=2e-3 * np.abs(target).max())


def test_block_regression_of_a_constant_is_the_constant():
    rng = np.random.default_rng(4)
    terms, _ = _random_terms(rng, 23, 19)
    target = np.full((3, 23, 19), 0.37, np.float32)
    np.testing.assert_allclose(block_regression(terms, target, BlockParams()), target, rtol=1e-5)


def _cluster_frame(rng, height=40, width=48):
    """Dim smooth background (0.5 .. 1.0, 4-spp-like noise) with a 3x3 cluster of fireflies at 1e3."""
    ramp = np.linspace(0.5, 1.0, width, dtype=np.float32)
    clean = np.broadcast_to(ramp, (3, height, width)).astype(np.float32)
    noisy = clean * rng.gamma(4.0, 0.25, (3, height, width)).astype(np.float32)
    noisy[:, 18:21, 20:23] = 1e3
    return clean, noisy


def test_clamp_outlier_clusters_matches_reference_and_keeps_smooth_images():
    rng = np.random.default_rng(3)
    _, noisy = _cluster_frame(rng)
    noisy[1, 5, 7] = -400.0  # a negative outlier (emission-subtraction residual)
    np.testing.assert_allclose(clamp_outlier_clusters(noisy), clamp_outlier_clusters_reference(noisy), rtol=1e-5)
    ramp = np.broadcast_to(np.linspace(0.1, 5.0, 30, dtype=np.float32), (2, 20, 30)).copy()
    np.testing.assert_array_equal(clamp_outlier_clusters(ramp), ramp)
    np.testing.assert_array_equal(clamp_outlier_clusters(np.full((1, 1, 1), 7.0, np.float32)), np.full((1, 1, 1), 7.0))


@pytest.mark.parametrize("shape, radius", [((1, 1, 1), 3), ((2, 2, 5), 3), ((1, 5, 2), 3), ((3, 17, 33), 3),
                                           ((2, 35, 20), 1), ((1, 30, 30), 0), ((2, 50, 41), 5)])  # fmt: skip
def test_clamp_outlier_clusters_matches_reference_at_odd_sizes(shape, radius):
    rng = np.random.default_rng(5)
    x = rng.gamma(1.0, 1.0, shape) * np.where(rng.random(shape) < 0.05, 300.0, 1.0)  # sparse outliers
    x = (x * np.where(rng.random(shape) < 0.1, -1.0, 1.0)).astype(np.float32)  # negative ones too
    np.testing.assert_allclose(
        clamp_outlier_clusters(x, radius), clamp_outlier_clusters_reference(x, radius), rtol=1e-5, atol=1e-6
    )


def test_log_fast_matches_log():
    v = np.concatenate([1.0 + np.geomspace(1e-7, 1e9, 5000), [1.0, 1.41421, 1.41422, 2.0]]).astype(np.float32)
    got = np.array([_log_fast(x) for x in v], np.float64)
    np.testing.assert_allclose(got, np.log(v.astype(np.float64)), rtol=3e-7, atol=1e-7)


def test_clamp_outlier_clusters_rejects_a_cluster_the_3x3_clamp_keeps():
    rng = np.random.default_rng(4)
    clean, noisy = _cluster_frame(rng)
    assert clamp_fireflies(noisy)[:, 19, 21].min() == 1e3  # shielded by its own neighbours
    out = clamp_outlier_clusters(noisy)
    assert out[:, 18:21, 20:23].max() < 20.0
    outside = np.ones(noisy.shape[1:], bool)
    outside[18:21, 20:23] = False
    changed = (out != noisy)[:, outside].mean()
    assert changed < 0.01  # the background noise is left almost untouched


@pytest.mark.parametrize("constant", [True, False])
def test_cholesky_ridge_solve_matches_the_numpy_reference(constant):
    from service.regression.solve import cholesky_ridge_solve

    rng = np.random.default_rng(9)
    lanes, k, m = 21, 5, 3
    x = rng.standard_normal((lanes, 40, k))
    x[..., 0] = 1.0 if constant else x[..., 0]
    x[3, :, 2] = x[3, :, 1]  # a singular system
    x[4, :, 1:] = 0.0  # features that never vary
    gram, rhs = np.einsum("lik,lij->lkj", x, x), np.einsum("lik,lim->lkm", x, rng.standard_normal((lanes, 40, m)))
    a, b = np.ascontiguousarray(gram.transpose(1, 2, 0)), np.ascontiguousarray(rhs.transpose(1, 2, 0))
    sums = rng.uniform(0.5, 2.0, lanes)
    cholesky_ridge_solve(a, b, k, m, 1e-3, 1e-6, constant, sums, lanes - 1)  # the last lane is left alone
    weight_sum = None if constant else sums[:-1]
    ref = solve_ridge_reference(gram[:-1], rhs[:-1], 1e-3, 1e-6, weight_sum=weight_sum)
    np.testing.assert_allclose(b[..., :-1].transpose(2, 0, 1), ref, rtol=1e-5, atol=1e-6)
    np.testing.assert_array_equal(b[..., -1], rhs[-1])
    assert np.isfinite(b).all() and not b[1:, :, 4].any()  # no slope for features that never vary


@pytest.mark.parametrize("channels", [1, 3, 4])
def test_channel_planes_match_the_numpy_reference(channels):
    from service.regression.planes import channel_planes, channel_planes_reference

    rng = np.random.default_rng(10)
    image = rng.standard_normal((9, 14, channels), dtype=np.float32)
    albedo = rng.random((9, 14, channels), dtype=np.float32) - 0.1  # negative albedo counts as 0
    for factor in (None, albedo):
        np.testing.assert_array_equal(channel_planes(image, factor), channel_planes_reference(image, factor))
    stack = np.zeros((channels + 2, 9, 14), np.float32)
    channel_planes(image, albedo, out=stack[1:-1])  # into a slice of a larger stack
    np.testing.assert_array_equal(stack[1:-1], channel_planes_reference(image, albedo))
    assert not stack[0].any() and not stack[-1].any()


def test_standardise_in_place_matches_the_numpy_reference_over_many_blocks():
    from service.regression.planes import STANDARDISE_BLOCK, standardise_reference

    planes = np.random.default_rng(11).standard_normal((3, 20, 70000 // 20)).astype(np.float32) * 3 + 7
    assert planes[0].size > STANDARDISE_BLOCK  # sums over two blocks, relative to the first value
    expected = standardise_reference(planes)
    assert standardise(planes, out=planes) is planes
    np.testing.assert_allclose(planes, expected, rtol=1e-5, atol=1e-5)


# subsamples of 1, 12, 12, 24 and 9 values: both median branches
@pytest.mark.parametrize("shape", [(1, 1, 1), (3, 5, 7), (3, 8, 8), (2, 9, 13), (1, 9, 9)])
def test_radiance_scale_is_the_median_of_the_subsample(shape):
    from service.stages.outliers import radiance_scale

    planes = np.random.default_rng(12).standard_normal(shape).astype(np.float32)
    expected = max(float(np.median(np.abs(planes[:, ::4, ::4]).astype(np.float64))), 1e-6)
    assert radiance_scale(planes) == pytest.approx(expected, rel=1e-7)
    assert radiance_scale(np.zeros(shape, np.float32)) == 1e-6


@pytest.mark.parametrize("sparsity, width", [(4, 4 * LANES * 2 + 5), (4, 3), (3, 40), (1, 7)])
def test_normalise_phases_divides_and_unsplits_every_pixel(sparsity, width):
    """Whole blocks (as vectors at sparsity 4) and the tail: pixel x = S q + p from lane pad + q of phase p;
    no weight gives 0."""
    rng = np.random.default_rng(9)
    pad, height = 2, 3
    lanes = -(-width // sparsity) + 2 * pad + LANES
    num = rng.standard_normal((sparsity, 2, height, lanes)).astype(np.float32)
    den = rng.random((sparsity, height, lanes)).astype(np.float32) + 0.5
    den[0, 1, pad] = 0.0  # pixel (1, 0): no weight arrived
    num[0, :, 1, pad] = 0.0
    out = np.full((2, height, width), np.nan, np.float32)
    normalise_phases(num, den, pad, out)
    x = np.arange(width)
    p, q = x % sparsity, pad + x // sparsity
    expected = num[p, :, :, q] / np.where(den > 0, den, 1.0)[p, :, q][:, None]  # (W, C, H); 0 / 1 without weight
    np.testing.assert_allclose(out, np.moveaxis(expected, 0, -1), rtol=1e-6)
