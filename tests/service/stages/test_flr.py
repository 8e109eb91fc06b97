import numpy as np
import pytest

from service.stages.flr import (
    FlrParams,
    apply_coefficients,
    apply_coefficients_reference,
    cell_sums,
    cell_sums_reference,
    gaussian_blur,
    gaussian_blur_reference,
    gbuffer_guides,
    gbuffer_guides_reference,
    local_linear_regression,
    solve_cells,
    solve_cells_reference,
)


def _guides(height, width, rng):
    y, x = np.mgrid[0:height, 0:width].astype(np.float32)
    normal = np.stack([np.sin(x / 7.0), np.cos(y / 5.0), 0.2 + 0.0 * x], axis=-1).astype(np.float32)
    depth = (2.0 + y / height + 0.2 * rng.random((height, width)))[..., None].astype(np.float32)
    ao = (0.5 + 0.5 * np.sin(x / 4.0 + y / 6.0))[..., None].astype(np.float32)
    return normal, depth, ao


def test_guides_take_what_is_present():
    rng = np.random.default_rng(0)
    normal, depth, ao = _guides(8, 9, rng)
    assert gbuffer_guides(normal, depth, ao).shape == (8, 9, 5)
    assert gbuffer_guides(normal).shape == (8, 9, 3)
    with pytest.raises(ValueError, match="at least one guide"):
        gbuffer_guides()


@pytest.mark.parametrize("size", [(1, 1), (3, 5), (17, 31), (9, 40)])
@pytest.mark.parametrize("scale", [1, 2, 4])
def test_numba_kernels_match_the_numpy_reference(size, scale):
    rng = np.random.default_rng(1)
    x = rng.standard_normal((4, *size)).astype(np.float32)
    y = rng.standard_normal((3, *size)).astype(np.float32)
    sums = cell_sums(x, y, scale)
    assert sums.shape == (-(-size[0] // scale), 1 + 4 + 3 + 10 + 12, -(-size[1] // scale))
    np.testing.assert_allclose(sums, cell_sums_reference(x, y, scale), rtol=1e-5, atol=1e-4)
    blurred = gaussian_blur(sums, 1.0, 3.0)
    np.testing.assert_allclose(blurred, gaussian_blur_reference(sums, 1.0, 3.0), rtol=1e-5, atol=1e-4)
    coefs = solve_cells(blurred, 4, 3, FlrParams(scale=scale))
    assert coefs.shape == (sums.shape[0], 5, 3, sums.shape[2]) and coefs.dtype == np.float32
    expected = solve_cells_reference(blurred, 4, 3, FlrParams(scale=scale))
    np.testing.assert_allclose(coefs, expected, rtol=1e-4, atol=1e-4)
    fast = apply_coefficients(x, coefs, scale)
    np.testing.assert_allclose(fast, apply_coefficients_reference(x, coefs, scale), rtol=1e-5, atol=1e-5)
    assert fast.shape == (3, *size) and np.isfinite(fast).all()
    albedo = rng.random((*size, 3), dtype=np.float32)  # remodulation fused into the store
    np.testing.assert_allclose(apply_coefficients(x, coefs, scale, albedo),
                               apply_coefficients_reference(x, coefs, scale, albedo), rtol=1e-5, atol=1e-5)  # fmt: skip


def test_guides_match_the_numpy_reference_and_are_planes_in_memory():
    normal, depth, ao = _guides(11, 13, np.random.default_rng(4))
    depth[0, 0] = 0.0  # below DEPTH_FLOOR
    for layers in ((normal, depth, ao), (normal, None, None), (None, depth, ao)):
        guides = gbuffer_guides(*layers)
        np.testing.assert_array_equal(guides, gbuffer_guides_reference(*layers))
        assert guides.transpose(2, 0, 1).flags.c_contiguous  # `to_planes` of it is free


def test_without_guides_the_solve_gives_the_weighted_mean():
    rng = np.random.default_rng(6)
    sums = gaussian_blur(cell_sums(np.zeros((0, 9, 10), np.float32), rng.random((3, 9, 10), np.float32), 2), 0.5, 3.0)
    coefs = solve_cells(sums, 0, 3, FlrParams())
    np.testing.assert_allclose(coefs[:, 0], sums[:, 1:4] / sums[:, :1], rtol=1e-6)
    np.testing.assert_allclose(coefs, solve_cells_reference(sums, 0, 3, FlrParams()), rtol=1e-6)


def test_radiance_linear_in_the_guides_is_reproduced():
    rng = np.random.default_rng(2)
    normal, depth, ao = _guides(37, 45, rng)
    guides = gbuffer_guides(normal, depth, ao)
    radiance = 0.5 + guides @ np.float32([[0.3, 0.1, 0.0], [-0.2, 0.4, 0.1], [0.0, 0.0, 0.2], [1.0, 0.5, -0.3],
                                          [0.7, 0.2, 0.9]])  # fmt: skip
    out = local_linear_regression(radiance, guides, FlrParams(firefly_k=None))
    np.testing.assert_allclose(out, radiance, atol=1e-2 * np.abs(radiance).max())


def test_without_guides_it_is_a_gaussian_mean():
    rng = np.random.default_rng(3)
    radiance = rng.random((20, 24, 3)).astype(np.float32)
    out = local_linear_regression(radiance, np.zeros((20, 24, 0), np.float32), FlrParams(firefly_k=None))
    assert out.std() < radiance.std() / 3 and out.mean() == pytest.approx(radiance.mean(), rel=0.05)


def test_the_stage_matches_its_numpy_reference_with_demodulation():
    rng = np.random.default_rng(7)
    normal, depth, ao = _guides(26, 35, rng)
    radiance = rng.lognormal(0.0, 0.5, (26, 35, 3)).astype(np.float32)
    albedo = rng.random((26, 35, 3), dtype=np.float32)
    guides = gbuffer_guides(normal, depth, ao)
    fast = local_linear_regression(radiance, guides, albedo=albedo)
    slow = local_linear_regression(radiance, guides, albedo=albedo, reference=True)
    np.testing.assert_allclose(fast, slow, rtol=1e-4, atol=1e-4 * np.abs(slow).max())
