import numpy as np
import pytest

from service.stages.bmfr import BmfrParams, bmfr, gbuffer_features, gbuffer_features_reference


def _scene(height, width, rng):
    y, x = np.mgrid[0:height, 0:width].astype(np.float32)
    albedo = (0.4 + 0.3 * np.sin(x / 3.0)[..., None] * np.float32([1.0, 0.5, -0.5])).astype(np.float32)
    normal = np.stack([np.sin(y / 9.0), np.cos(y / 9.0), 0.1 * np.ones_like(y)], axis=-1).astype(np.float32)
    depth = (3.0 + x / width + rng.random((height, width)) * 0.5)[..., None].astype(np.float32)
    return albedo, normal, depth


def test_features_are_standardised_planes():
    rng = np.random.default_rng(0)
    albedo, normal, depth = _scene(12, 15, rng)
    features = gbuffer_features(albedo, normal, depth)
    assert features.shape == (9, 12, 15) and features.dtype == np.float32
    assert gbuffer_features(albedo, normal).shape == (8, 12, 15)
    np.testing.assert_allclose(features.reshape(9, -1).mean(axis=1), 0.0, atol=1e-5)
    for layers in ((albedo, normal, depth), (albedo, normal)):
        np.testing.assert_allclose(gbuffer_features(*layers), gbuffer_features_reference(*layers), rtol=1e-5, atol=1e-5)


def test_params_are_validated():
    with pytest.raises(ValueError, match="odd"):
        BmfrParams(window=10)


def test_numba_matches_the_numpy_reference():
    rng = np.random.default_rng(1)
    albedo, normal, depth = _scene(23, 30, rng)
    color = rng.lognormal(0.0, 0.8, (23, 30, 3)).astype(np.float32)
    fast = bmfr(color, albedo, normal, depth)
    slow = bmfr(color, albedo, normal, depth, reference=True)
    np.testing.assert_allclose(fast, slow, rtol=1e-3, atol=1e-3 * np.abs(slow).max())


def test_radiance_linear_in_the_features_is_reproduced_in_the_interior():
    rng = np.random.default_rng(2)
    albedo, normal, depth = _scene(40, 48, rng)
    y, x = np.mgrid[0:40, 0:48].astype(np.float32)
    irradiance = 1.0 + normal @ np.float32([0.3, -0.2, 0.5]) + 0.4 * np.log(depth[..., 0]) + 0.01 * x - 0.005 * y
    color = (albedo + 0.01) * irradiance[..., None]  # demodulation divides by albedo + 0.01
    out = bmfr(color, albedo, normal, depth, BmfrParams(firefly_k=None))
    inner = (slice(6, -6), slice(6, -6))
    np.testing.assert_allclose(out[inner], color[inner], rtol=5e-3, atol=5e-3)


@pytest.mark.parametrize("stage", ["bmfr", "flr"])
def test_a_cluster_of_fireflies_leaves_the_output_better_than_the_input(stage):
    """The `fireflies` bench failure: a 3x3 group at 1e3 on a dim smooth background was spread over the
    regression window, making the output many times worse than the noisy input."""
    from service.metrics import rel_l2
    from service.stages.flr import FlrParams, gbuffer_guides, local_linear_regression

    rng = np.random.default_rng(5)
    height, width = 48, 56
    clean = np.broadcast_to(np.linspace(0.5, 1.0, width, dtype=np.float32)[:, None], (height, width, 3)).copy()
    noisy = clean * rng.gamma(4.0, 0.25, clean.shape).astype(np.float32)
    noisy[22:25, 26:29] = 1e3
    albedo = np.ones_like(clean)
    normal = np.broadcast_to(np.array([0, 0, 1], np.float32), clean.shape).copy()
    if stage == "bmfr":
        out = bmfr(noisy, albedo, normal, None, BmfrParams())
        off = bmfr(noisy, albedo, normal, None, BmfrParams(robust_clamp=False))
    else:
        out = local_linear_regression(noisy, gbuffer_guides(normal), FlrParams())
        off = local_linear_regression(noisy, gbuffer_guides(normal), FlrParams(robust_clamp=False))
    # Trimmed (0.5%: the 9 cluster pixels of 2688) as in the benchmark: the error away from the cluster.
    noisy_error = rel_l2(noisy, clean, trim=0.005)
    assert rel_l2(off, clean, trim=0.005) > noisy_error  # the failure, without the cluster clamp
    assert rel_l2(out, clean, trim=0.005) < 0.5 * noisy_error
