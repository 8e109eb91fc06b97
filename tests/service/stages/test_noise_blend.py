"""The noise blend (service/stages/noise_blend.py): parity with the numpy twin, the weight it derives
(analytic cases), invariants, and that the blend beats both its inputs where the halves can tell."""

import numpy as np
import pytest

from service.metrics import rel_l2_map
from service.stages.blend_sums import level_kernel
from service.stages.error_estimate import interpolation_matrix
from service.stages.noise_blend import (
    ADMIT_K,
    LEVEL_RADIUS,
    TILE,
    _interpolation,
    blend_weights,
    firefly_clip,
    firefly_clip_reference,
    noise_blend,
    noise_blend_reference,
)
from service.stages.svgf import box_mean


def _halves(rng, truth, sd):
    a = (truth + rng.normal(0, sd, truth.shape)).astype(np.float32)
    b = (truth + rng.normal(0, sd, truth.shape)).astype(np.float32)
    return a, b, ((a + b) / 2).astype(np.float32)


@pytest.mark.parametrize("tile", [16, 7, 2, 1])  # pooled, two passes, pooled to 1, one size
@pytest.mark.parametrize("shape", [(1, 1, 3), (1, 37, 3), (37, 1, 3), (3, 2, 3), (16, 16, 3), (17, 33, 3),
                                   (41, 29, 3), (70, 9, 3)])
def test_matches_the_numpy_twin(shape, tile):
    rng = np.random.default_rng(0)
    truth = rng.uniform(0.0, 2.0, shape).astype(np.float32)
    a, b, color = _halves(rng, truth, 0.3)
    a[0, 0] *= 1e3  # a firefly
    color = ((a + b) / 2).astype(np.float32)
    out = (truth + rng.normal(0, 0.05, shape)).astype(np.float32)
    out[: shape[0] // 2, : shape[1] // 2] += 2.0  # a region the denoiser got wrong
    emission = np.where(rng.random(shape[:2])[..., None] < 0.2, np.float32(30.0), np.zeros(shape, np.float32))
    for given in (None, emission):
        shift = 0 if given is None else given
        arrays = [x + shift for x in (out, color, a, b)]
        np.testing.assert_allclose(noise_blend(*arrays, given, tile), noise_blend_reference(*arrays, given, tile),
                                   rtol=1e-4, atol=1e-4)
    whole = (emission != 0) & (np.arange(shape[1])[None, :, None] % 2 == 0)  # every other column's lights
    seen_whole = [np.where(whole, emission, x + shift) for x, shift in zip((out, color, a, b), [emission] * 4,
                                                                         strict=True)]  # beside other lights
    np.testing.assert_allclose(noise_blend(*seen_whole, emission, tile),
                               noise_blend_reference(*seen_whole, emission, tile), rtol=1e-4, atol=1e-4)


def test_radiance_up_to_float32s_largest_stays_finite():
    """Values near 3.4e38 (finite float32): every sum runs in float64 and the blend stays in range; a 1e20
    at a row's start does not spoil the level of the rest of the row."""
    rng = np.random.default_rng(7)
    shape = (20, 24, 3)
    huge = np.float32(3.3e38)
    a = rng.uniform(0, 1, shape).astype(np.float32)
    b = rng.uniform(0, 1, shape).astype(np.float32)
    a[3, 4], b[3, 5], a[0, 0] = huge, -huge, 1e20
    color = ((a.astype(np.float64) + b) / 2).astype(np.float32)
    out = np.full(shape, 0.5, np.float32)
    out[3, 5] = huge
    emission = np.zeros(shape, np.float32)
    emission[10, 10] = huge
    for given in (None, emission):  # (the tile sums cancel at 1e38: finite, but no twin to match there)
        assert np.isfinite(noise_blend(out, color, a, b, given)).all()
        with np.errstate(over="ignore", invalid="ignore"):  # the twin's float32 sums overflow to +-inf there
            assert np.isfinite(noise_blend_reference(out, color, a, b, given)).all()
    level = np.empty(shape[:2], np.float32)
    level_kernel(color, color, False, LEVEL_RADIUS, level)
    with np.errstate(over="ignore", invalid="ignore"):  # float32 sums around 3.3e38: inf there, unused below
        expected = box_mean(color.mean(axis=-1, keepdims=True), LEVEL_RADIUS)[..., 0]
    np.testing.assert_allclose(level[6:, :], expected[6:, :], rtol=1e-5)  # rows the huge values do not reach
    np.testing.assert_allclose(level[0, 3:], expected[0, 3:], rtol=1e-5)  # the 1e20 at (0, 0) stays local


def test_an_emitter_keeps_the_output():
    """A 1-pixel light (emission 100) on a brighter noisy wall: the blend neither clips it nor takes any of
    the input back there, as the noise clamp leaves pixels with emission."""
    rng = np.random.default_rng(8)
    wall = np.full((16, 16, 3), 10.0, np.float32)
    a, b, color = _halves(rng, wall, 2.0)
    emission = np.zeros_like(wall)
    emission[8, 8] = 100.0
    a, b, color = a + emission, b + emission, color + emission
    out = wall + emission + np.float32(0.2)
    blended = noise_blend(out, color, a, b, emission)
    np.testing.assert_array_equal(blended[8, 8], out[8, 8])


def test_emission_is_left_out_and_added_back():
    """The blend of radiance + emission, told the emission, is the blend of the radiance plus the emission
    (a light is no level for its neighbours' weights); the emitter's own pixels keep the output."""
    rng = np.random.default_rng(6)
    truth = rng.uniform(0.2, 1.0, (40, 40, 3)).astype(np.float32)
    a, b, color = _halves(rng, truth, 0.3)
    out = (truth * 0.8).astype(np.float32)
    emission = np.zeros_like(truth)
    emission[10:14, 20:30] = 500.0
    plain = noise_blend(out, color, a, b)
    lit = noise_blend(out + emission, color + emission, a + emission, b + emission, emission)
    emitted = (emission != 0).any(axis=-1)
    np.testing.assert_allclose(lit[~emitted], plain[~emitted] + emission[~emitted], rtol=1e-5, atol=1e-4)
    np.testing.assert_array_equal(lit[emitted], (out + emission)[emitted])  # the emitter keeps the output


def test_weight_is_the_estimated_optimum():
    assert blend_weights(np.array([[0.0, 1.0, 3.0, -2.0, 0.0]]), np.array([[1.0, 1.0, 1.0, 1.0, 0.0]])).tolist() == \
        [[1.0, 0.5, 0.25, 1.0, 1.0]]  # Eo <= 0: keep the output; both 0: keep it
    assert blend_weights(np.array([[2.0]]), np.array([[0.0]])).tolist() == [[0.0]]  # no noise: the input is right


def test_one_tile_takes_the_analytic_weight():
    """One tile, a constant truth of 1: v = 1/4 everywhere (halves 1 -+ 1/2... a mean of 1), o = c + 1, so per
    pixel e = 1 - v: t = v / (1 - v + v) = 1/4."""
    shape = (TILE, TILE, 3)
    a, b = np.full(shape, 0.5, np.float32), np.full(shape, 1.5, np.float32)
    color = np.ones(shape, np.float32)
    out = color + 1.0
    np.testing.assert_allclose(noise_blend(out, color, a, b), 1.25, rtol=1e-6)


def test_constant_and_noise_free_frames_are_unchanged():
    shape = (40, 50, 3)
    constant = np.full(shape, 0.7, np.float32)
    halves = constant - np.float32(0.1), constant + np.float32(0.1)  # noisy halves, a denoiser that is right
    np.testing.assert_allclose(noise_blend(constant + np.float32(1e-3), constant, *halves), 0.7 + 1e-3, rtol=1e-6)
    # halves that agree: the renderer resolved every pixel, and a denoiser that moved them is undone
    rng = np.random.default_rng(2)
    exact = rng.uniform(0, 5, shape).astype(np.float32)
    moved = exact + np.float32(0.3)
    np.testing.assert_array_equal(noise_blend(moved, exact, exact, exact), exact)


def test_interpolation_tables_match_the_matrix():
    for size, tile in ((1, 16), (15, 16), (16, 16), (40, 16), (100, 7)):
        first, second, weight = _interpolation(size, tile)
        matrix = np.zeros((size, -(-size // tile)))
        np.add.at(matrix, (np.arange(size), first), 1 - weight)
        np.add.at(matrix, (np.arange(size), second), weight)
        np.testing.assert_allclose(matrix, interpolation_matrix(size, tile), atol=1e-7)


def _tile_errors(image, truth):
    errors = rel_l2_map(image, truth)
    h, w = (s // TILE * TILE for s in errors.shape)
    return errors[:h, :w].reshape(h // TILE, TILE, w // TILE, TILE).mean(axis=(1, 3))


def test_a_ring_goes_back_to_the_input_and_a_good_output_stays():
    """A dark region (truth 0.02) that the denoiser lifted to 1 (a shadow blurred with its lit surround) goes
    back to the input where the interpolation does not reach across its edge (its centre tile); the tiles
    it got right keep the output, and every tile ends far better than the denoiser left it."""
    rng = np.random.default_rng(3)
    truth = np.ones((96, 96, 3), np.float32)
    truth[16:64, 16:64] = 0.02
    a, b, color = _halves(rng, truth, 0.3 * truth + 0.01)
    out = (truth + rng.normal(0, 0.02, truth.shape) * truth).astype(np.float32)
    out[16:64, 16:64] = 1.0
    blended = noise_blend(out, color, a, b)
    before, noisy, after = (_tile_errors(x, truth) for x in (out, color, blended))
    assert before[2, 2] > 100 * noisy[2, 2]  # the denoiser's ring
    assert after[2, 2] < 1.1 * noisy[2, 2]
    assert (after[1:4, 1:4] < 0.5 * before[1:4, 1:4]).all()
    assert (after[5, :] < 0.5 * noisy[5, :]).all()  # tiles far from it keep the denoised output


def test_fireflies_are_not_taken_back_and_an_unchanged_value_stays():
    """Where the blend takes part of the input back, a firefly (one half) is clipped to its neighbours; a
    value the denoiser left as it came stays exactly so, even where the clip would move it (the step's
    noise clamp leaves exact pixels so)."""
    truth = np.full((32, 32, 3), 0.5, np.float32)
    rng = np.random.default_rng(5)
    a, b, color = _halves(rng, truth, 0.2)
    a[8, 8] += 1000.0  # a firefly in half A
    a[20, 20] += 1000.0  # another, which the denoiser passed through
    color = ((a + b) / 2).astype(np.float32)
    out = np.full_like(truth, 0.8)  # biased: the blend takes a good part of the input back
    out[20, 20] = color[20, 20]
    blended = noise_blend(out, color, a, b)
    assert blended[8, 8].max() < 2.0
    np.testing.assert_array_equal(blended[20, 20], color[20, 20])


def test_the_blend_beats_both_where_the_denoiser_is_biased():
    """A denoiser that is too smooth (a uniform 10% bias) on a noisy frame: the blend's relL2 is below both."""
    rng = np.random.default_rng(4)
    y, x = np.mgrid[:96, :96]
    truth = (0.2 + (np.sin(x / 5.0) * np.cos(y / 7.0)) ** 2)[..., None].repeat(3, -1).astype(np.float32)
    a, b, color = _halves(rng, truth, 0.15)
    out = (truth * 0.9).astype(np.float32)
    blended = noise_blend(out, color, a, b)
    err = {name: float(rel_l2_map(v, truth).mean()) for name, v in (("out", out), ("in", color), ("blend", blended))}
    assert err["blend"] < min(err["out"], err["in"]), err


def test_shapes_must_agree():
    x = np.zeros((4, 4, 3), np.float32)
    with pytest.raises(ValueError, match="share one"):
        noise_blend(x, x, x, np.zeros((4, 5, 3), np.float32))
    with pytest.raises(ValueError, match="tile must be >= 1"):
        noise_blend(x, x, x, x, tile=0)
    with pytest.raises(ValueError, match="share one"):
        noise_blend(x, x, x, x, np.zeros((4, 4, 1), np.float32))


def _sparse_frame(rng, p, shape=(128, 128, 3)):
    """One sample per half of a 0/1 signal that is 1 with probability p: most pixels' halves both black."""
    a = (rng.random(shape[:2]) < p).astype(np.float32)[..., None].repeat(3, -1)
    b = (rng.random(shape[:2]) < p).astype(np.float32)[..., None].repeat(3, -1)
    return a, b, ((a + b) / 2).astype(np.float32)


@pytest.mark.parametrize("p", [0.01, 0.03])
def test_a_good_output_on_a_dim_sparse_frame_is_kept(p):
    """Where both halves of most pixels saw nothing, a half tile's Ec is ~0 because the samples are few: it
    must not pull an output within 10% of the truth back to the black input (NOISY_SHARE)."""
    rng = np.random.default_rng(11)
    truth = np.full((128, 128, 3), p, np.float32)
    a, b, color = _sparse_frame(rng, p)
    out = (truth * (1 + 0.1 * rng.standard_normal(truth.shape[:2]))[..., None]).astype(np.float32)
    blended = noise_blend(out, color, a, b)
    err = {name: float(rel_l2_map(v, truth).mean()) for name, v in (("out", out), ("in", color), ("blend", blended))}
    assert err["blend"] < 0.01 and err["in"] > 0.4, err  # without NOISY_SHARE 0.015 and 0.017
    assert float(blended.mean()) > 0.95 * p  # not pulled toward black (0.73 p at p = 0.01 without it)


def test_a_small_wrong_region_inside_a_good_tile_goes_back_by_its_half_tile(monkeypatch):
    """An 8x8 region the denoiser lifted (truth 0.05, output 1) inside a 16x16 tile it got right elsewhere:
    the tile's weight alone keeps much of the output there, its half tile's takes the input back, and the
    tiles far from it keep the output."""
    from service.stages import noise_blend as module

    rng = np.random.default_rng(12)
    truth = np.ones((64, 64, 3), np.float32)
    truth[24:32, 24:32] = 0.05
    a, b, color = _halves(rng, truth, 0.5 * truth + 0.02)
    out = truth.copy()
    out[24:32, 24:32] = 1.0
    blended = noise_blend(out, color, a, b)
    monkeypatch.setattr(module, "WORSE", 0.0)  # no half tile overrides
    tile_only = noise_blend(out, color, a, b)
    region = (slice(24, 32), slice(24, 32))
    before, alone, after = (float(rel_l2_map(x, truth)[region].mean()) for x in (out, tile_only, blended))
    assert after < 0.75 * alone and alone < 0.5 * before, (before, alone, after)
    assert float(rel_l2_map(blended, truth)[:, 48:].mean()) < 0.1 * float(rel_l2_map(color, truth)[:, 48:].mean())


def test_pixels_darkened_to_zero_do_not_hide_a_row_lifted_beside_a_window(monkeypatch):
    """The top-left tile of a 32x32 frame: a dim room under a window (1000 in both halves), where 15% of the
    pixels have one bright half (a sky sample; the truth is their mean, 3.75) and the output darkened those
    to 0, while it lifted the row under the window to 200. With the stand-in level at least PROXY_FLOOR of
    the box mean the lifted row weighs as it should and the blend takes it back; without it each darkened
    pixel weighs 1 / REL_L2_EPS and the tile keeps the lifted row. The tile far from it keeps the output."""
    from service.stages import dark_tiles
    from service.stages import noise_blend as module

    rng = np.random.default_rng(0)
    truth = np.full((32, 32, 3), 10.0, np.float32)
    truth[:16, :16] = 3.75
    truth[:3, :16] = 1000.0
    a = (truth + rng.normal(0, 2, truth.shape)).astype(np.float32)
    b = (truth + rng.normal(0, 2, truth.shape)).astype(np.float32)
    a[:3, :16] = b[:3, :16] = 1000.0
    a[3:16, :16] = b[3:16, :16] = 0.0
    hits = [(y, x) for y in range(4, 16) for x in range(16) if rng.random() < 0.15]
    for i, (y, x) in enumerate(hits):
        (a if i % 2 else b)[y, x] = rng.uniform(20, 80)
    color = (a + b) / 2
    out = truth.copy()
    out[3, :16] = 200.0
    for y, x in hits:
        out[y, x] = 0.0
    np.testing.assert_allclose(noise_blend(out, color, a, b), noise_blend_reference(out, color, a, b), rtol=1e-5,
                               atol=1e-6)
    monkeypatch.setattr(dark_tiles, "EVIDENCE", np.inf)  # the floor alone (the room's dark pixels refute the row too)
    blended = noise_blend(out, color, a, b)
    monkeypatch.setattr(module, "PROXY_FLOOR", 0.0)
    unfloored = noise_blend(out, color, a, b)
    row = (slice(3, 4), slice(0, 16))
    assert float(blended[row].mean()) < 100.0 and float(unfloored[row].mean()) > 150.0  # (the next tile keeps it)
    room = (slice(3, 16), slice(0, 16))
    assert float(rel_l2_map(blended, truth)[room].mean()) < 0.25 * float(rel_l2_map(unfloored, truth)[room].mean())
    far = (slice(20, 32), slice(20, 32))
    assert float(rel_l2_map(blended, out)[far].mean()) < 0.01 * float(rel_l2_map(color, truth)[far].mean())


def test_a_rejected_half_tile_holds_its_weight_over_its_own_pixels():
    """A denoiser wrong on one grid-aligned 8x8 half tile only (lifted by 4 where the truth is 1): its weight w
    holds over the half tile's inner pixels (one value, near 0), its edge pixel beside a neighbour of weight
    1 takes (2 w + 1) / 3 and the pixel beyond at most (w + 2) / 3 (the 3-pixel ramp; the tiles' own
    interpolated weight may be lower there), and far off the output is kept. Interpolated between half-tile
    centres, as before, the inner pixels ranged from w to ~(w + 1) / 2. The weight is read back as
    (blend - input) / (output - input)."""
    rng = np.random.default_rng(6)
    truth = np.ones((64, 64, 3), np.float32)
    a, b, color = _halves(rng, truth, 0.3)
    out = truth.copy()
    out[24:32, 24:32] += 4.0
    blended = noise_blend(out, color, a, b)
    weight = ((blended - color) / (out - color)).mean(axis=-1)  # out - color: ~1 outside, ~4 inside
    inner = weight[25:31, 25:31]
    assert inner.max() - inner.min() < 1e-4 and inner.max() < 0.1
    w = float(inner.mean())
    np.testing.assert_allclose(weight[27, 31], (2 * w + 1) / 3, atol=0.01)  # the half tile's right edge
    assert weight[27, 32] <= (w + 2) / 3 + 0.01  # just outside it
    assert weight[27, 44:].min() > 0.9


def test_a_one_half_firefly_beside_a_light_is_clipped_to_its_unlit_neighbours():
    """The firefly clip of what the blend takes back leaves lights (pixels with emission) out of a pixel's range:
    beside a light whose emission pass took other samples than its colour (emission 666, colour 1335), a pixel
    whose half A hit the light (1500) and half B did not (1.3), with no emission of its own, is clipped to its
    unlit neighbours' level, not let through at 750 (the 64-frame `fireflies` benchmark's case)."""
    rng = np.random.default_rng(9)
    truth = np.ones((32, 32, 3), np.float32)
    a, b, _ = _halves(rng, truth, 0.05)
    emission = np.zeros_like(truth)
    a[10:13, 10:14] = b[10:13, 10:14] = 1001.0
    emission[10:13, 10:14] = 1000.0
    a[12, 11] = b[12, 11] = 1335.0
    emission[12, 11] = 666.0
    a[13, 11], b[13, 11] = 1500.0, 1.3
    color = ((a + b) / 2).astype(np.float32)
    out = np.where(emission != 0, color, np.float32(6.0)).astype(np.float32)  # wrong off the light: taken back
    for blend in (noise_blend, noise_blend_reference):
        blended = blend(out, color, a, b, emission)
        assert blended[13, 11].max() < 10.0
        np.testing.assert_array_equal(blended[emission != 0], color[emission != 0])  # the light as it came


def _window_edge():
    """A 32x32 dim wall (0.002, halves with sd 0.001) with a sky seen whole left of column 6 (0.333 in both
    halves, given as emission, as `exact.exact_emission` gives it), and every other pixel of column 6 partly
    covered by the sky (half A 0.333, half B 0.167). Returns (color, colorA, colorB, emission)."""
    rng = np.random.default_rng(4)
    truth = np.full((32, 32, 3), 0.002, np.float32)
    a = (truth + rng.normal(0, 0.001, truth.shape)).astype(np.float32)
    b = (truth + rng.normal(0, 0.001, truth.shape)).astype(np.float32)
    a[:, :6] = b[:, :6] = 0.333
    a[::2, 6], b[::2, 6] = 0.333, 0.167
    color = ((a + b) / 2).astype(np.float32)
    emission = np.where(np.arange(32)[None, :, None] < 6, color, np.float32(0.0)).astype(np.float32)
    return color, a, b, emission


def test_a_light_seen_whole_enters_its_neighbours_range_at_its_full_value():
    """A pixel partly covered by a light seen whole (all emission) may hold up to the light's value: the firefly
    clip of what the blend takes back ranges over the light at its colour, so the edge pixels an output
    darkened to the wall (a dim room's window without an emission layer, hard case `dark`) go back toward
    their input (0.25) rather than to the wall's level (0.006 with the light left out of the range)."""
    color, a, b, emission = _window_edge()
    out = color.copy()
    out[::2, 6] = 0.002
    for blend in (noise_blend, noise_blend_reference):
        blended = blend(out, color, a, b, emission)
        assert blended[::2, 6].min() > 0.2
        np.testing.assert_array_equal(blended[:, :6], color[:, :6])  # the sky as it came
    np.testing.assert_allclose(noise_blend(out, color, a, b, emission),
                               noise_blend_reference(out, color, a, b, emission), rtol=1e-5, atol=1e-7)


def _light_left(leak):
    """A 64x64 frame lit (1, halves with sd 0.3) left of column 40, every sample 0 right of it, and an output
    that is the truth but for `leak` in columns 40-47. Returns (out, color, colorA, colorB)."""
    truth = np.zeros((64, 64, 3), np.float32)
    truth[:, :40] = 1.0
    a, b, color = _halves(np.random.default_rng(3), truth, 0.3 * truth)
    out = truth.copy()
    out[:, 40:48] = leak
    return out, color, a, b


def test_an_all_dark_half_tile_the_output_lit_goes_back_to_its_black_input(monkeypatch):
    """A light has left the right of the frame: every sample of both halves is 0 there (the truth too), while
    the left is lit (1, halves with sd 0.3). An output that leaks 0.05 into the first dark column of half tiles
    adds 3.2 over each, 70 of the lit neighbours' one-hit values (their v / mean, 0.045): its samples could not
    all have missed, and the column comes back as its input, 0, exactly. Without the rule the tiles' weights,
    interpolated with the lit tiles', keep part of the leak; the lit side does not change."""
    from service.stages import dark_tiles

    out, color, a, b = _light_left(0.05)
    blended = noise_blend(out, color, a, b)
    np.testing.assert_array_equal(blended[:, 40:], 0.0)
    np.testing.assert_allclose(blended, noise_blend_reference(out, color, a, b), rtol=1e-5, atol=1e-6)
    monkeypatch.setattr(dark_tiles, "EVIDENCE", np.inf)
    without = noise_blend(out, color, a, b)
    assert float(without[:, 40:48].mean()) > 0.01
    np.testing.assert_array_equal(blended[:, :39], without[:, :39])  # beyond the ramp's pixel, nothing else moves


def test_an_all_dark_half_tile_keeps_a_lift_its_samples_could_have_missed():
    """The same frame with a leak of 0.002: 0.128 over each half tile, under 7 one-hit values (0.3), which all
    of its samples could have missed by chance: the rule does not apply and the tiles' weights decide."""
    out, color, a, b = _light_left(0.002)
    blended = noise_blend(out, color, a, b)
    assert float(blended[:, 40:48].min()) > 0.0
    np.testing.assert_allclose(blended, noise_blend_reference(out, color, a, b), rtol=1e-5, atol=1e-6)


def test_a_hard_shadow_the_output_smeared_goes_back_despite_a_few_noisy_pixels(monkeypatch):
    """A lit frame (1, halves with sd 0.3) with an 8x8 shadow whose samples all missed but for 4 one-half hits
    (4 of 64 pixels noisy: under NOISY_SHARE, which alone would leave the tiles' weights to decide); the output
    smeared the light into it (0.5). Its 60 dark pixels refute that (dark_tiles), so the half tile's own weight
    overrides, and the shadow comes back far darker than without the test."""
    from service.stages import dark_tiles

    rng = np.random.default_rng(8)
    truth = np.ones((48, 48, 3), np.float32)
    truth[24:32, 24:32] = 0.0
    a, b, color = _halves(rng, truth, 0.3 * truth)
    for i, (y, x) in enumerate([(25, 26), (27, 30), (29, 25), (31, 28)]):
        (a if i % 2 else b)[y, x] = 0.4
    color = ((a + b) / 2).astype(np.float32)
    out = truth.copy()
    out[24:32, 24:32] = 0.5
    blended = noise_blend(out, color, a, b)
    np.testing.assert_allclose(blended, noise_blend_reference(out, color, a, b), rtol=1e-5, atol=1e-6)
    monkeypatch.setattr(dark_tiles, "EVIDENCE", np.inf)
    without = noise_blend(out, color, a, b)
    shadow = (slice(25, 31), slice(25, 31))
    assert float(blended[shadow].mean()) < 0.05 < 0.2 < float(without[shadow].mean())


def test_a_dim_room_of_rare_bright_samples_beside_a_lit_floor_is_not_refuted(monkeypatch):
    """A room whose light comes in rare bright samples (15% of pixels with one half of 50: the truth 3.75,
    a one-hit value of 25) beside a floor lit at 10 (halves with sd 2, variance-to-mean ratio 0.2), the output
    the truth. Judged by the floor's ratio, the room's 85% dark pixels would refute it (3.75 / 0.2 a pixel);
    by the room's own ratio, which is larger, they do not: the blend is what it is without the test."""
    from service.stages import dark_tiles

    rng = np.random.default_rng(9)
    truth = np.full((32, 32, 3), 10.0, np.float32)
    truth[:16, :16] = 3.75
    a, b, color = _halves(rng, truth, np.where(truth == 10.0, 2.0, 0.0))
    a[:16, :16] = b[:16, :16] = 0.0
    for i, (y, x) in enumerate((y, x) for y in range(16) for x in range(16) if rng.random() < 0.15):
        (a if i % 2 else b)[y, x] = 50.0
    color = ((a + b) / 2).astype(np.float32)
    blended = noise_blend(truth, color, a, b)
    np.testing.assert_allclose(blended, noise_blend_reference(truth, color, a, b), rtol=1e-5, atol=1e-6)
    monkeypatch.setattr(dark_tiles, "EVIDENCE", np.inf)
    np.testing.assert_array_equal(blended, noise_blend(truth, color, a, b))


def test_a_temporal_blend_judges_dark_pixels_by_this_frames_one_hit_value(monkeypatch):
    """The dim room of the test above, lit at 100 (halves with sd 5) for four frames before its light goes: the
    temporal tile sums still remember the bright room, whose variance-to-mean ratio (~0.1) is far below the
    dim room's 25. Judged by this frame's sums, the dark pixels refute nothing, as in the plain blend."""
    from service.stages import dark_tiles
    from service.stages.input_history import InputHistory

    def run():
        rng = np.random.default_rng(9)
        history = InputHistory()
        for k in range(5):
            truth = np.full((32, 32, 3), 10.0, np.float32)
            truth[:16, :16] = 3.75 if k == 4 else 100.0
            a, b, color = _halves(rng, truth, np.where(truth == 10.0, 2.0, 0.0 if k == 4 else 5.0))
            if k == 4:
                a[:16, :16] = b[:16, :16] = 0.0
                for i, (y, x) in enumerate((y, x) for y in range(16) for x in range(16) if rng.random() < 0.15):
                    (a if i % 2 else b)[y, x] = 50.0
                color = ((a + b) / 2).astype(np.float32)
            blended = noise_blend(truth, color, a, b, history=history, motion=np.zeros((32, 32, 2), np.float32))
        return blended

    with_test = run()
    monkeypatch.setattr(dark_tiles, "EVIDENCE", np.inf)
    np.testing.assert_array_equal(with_test, run())


@pytest.mark.parametrize("with_emission", [False, True])
def test_firefly_clip_gives_the_blends_input_and_the_clamps_admitted_value(with_emission):
    """`firefly_clip`: c' less the emission, as the blend makes it when not given, and as radiance: e + c' where
    the clip moved the value, the colour itself (bit for bit) elsewhere."""
    rng = np.random.default_rng(12)
    truth = rng.uniform(0.2, 1.0, (20, 24, 3)).astype(np.float32)
    a, b, color = _halves(rng, truth, 0.1)
    a[5, 6] += 400.0  # a firefly in one half
    b[9, 9] = a[9, 9]  # halves that agree: never clipped
    color = ((a + b) / 2).astype(np.float32)
    emission = np.zeros_like(truth)
    emission[12:14, 3:8] = 50.0
    e = emission if with_emission else None
    shift = emission if with_emission else np.float32(0)
    a, b, color = a + shift, b + shift, color + shift
    clipped, admitted = firefly_clip(color, a, b, e)
    moved = clipped != color - shift
    assert moved[5, 6].all() and not moved[9, 9].any()
    np.testing.assert_array_equal(admitted[~moved], color[~moved])
    np.testing.assert_allclose(admitted[moved], (clipped + shift)[moved], rtol=1e-6)
    assert (admitted[5, 6] < 10.0).all()  # near its neighbours' range (up to 1.1 + its spread), not the 200 given
    out = (truth * 0.9 + shift).astype(np.float32)
    np.testing.assert_array_equal(noise_blend(out, color, a, b, e, clipped=clipped), noise_blend(out, color, a, b, e))


@pytest.mark.parametrize("with_emission", [False, True])
def test_firefly_clip_matches_its_twin(with_emission):
    """Both arrays, with fireflies in one half, lights (some seen whole) and values near the admission's limit."""
    rng = np.random.default_rng(13)
    a = rng.uniform(0.1, 1.0, (17, 19, 3)).astype(np.float32)
    b = rng.uniform(0.1, 1.0, (17, 19, 3)).astype(np.float32)
    a[rng.random((17, 19)) < 0.1] *= 200.0  # fireflies: some admitted, some beyond ADMIT_K |A - B| / 2
    color = np.float32(0.5) * (a + b)
    emission = np.zeros_like(a)
    if with_emission:
        emission[2:4, 5:9] = 40.0
        a[2:4, 5:9] += 40.0
        b[2:4, 5:9] += 40.0
        color[2:4, 5:9] += 40.0
        a[2, 5] = b[2, 5] = color[2, 5] = emission[2, 5]  # a light seen whole
    e = emission if with_emission else None
    for got, want in zip(firefly_clip(color, a, b, e), firefly_clip_reference(color, a, b, e), strict=True):
        np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-6)


def test_the_clip_is_admitted_up_to_admit_k_half_differences():
    """A pixel whose neighbours are black, its halves c +- 10: its clip (0) is admitted where c <= ADMIT_K / 2 * 20
    and not beyond."""
    limit = np.float32(ADMIT_K / 2 * 20.0)
    for c, admitted in ((limit, True), (limit + np.float32(0.5), False)):
        a = np.zeros((5, 5, 3), np.float32)
        b = a.copy()
        a[2, 2], b[2, 2] = c + np.float32(10.0), c - np.float32(10.0)
        color = np.float32(0.5) * (a + b)
        got = firefly_clip(color, a, b)[1][2, 2]
        np.testing.assert_array_equal(got, 0.0 if admitted else color[2, 2])


def test_a_given_clip_of_another_shape_is_refused():
    a = np.ones((8, 8, 3), np.float32)
    with pytest.raises(ValueError, match="noise blend: out, color, the halves, emission and clipped must share"):
        noise_blend(a, a, a, a, clipped=a[:, :4])
    with pytest.raises(ValueError, match="firefly clip: color, the halves and emission must share"):
        firefly_clip(a, a, a[:4])
