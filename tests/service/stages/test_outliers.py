"""clamp_outliers (service/stages/outliers.py): a firefly and a small cluster are clipped, a constant image,
a smooth gradient and an edge are not; with the halves, what both show is kept."""

import numpy as np
import pytest

from service.regression.planes import from_planes, to_planes
from service.stages.albedo import ALBEDO_EPS, demodulate, remodulate
from service.stages.outliers import ROBUST_RADIUS, clamp_outlier_planes, clamp_outliers
from service.stages.svgf import box_mean


def test_firefly_and_small_cluster_are_clipped():
    image = np.ones((32, 32, 3), np.float32)
    image[5, 5] = 1000.0
    image[20:22, 20:22] = 500.0  # a 2x2 cluster: the 3x3 clamp alone cannot see it
    out = clamp_outliers(image)
    assert out[5, 5].max() < 10.0 and out[20:22, 20:22].max() < 10.0
    np.testing.assert_array_equal(out[:3, :3], image[:3, :3])


def test_constant_gradient_and_edge_are_unchanged():
    constant = np.full((17, 23, 3), 0.7, np.float32)
    np.testing.assert_array_equal(clamp_outliers(constant), constant)
    ramp = np.broadcast_to(np.linspace(0.1, 2.0, 23, dtype=np.float32)[None, :, None], (17, 23, 3)).copy()
    np.testing.assert_allclose(clamp_outliers(ramp), ramp, rtol=1e-6)
    edge = np.ones((17, 23, 3), np.float32)
    edge[:, 12:] = 50.0  # half the frame: signal, not an outlier
    np.testing.assert_array_equal(clamp_outliers(edge), edge)


def test_with_the_halves_a_glint_both_show_survives_and_a_one_half_firefly_does_not():
    """At 2 samples per half: a glint of 400 is seen by a sample of each half (A 300, B 500); a firefly of 2000
    by one sample of one half (A 1, B 4000). The glint comes back at min(A, B), never above the image."""
    a = np.ones((32, 32, 3), np.float32)
    b = a.copy()
    a[5, 5], b[5, 5] = 300.0, 500.0  # a glint
    b[20, 20] = 4000.0  # a firefly
    image = (a + b) / 2
    plain = clamp_outliers(image)
    assert plain[5, 5].max() < 10.0 and plain[20, 20].max() < 10.0  # both clipped without the halves
    out = clamp_outliers(image, halves=(a, b))
    np.testing.assert_array_equal(out[5, 5], [300.0] * 3)
    np.testing.assert_array_equal(out[20, 20], plain[20, 20])
    mask = np.ones((32, 32), bool)
    mask[5, 5] = False
    np.testing.assert_array_equal(out[mask], plain[mask])  # elsewhere as without them
    assert (out <= image).all()
    lower = image.copy()
    lower[5, 5] = 100.0  # an image below what both halves show there (the caller's rounding): never above it
    np.testing.assert_array_equal(clamp_outliers(lower, halves=(a, b))[5, 5], [100.0] * 3)


def test_halves_of_another_shape_are_refused():
    image = np.ones((8, 8, 3), np.float32)
    with pytest.raises(ValueError, match="halves"):
        clamp_outliers(image, halves=(image, image[:4]))


def test_with_the_albedo_a_bright_texel_is_texture_and_an_edge_firefly_is_clipped():
    """Under an irradiance of about 1 (a gentle ramp), one texel of albedo 0.9 among texels of 0.05: its radiance
    is 15 times its neighbours', texture that the albedo shows, kept bit for bit; without the albedo, clipped.
    A silhouette's edge: a row the surface covers a tenth of (albedo 0.075, radiance 0.1) between a lit floor
    (albedo 0.75, radiance 1) and the void (0); one sample there hit a firefly of 2.5. Against its radiance
    neighbours (0 to 1, bound 3) it is no outlier; against their irradiance (0 to 1.3, its own 29) it is."""
    albedo = np.full((16, 16, 3), 0.05, np.float32)
    albedo[8, 8] = 0.9
    irradiance = np.linspace(1.0, 1.2, 16, dtype=np.float32)[None, :, None]
    image = ((albedo + ALBEDO_EPS) * irradiance).astype(np.float32)
    assert clamp_outliers(image)[8, 8].max() < 0.1
    np.testing.assert_array_equal(clamp_outliers(image, albedo=albedo), image)
    albedo = np.zeros((16, 16, 3), np.float32)
    albedo[:8], albedo[8] = 0.75, 0.075
    image = np.zeros((16, 16, 3), np.float32)
    image[:8], image[8] = 1.0, 0.1
    image[8, 8] = 2.5
    np.testing.assert_array_equal(clamp_outliers(image)[8, 8], image[8, 8])
    out = clamp_outliers(image, albedo=albedo)
    assert out[8, 8].max() < 0.5 and (out[8, 8] >= 0.1).all()
    mask = np.ones((16, 16), bool)
    mask[8, 8] = False
    np.testing.assert_array_equal(out[mask], image[mask])


def test_with_the_albedo_no_value_is_raised_near_a_sky_the_radiance_judges_and_shapes_are_checked():
    """A dark pixel among surfaces (albedo 0.9, radiance 0.1 among albedo 0.5, radiance 1): a dark outlier of
    their irradiance, kept (the radiance clamp raises it). A surface pixel (albedo 0.8, radiance 0.3) among sky
    pixels (albedo 0, radiance about 1): near a sky every pixel is judged on its radiance, as without the
    albedo (against the sky's unscaled radiance, demodulated, it would be raised to a firefly of ~60). A
    silhouette column (albedo 0.1, radiance 0.9, most of it the sky's) between a sky and a surface keeps its
    value, as does a sky pixel seen through a gap among surfaces. Beside the black void (albedo 0, radiance 0)
    the albedo still judges: the firefly at the floor's edge in the test above."""
    shade = np.ones((9, 9, 3), np.float32)
    surfaces = np.full((9, 9, 3), 0.5, np.float32)
    shade[4, 4], surfaces[4, 4] = 0.1, 0.9
    assert clamp_outliers(shade)[4, 4].min() > 0.5
    np.testing.assert_array_equal(clamp_outliers(shade, albedo=surfaces), shade)
    rng = np.random.default_rng(0)
    image = (1.0 + 0.1 * rng.random((9, 9, 3))).astype(np.float32)
    albedo = np.zeros((9, 9, 3), np.float32)
    image[4, 4], albedo[4, 4] = 0.3, 0.8
    out = clamp_outliers(image, albedo=albedo)
    np.testing.assert_array_equal(out, clamp_outliers(image))
    assert out.max() <= image.max()
    noise = 1.0 + 0.05 * rng.standard_normal((24, 24, 3))
    columns = np.arange(24)[None, :, None]
    image = np.where(columns < 12, noise, 0.5 * noise).astype(np.float32)  # a sky left, a surface right
    albedo = np.where(columns < 12, 0.0, 0.5) * np.ones((24, 24, 3), np.float32)
    image[:, 12], albedo[:, 12] = 0.9, 0.1  # the silhouette, 20% covered
    np.testing.assert_array_equal(clamp_outliers(image, albedo=albedo.astype(np.float32))[:, 12], image[:, 12])
    surfaces = np.full((9, 9, 3), 0.8, np.float32)
    surfaces[4, 4] = 0.0
    constant = np.full((9, 9, 3), 1.05, np.float32)  # a sky pixel seen through a gap
    np.testing.assert_array_equal(clamp_outliers(constant, albedo=surfaces), constant)
    with pytest.raises(ValueError, match="albedo"):
        clamp_outliers(constant, albedo=surfaces[:4])


def test_with_the_albedo_matches_the_numpy_composition_bit_for_bit():
    """The compiled demodulation, sky test and remodulation against the same steps in numpy (`albedo.demodulate`,
    `remodulate`, the planes through `clamp_outlier_planes`), on a frame with fireflies, a sky of albedo 0, black
    paint, negative albedo and a NaN."""
    rng = np.random.default_rng(3)
    image = rng.gamma(1.0, 1.0, (24, 31, 3)).astype(np.float32)
    image[rng.random((24, 31)) < 0.03] *= 200.0  # fireflies
    albedo = rng.uniform(0.0, 1.0, (24, 31, 3)).astype(np.float32)
    albedo[:5, :9] = 0.0  # a sky: radiance without albedo
    albedo[20:, 20:] = 0.0
    image[20:, 20:] = 0.0  # black paint showing no light
    albedo[10, 10] = -0.5
    image[12, 3, 1] = np.nan
    flat = demodulate(image, albedo)
    kept = from_planes(clamp_outlier_planes(to_planes(flat)))
    back = remodulate(kept, albedo)
    lowered = ((kept != flat) & (np.abs(back) < np.abs(image))) | np.isnan(image)
    want = np.where(lowered, back, image).astype(np.float32)
    sky = (albedo < ALBEDO_EPS).all(axis=-1) & (image != 0).any(axis=-1)
    near = box_mean(sky[..., None].astype(np.float32), ROBUST_RADIUS) > 0
    want = np.where(near, from_planes(clamp_outlier_planes(to_planes(image))), want)
    np.testing.assert_array_equal(clamp_outliers(image, albedo=albedo), want)
