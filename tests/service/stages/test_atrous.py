import numpy as np
import pytest

from service.stages.atrous import (
    B3_SPLINE,
    VARIANCE_EPS,
    AtrousParams,
    _pass_inputs,
    atrous,
    depth_gradient,
    edge_aware_filter,
    edge_aware_filter_numpy,
    edge_guides,
    luminance,
    prefilter_variance,
)
from tests.tolerances import FILTER_ATOL


def _guides(h, w, seed=0, background=False, length=1.0):
    rng = np.random.default_rng(seed)
    depth = (2 + rng.random((h, w, 1)) * 0.1 + np.linspace(0, 1, h)[:, None, None]).astype(np.float32)
    normal = np.tile(np.float32([0, 0, length]), (h, w, 1))
    normal[: h // 3] = np.float32([0, length, 0])
    if background:
        normal[-2:] = 0
    return edge_guides(depth, normal)


@pytest.mark.parametrize(
    "step, sigma_normal, squared, shape, length",
    [(1, 128.0, 3, (13, 17), 1.0), (2, 3.0, -1, (13, 17), 1.0), (4, 128.0, 0, (13, 17), 1.0),
     (1, 2048.0, 3, (9, 40), 1.0), (16, 1.0, 3, (40, 9), 1.0), (1, 128.0, 3, (1, 1), 1.0),
     (1, 128.0, 3, (13, 17), 3.0), (2, 3.0, -1, (13, 17), 1000.0)],  # normals longer than 1: cos held at 1
)
def test_compiled_pass_matches_numpy_reference(step, sigma_normal, squared, shape, length):
    rng = np.random.default_rng(1)
    h, w = shape
    guides = _guides(h, w, background=True, length=length)
    values = rng.random((h, w, 4), dtype=np.float32)
    lum = luminance(values[..., :3])
    phi = (0.1 + rng.random((h, w))).astype(np.float32)
    kernel = np.asarray(B3_SPLINE, np.float32)
    args = values, lum, phi, guides, kernel, step, 1.0, sigma_normal, squared
    out = edge_aware_filter(*args)
    assert np.isfinite(out).all()
    np.testing.assert_allclose(out, edge_aware_filter_numpy(*args), rtol=2e-5, atol=1e-6)


def test_constant_image_is_unchanged_and_variance_shrinks():
    h, w = 17, 31
    color = np.full((h, w, 3), 0.37, np.float32)
    variance = np.full((h, w), 0.5, np.float32)
    out, var, first = atrous(color, variance, _guides(h, w, background=True), AtrousParams())
    np.testing.assert_allclose(out, 0.37, atol=FILTER_ATOL)
    np.testing.assert_allclose(first, 0.37, atol=FILTER_ATOL)
    assert np.all(var <= 0.5 + 1e-6) and var.mean() < 0.5


def test_depth_gradient_ignores_silhouettes():
    depth = np.ones((4, 6), np.float32)
    depth[:, 3:] = 10.0  # a step: either side is flat
    grad = depth_gradient(depth)
    assert grad.max() < 1e-6
    ramp = np.tile(np.arange(6, dtype=np.float32) * 0.5, (4, 1))
    np.testing.assert_allclose(depth_gradient(ramp), 0.5)


def test_prefilter_is_normalised_at_borders():
    np.testing.assert_allclose(prefilter_variance(np.full((3, 4), 2.0, np.float32)), 2.0, rtol=1e-6)


@pytest.mark.parametrize("shape", [(1, 1), (2, 7), (13, 17)])
def test_compiled_pass_inputs_match_luminance_and_prefilter(shape):
    rng = np.random.default_rng(6)
    planes = rng.random((4, *shape), dtype=np.float32)
    lum, phi = _pass_inputs(planes, np.float32(4.0))
    np.testing.assert_allclose(lum, luminance(np.moveaxis(planes[:3], 0, -1)), rtol=1e-6, atol=1e-7)
    expected = 4.0 * np.sqrt(np.maximum(prefilter_variance(planes[3]), 0) + np.float32(VARIANCE_EPS))
    np.testing.assert_allclose(phi, expected, rtol=1e-6)


def test_firefly_stays_within_the_filter_reach():
    h, w = 80, 80
    color = np.full((h, w, 3), 0.5, np.float32)
    color[40, 40] = 1e6
    variance = np.full((h, w), 1e12, np.float32)
    variance[40, 40] = 1e12
    params = AtrousParams(iterations=3)  # reach 2 * (1 + 2 + 4) = 14 pixels
    out, var, _ = atrous(color, variance, _guides(h, w), params)
    assert np.isfinite(out).all() and np.isfinite(var).all()
    changed = np.argwhere(np.abs(out - 0.5).max(axis=-1) > 1e-3)
    assert np.abs(changed - 40).max() <= 14
    assert out.max() <= 1e6


@pytest.mark.parametrize("shape", [(1, 1), (3, 5), (17, 31)])
def test_tiny_sizes_negative_radiance_and_float16(shape):
    h, w = shape
    rng = np.random.default_rng(4)
    color = rng.normal(size=(h, w, 3)).astype(np.float16).astype(np.float32)
    variance = rng.random((h, w)).astype(np.float16).astype(np.float32)
    out, var, first = atrous(color, variance, _guides(h, w), AtrousParams())
    assert out.shape == color.shape and np.isfinite(out).all() and np.all(var >= 0)
    assert out.min() >= color.min() - 1e-5 and out.max() <= color.max() + 1e-5


def test_invalid_params_are_refused():
    with pytest.raises(ValueError, match="sigma_luminance"):
        AtrousParams(sigma_luminance=0)
