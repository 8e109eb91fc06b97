"""The noise clamp (service/stages/noise_clamp.py): parity with the numpy twin, the band it allows, exact
pixels unchanged, and what it leaves alone."""

import numpy as np
import pytest

from service.stages.noise_blend import firefly_clip
from service.stages.noise_clamp import NOISE_K, noise_clamp, noise_clamp_reference, noise_sd_reference


def _frame(rng, shape, sd=0.2):
    truth = rng.uniform(0.5, 2.0, shape).astype(np.float32)
    a = (truth + rng.normal(0, sd, shape)).astype(np.float32)
    b = (truth + rng.normal(0, sd, shape)).astype(np.float32)
    return truth, a, b, ((a + b) / 2).astype(np.float32)


@pytest.mark.parametrize("shape", [(1, 1, 3), (1, 5, 3), (3, 2, 3), (2, 7, 3), (41, 29, 3)])
def test_matches_the_numpy_twin(shape):
    rng = np.random.default_rng(0)
    _, a, b, color = _frame(rng, shape)
    exact = rng.random(shape[:2]) < 0.2
    b[exact] = a[exact]
    color = ((a + b) / 2).astype(np.float32)
    emission = np.where(rng.random(shape[:2])[..., None] < 0.3, color, 0.0).astype(np.float32)
    emission[0, 0] = 0.5 * color[0, 0]  # emission that disagrees with an exact pixel
    out = rng.uniform(-5, 5, shape).astype(np.float32)
    for given in (None, emission):
        np.testing.assert_allclose(noise_clamp(out, color, a, b, given),
                                   noise_clamp_reference(out, color, a, b, given), rtol=1e-6, atol=1e-6)


def test_band_is_k_standard_deviations_of_the_pixel_estimate():
    shape = (3, 3, 3)
    a = np.zeros(shape, np.float32)
    b = np.full(shape, 2.0, np.float32)  # (a - b)^2 / 4 = 1 everywhere: sd 1
    color = np.ones(shape, np.float32)
    out = np.full(shape, 100.0, np.float32)
    np.testing.assert_allclose(noise_clamp(out, color, a, b), 1.0 + NOISE_K)
    np.testing.assert_allclose(noise_clamp(-out, color, a, b), 1.0 - NOISE_K)
    inside = np.full(shape, 2.5, np.float32)
    np.testing.assert_array_equal(noise_clamp(inside, color, a, b), inside)  # within the band: unchanged


def test_exact_pixels_and_black_regions_come_out_as_they_went_in():
    rng = np.random.default_rng(1)
    _, a, b, color = _frame(rng, (12, 12, 3))
    a[5, 5] = b[5, 5] = color[5, 5] = 1000.0  # a light: exact
    a[:3, :3] = b[:3, :3] = color[:3, :3] = 0.0  # the reflection of a black void, both halves black
    out = noise_clamp(np.full_like(color, 7.0), color, a, b)
    assert (out[5, 5] == 1000.0).all()
    assert (out[:2, :2] == 0.0).all()  # its 3x3 neighbourhood is black too: sd 0
    assert not np.array_equal(out[8:, 8:], color[8:, 8:])  # noisy pixels move
    emission = np.zeros_like(color)
    emission[5, 5] = 400.0  # the renderer: only partly emitted, the halves agree by chance
    emission[0, 0] = 1.0  # emission: not clipped
    with_emission = noise_clamp(np.full_like(color, 7.0), color, a, b, emission)
    assert (with_emission[5, 5] == 7.0).all() and (with_emission[0, 0] == 7.0).all()
    np.testing.assert_allclose(with_emission, noise_clamp_reference(np.full_like(color, 7.0), color, a, b, emission),
                               rtol=1e-6)


def test_a_good_denoiser_is_rarely_clamped():
    rng = np.random.default_rng(2)
    truth, a, b, color = _frame(rng, (64, 64, 3))
    sd = noise_sd_reference(a, b)
    assert 0.05 < float(np.median(sd)) < 0.3  # sd of the mean of two halves: 0.2 / sqrt(2)
    out = noise_clamp(truth, color, a, b)
    assert np.mean(out != truth) < 0.01


def test_refuses_mismatched_shapes_and_negative_k():
    x = np.zeros((4, 4, 3), np.float32)
    with pytest.raises(ValueError, match="share one"):
        noise_clamp(x, x, x, x[:3])
    for k in (-1.0, np.inf):
        with pytest.raises(ValueError, match="k must be finite and >= 0"):
            noise_clamp(x, x, x, x, k=k)
    with pytest.raises(ValueError, match="share one"):
        noise_clamp(x, x, x, x, emission=x[:, :2])


@pytest.mark.parametrize("with_emission", [False, True])
@pytest.mark.parametrize("exact", [False, True])
def test_matches_the_twin_on_exact_pixels_emitters_and_repaired_colours(with_emission, exact):
    """Exact pixels (halves agree), emitters, and a black colour over agreeing halves (a NaN colour the
    frame repaired to 0): the twin's answer whether or not the frame has an emission layer. exact=False is
    only for frames without exact pixels, so it is compared where there are none."""
    rng = np.random.default_rng(7)
    a = rng.uniform(0.1, 1.0, (9, 11, 3)).astype(np.float32)
    b = rng.uniform(0.1, 1.0, (9, 11, 3)).astype(np.float32)
    color = np.float32(0.5) * (a + b)
    emission = np.zeros_like(a)
    if exact:
        b[2, 3] = a[2, 3]  # exact, all emission when there is a layer
        color[2, 3] = emission[2, 3] = a[2, 3]
        b[4, 5] = a[4, 5]  # halves agree, colour repaired to black
        color[4, 5] = 0.0
    emission[6, 7] = 0.3  # an emitter's edge: emission, halves that differ
    out = rng.uniform(0.0, 2.0, a.shape).astype(np.float32)
    given = emission if with_emission else None
    expected = noise_clamp_reference(out, color, a, b, given)
    result = noise_clamp(out, color, a, b, given, exact=exact or with_emission)
    np.testing.assert_allclose(result, expected, rtol=1e-6, atol=1e-6)  # the band's sum order: an ulp
    if exact:
        np.testing.assert_array_equal(result[4, 5], 0.0)  # exact: the input, a repaired black


def _box_beside_floor(rng, size=12):
    """A lit, noisy floor (normal +z, depth 4) with a column one pixel wide of a box's unlit side (normal -x,
    depth 3) at x = 6, every sample of it black, and the background (no hit) from x = 7 on."""
    shape = (size, size, 3)
    truth, a, b, color = _frame(rng, shape, sd=0.5)
    normal = np.zeros(shape, np.float32)
    normal[:, :6, 2] = 1.0
    normal[:, 6, 0] = -1.0
    depth = np.full((size, size, 1), 1e4, np.float32)
    depth[:, :6] = 4.0
    depth[:, 6] = 3.0
    for x in (a, b, color):
        x[:, 6:] = 0.0
    return a, b, color, normal, depth


@pytest.mark.parametrize("with_depth", [False, True])
def test_a_black_surface_beside_a_noisy_one_keeps_black(with_depth):
    a, b, color, normal, depth = _box_beside_floor(np.random.default_rng(2))
    depth = depth if with_depth else None
    bleed = color.copy()
    bleed[:, 6] = 0.1  # a filter's bleed from the lit floor onto the unlit side
    plain = noise_clamp(bleed, color, a, b)
    assert (plain[1:-1, 6] == 0.1).all()  # the floor's noise in the 3x3 window lets it through
    per_surface = noise_clamp(bleed, color, a, b, normal=normal, depth=depth)
    assert (per_surface[:, 6] == 0.0).all()
    np.testing.assert_array_equal(per_surface[:, :6], plain[:, :6])  # the noisy floor: as before
    np.testing.assert_allclose(per_surface, noise_clamp_reference(bleed, color, a, b, normal=normal, depth=depth),
                               rtol=1e-6, atol=1e-6)


def test_a_black_pixel_on_a_surface_whose_samples_differ_is_not_frozen():
    a, b, color, normal, depth = _box_beside_floor(np.random.default_rng(3))
    a[4, 2] = b[4, 2] = color[4, 2] = 0.0  # a floor pixel whose few samples all missed: its neighbours saw light
    out = np.full_like(color, 0.8)
    np.testing.assert_array_equal(noise_clamp(out, color, a, b, normal=normal, depth=depth)[4, 2],
                                  noise_clamp(out, color, a, b)[4, 2])
    assert (noise_clamp(out, color, a, b, normal=normal, depth=depth)[4, 2] > 0).all()


def test_depth_tells_surfaces_apart_that_normals_do_not():
    a, b, color, normal, depth = _box_beside_floor(np.random.default_rng(4))
    normal[:, 6] = normal[:, 5]  # the column faces up like the floor, but stands 1 unit nearer
    bleed = color.copy()
    bleed[:, 6] = 0.1
    assert (noise_clamp(bleed, color, a, b, normal=normal)[1:-1, 6] == 0.1).all()  # one surface by its normal
    assert (noise_clamp(bleed, color, a, b, normal=normal, depth=depth)[:, 6] == 0.0).all()


@pytest.mark.parametrize("shape", [(1, 1, 3), (1, 5, 3), (3, 2, 3), (41, 29, 3)])
def test_matches_the_numpy_twin_with_surfaces(shape):
    rng = np.random.default_rng(5)
    _, a, b, color = _frame(rng, shape)
    black = rng.random(shape[:2]) < 0.6  # regions of agreeing halves, across surfaces
    a[black] = b[black] = color[black] = 0.0
    normal = np.zeros(shape, np.float32)
    normal[..., 2] = 1.0
    normal[rng.random(shape[:2]) < 0.3] = (1.0, 0.0, 0.0)
    normal[rng.random(shape[:2]) < 0.2] = 0.0  # background
    depth = rng.choice(np.array([2.0, 2.1, 3.0], np.float32), shape[:2])[..., None]
    out = rng.uniform(-5, 5, shape).astype(np.float32)
    for d in (None, depth):
        np.testing.assert_allclose(noise_clamp(out, color, a, b, normal=normal, depth=d),
                                   noise_clamp_reference(out, color, a, b, normal=normal, depth=d),
                                   rtol=1e-6, atol=1e-6)


def test_refuses_a_gbuffer_of_another_size():
    x = np.ones((4, 4, 3), np.float32)
    with pytest.raises(ValueError, match="normal"):
        noise_clamp(x, x, x, x, normal=x[:3])
    with pytest.raises(ValueError, match="depth"):
        noise_clamp(x, x, x, x, normal=x, depth=x)


def test_a_channel_whose_halves_differ_on_the_surface_gets_a_band_the_others_none():
    a, b, color, normal, depth = _box_beside_floor(np.random.default_rng(6))
    b[3, 6, 2] = 0.5  # one sample of the unlit column found some blue: its halves differ in one channel
    color[3, 6] = (a[3, 6] + b[3, 6]) / 2
    bleed = color.copy()
    bleed[:, 6] = 0.1
    out = noise_clamp(bleed, color, a, b, normal=normal, depth=depth)
    assert (out[2:5, 6, 2] == 0.1).all()  # blue: the band of the column's own pixels (sd 0.25/sqrt(n)) holds 0.1
    assert (out[2:5, 6, :2] == color[2:5, 6, :2]).all() and (out[6:, 6] == 0.0).all()  # no band: the input
    np.testing.assert_allclose(out, noise_clamp_reference(bleed, color, a, b, normal=normal, depth=depth),
                               rtol=1e-6, atol=1e-6)


def test_a_bar_one_pixel_wide_takes_its_band_from_its_own_pixels():
    """A dark bar (radiance 0.1, halves within 0.02) in front of a noisy bright wall (sd 0.5): the wall's noise
    no longer widens the bar's band, so a filter's bleed of 1.0 from the wall is held near the bar's input."""
    rng = np.random.default_rng(9)
    a, b, color, normal, depth = _box_beside_floor(rng)
    normal[:, 7:] = normal[:, :5][:, :5]  # the floor continues behind the bar (no background)
    depth[:, 7:] = 4.0
    a[:, 6], b[:, 6] = 0.09, 0.11
    color[:, 6] = 0.1
    bleed = color.copy()
    bleed[:, 6] = 1.0
    window = noise_clamp(bleed, color, a, b)
    surface = noise_clamp(bleed, color, a, b, normal=normal, depth=depth)
    assert window[:, 6].mean() > 0.6  # the wall's noise lets most of the bleed through
    np.testing.assert_allclose(surface[:, 6], 0.1 + NOISE_K * 0.01, rtol=1e-5)  # sd of the bar: 0.02 / 2
    np.testing.assert_allclose(surface, noise_clamp_reference(bleed, color, a, b, normal=normal, depth=depth),
                               rtol=1e-6, atol=1e-6)


def test_emission_and_exact_pixels_keep_their_rules_on_a_quiet_surface():
    """A quiet pixel with emission keeps the output unclipped, an exact one its input; without exact pixels
    (exact=False: none in a frame without an emission layer) the quiet pixels still take their input."""
    a, b, color, normal, depth = _box_beside_floor(np.random.default_rng(8))
    bleed = color.copy()
    bleed[:, 6] = 0.1
    emission = np.zeros_like(color)
    emission[4, 6] = 0.05  # a dim emitter on the unlit side, its halves equal
    a[4, 6] = b[4, 6] = color[4, 6] = 0.05
    out = noise_clamp(bleed, color, a, b, emission, normal=normal, depth=depth)
    assert (out[4, 6] == 0.05).all()  # exact (all emission): as it came in
    emission[4, 6] = 0.02  # only part of it emitted: not exact, kept unclipped
    out = noise_clamp(bleed, color, a, b, emission, normal=normal, depth=depth)
    assert (out[4, 6] == 0.1).all() and (out[8:, 6] == 0.0).all()
    np.testing.assert_allclose(out, noise_clamp_reference(bleed, color, a, b, emission, normal=normal, depth=depth),
                               rtol=1e-6, atol=1e-6)
    a[4, 6] = b[4, 6] = color[4, 6] = 0.0
    assert (noise_clamp(bleed, color, a, b, exact=False, normal=normal, depth=depth)[:, 6] == 0.0).all()


def test_short_normals_of_one_direction_are_one_surface():
    """Normals averaged over a pixel's samples are shorter than 1: the test takes their directions."""
    a, b, color, normal, depth = _box_beside_floor(np.random.default_rng(9))
    a[4, 2] = b[4, 2] = color[4, 2] = 0.0  # a floor pixel whose samples all missed, its neighbours lit
    normal[:, :6] *= 0.9  # |n| = 0.9: a raw dot of 0.81 against its neighbours
    out = np.full_like(color, 0.8)
    assert (noise_clamp(out, color, a, b, normal=normal, depth=depth)[4, 2] > 0).all()  # not frozen
    np.testing.assert_allclose(noise_clamp(out, color, a, b, normal=normal, depth=depth),
                               noise_clamp_reference(out, color, a, b, normal=normal, depth=depth),
                               rtol=1e-6, atol=1e-6)


def test_depth_is_compared_relative_to_the_nearer_pixel():
    """A floor 10.5% deeper than the column beside it is another surface (relative to the floor's depth the
    difference would be 9.5%, within SURFACE_DEPTH), seen from either pixel: one surface relation both ways."""
    a, b, color, normal, depth = _box_beside_floor(np.random.default_rng(10))
    normal[:, 6] = normal[:, 5]
    depth[:, 6] = 4.0 / 1.105  # the column; the floor beside it 10.5% deeper than it
    bleed = color.copy()
    bleed[:, 6] = 0.1
    assert (noise_clamp(bleed, color, a, b, normal=normal, depth=depth)[:, 6] == 0.0).all()


@pytest.mark.parametrize("shape", [(1, 1, 3), (1, 7, 3), (7, 1, 3), (2, 2, 3), (13, 4, 3), (17, 23, 3)])
def test_surface_bands_match_the_twin_on_random_surfaces(shape):
    """Normals from a few directions (opposite, background, short), random depths, some agreeing halves and
    emission: the compiled links and band agree with the numpy twin, with and without depth."""
    rng = np.random.default_rng(11)
    directions = np.array([(0, 0, 1), (1, 0, 0), (0, 0, -1), (0.6, 0, 0.8), (0, 0, 0)], np.float32)
    for _ in range(5):
        _, a, b, color = _frame(rng, shape)
        agreeing = rng.random(shape[:2]) < 0.3
        b[agreeing] = a[agreeing]
        color = ((a + b) / 2).astype(np.float32)
        normal = directions[rng.integers(0, len(directions), shape[:2])] * rng.uniform(0.7, 1.0, (*shape[:2], 1))
        depth = rng.uniform(1.0, 1.3, (*shape[:2], 1)).astype(np.float32)
        emission = np.where(rng.random(shape[:2])[..., None] < 0.2, color, 0.0).astype(np.float32)
        out = rng.uniform(-5, 5, shape).astype(np.float32)
        for d in (None, depth):
            for e in (None, emission):
                np.testing.assert_allclose(
                    noise_clamp(out, color, a, b, e, normal=normal.astype(np.float32), depth=d),
                    noise_clamp_reference(out, color, a, b, e, normal=normal.astype(np.float32), depth=d),
                    rtol=1e-6, atol=1e-6)


def test_the_band_reaches_the_inputs_firefly_clip():
    """A firefly in both halves (both hit a bright path, its neighbours saw nothing: the halves differ too little
    to widen the band) does not hold a denoiser that removed it: the band reaches the input's firefly clip
    (`firefly_clip`), 0 here. Where the clip leaves the colour, nothing changes, nor where it lies far beyond the
    pixel's own spread (a glint both halves saw alike)."""
    a = np.zeros((9, 9, 3), np.float32)
    b = a.copy()
    a[4, 4], b[4, 4] = 420.0, 280.0  # colour 350; the 3x3 mean of (a - b)^2 / 4: 70^2 / 9
    color = np.float32(0.5) * (a + b)
    out = np.zeros_like(a)  # the denoiser removed it
    np.testing.assert_allclose(noise_clamp(out, color, a, b)[4, 4], 350.0 - NOISE_K * 70.0 / 3.0, rtol=1e-6)
    clipped, admitted = firefly_clip(color, a, b)
    np.testing.assert_array_equal(admitted, np.zeros_like(a))  # clipped to its neighbours' range; the rest as given
    np.testing.assert_array_equal(noise_clamp(out, color, a, b, admitted=admitted), out)
    a[4, 4], b[4, 4] = 1015.0, 1050.0  # a glint both samples saw: its clip (0) lies 1032 away, 59 of its spreads
    color = np.float32(0.5) * (a + b)
    admitted = firefly_clip(color, a, b)[1]
    np.testing.assert_array_equal(admitted[4, 4], color[4, 4])  # not admitted: the band alone holds
    np.testing.assert_array_equal(noise_clamp(out, color, a, b, admitted=admitted), noise_clamp(out, color, a, b))


@pytest.mark.parametrize("with_emission", [False, True])
def test_matches_the_twin_with_an_admitted_value(with_emission):
    rng = np.random.default_rng(11)
    a = rng.uniform(0.1, 1.0, (9, 11, 3)).astype(np.float32)
    b = rng.uniform(0.1, 1.0, (9, 11, 3)).astype(np.float32)
    a[3, 4] = 300.0  # a firefly in one half
    color = np.float32(0.5) * (a + b)
    emission = np.zeros_like(a)
    emission[6, 7] = 0.3
    given = emission if with_emission else None
    admitted = firefly_clip(color, a, b, given)[1]
    out = rng.uniform(0.0, 2.0, a.shape).astype(np.float32)
    np.testing.assert_allclose(noise_clamp(out, color, a, b, given, admitted=admitted),
                               noise_clamp_reference(out, color, a, b, given, admitted=admitted), rtol=1e-6, atol=1e-6)
    with pytest.raises(ValueError, match="share one"):
        noise_clamp(out, color, a, b, given, admitted=admitted[:, :2])
