"""Per tile, a denoiser's output blended with the noisy input by the weight that the two halves say is best.

A pixel estimate c = (A + B) / 2 has variance v = E[(A - B)^2] / 4 (the halves are independent estimates
of the same mean mu). A denoiser's output o at that pixel averages many pixels, so it depends little on
c's own noise, and per pixel and channel

    e = (o - c)^2 - v          estimates o's squared error, E[(o - mu)^2]
    y = c + t (o - c)          the blend, whose squared error is about  v - 2 t v + t^2 (e + v),

least at t = v / (e + v): a tile where the denoiser is much better than its input keeps it (t ~ 1), one
where it is worse than the input (a bright ring blurred into a black shadow, a mirror's glint smeared
over the void it reflects) goes back toward the input, and with the per-pixel optimum the blend would be
no worse than either in expectation (per tile, with an estimated t and the clipped input below, it is
close). The sums run over TILE x TILE tiles, weighted like relL2 (service.metrics.rel_l2_map) by
1 / (p^2 + REL_L2_EPS) with p, a stand-in for the unknown reference, the smaller of o's and the 3x3 box mean of
c's channel means: where o lifts a region whose samples say dark, its error weighs as the reference's
darkness makes it weigh. p is at least PROXY_FLOOR times that box mean: where o darkens a pixel to about 0,
its weight would be 1 / REL_L2_EPS, and one such pixel with a bright sample (a sky seen in one half, in a
dark room lit through a window) would outweigh a whole row the output lifted beside it in the same tile.
With Eo and Ec the tile's weighted sums of e and v,

    t = Ec / (max(Eo, 0) + Ec)    (1 where both are 0),

interpolated between tile centres (no seams). A small region the output got wrong (a mirror sphere's
reflection blurred, a caustic smeared) can hide in a tile the output got right elsewhere, so t is also
taken over half tiles, and where a half tile's t is below WORSE (its Eo above its Ec: the output
estimated worse than the input there) it holds over the half tile's own pixels, eased over a ramp of
2 HALF_RAMP + 1 pixels across its border (the mean of the half-tile weights over the (2 HALF_RAMP + 1)^2
box of pixels around: with HALF_RAMP 1 and a neighbour of weight 1, a rejected half tile's edge pixels take
(2 w + 1) / 3, its corners (4 w + 5) / 9, and the pixels just outside (w + 2) / 3), and the smaller of it
and the interpolated t is the weight; a half tile's estimate is
noisier, and it only ever takes more of the input back where it says the output is worse, which an
ordinary tile rarely says by chance. Interpolated between half-tile centres instead, a rejected half
tile's weight was diluted by its neighbours' 1 over half of its pixels: a mirror's reflection of the void,
lifted by bmfr, stayed 1.16x worse than the input in its tile (hard case `bulb`), and a dark band
crossregression blurred, 1.13x (`glints`). It needs NOISY_SHARE of its pixels to have halves
that differ: where both halves of most pixels saw nothing (a dim region at 1 spp per half), Ec is about 0
because the samples are few, not because the input is right, unless the dark pixels there (both halves
about 0) refute the output (service/stages/dark_tiles.py: far more of them than the output's light leaves a
chance for, judged by the one-hit value of the noisy half tiles around): then it overrides all the same, and
its dark pixels take their input (weight 0, no ramp inward, and not the accumulated input). A light that
left a region, or a filter that smeared light into a hard shadow, is caught so (`make bench`: relL2 on
`fireflies` up to 3.1% lower, its other numbers unchanged; docs/benchmarks.md). The test also runs on half
tiles whose weight is below WORSE, and judges by this frame's sums, not the temporal average below.
The result is c' + t (o - c'), with c' the input with its fireflies clipped (`outliers.clamp_fireflies`, where
the halves differ: a firefly is in one half only, while a light seen directly is in both): the part of the
input the blend takes back should not bring them with it. `firefly_clip` makes c' once per step, for the blend
and for `noise_clamp`, whose band reaches it where the pixel's own halves allow (ADMIT_K; noise_clamp's
docstring says why and what it changed). Lights (pixels with emission) are left out of their
neighbours' ranges: beside a light whose emission pass took other samples than its colour (emission 666,
colour 1335 on the 64-frame `fireflies` benchmark sequence), its remainder widened the range enough to let a
one-half sample of 750 through where the truth was 25, in one pixel, which alone made up a quarter of the
sequence's temporal error (crossreg 0.879 -> 0.668, svgf 0.906 -> 0.695, kpn 0.875 -> 0.664 with them left
out; relL2 and the 8-frame benchmark unchanged to 4 digits; `make bench-long`). A light seen whole (its colour
all emission, as an exact pixel of a frame without an emission layer is) enters the ranges at its colour: a
pixel beside it may be partly covered by it. Left out too, it had the edge pixels of a dim room's window (a
sky of 0.33 beside a wall of 0.002; hard case `dark` given without its emission layer) clipped to the wall's
level where a filter darkened them: relL2 there, flr / kpn / svgf, 0.77x / 0.81x / 0.84x the noisy input's ->
0.56x / 0.58x / 0.60x, worst tile 2.27x / 2.31x / 2.25x -> 1.24x / 1.66x / 1.26x; `make bench` relL2 at most
0.4% higher (docs/benchmarks.md). A temporal pipeline gives its sequence's accumulated input
(`service.stages.input_history`: c' averaged over the frames before, reprojected, with a per-pixel estimate
of its error): per tile, where the weighted mean of the per-pixel differences d
between that estimate and v, plus CONFIDENCE standard errors of it, is below 0, c' is the accumulated input
and Ec the sum of its estimated error in that tile and its half tiles, at least the sum of a^2 v (the share of
this frame's noise in it; the estimate is of the unclamped average, see input_history's docstring). A temporal
pipeline's tile sums (of e, of the input's error and its floor, and the count of pixels whose halves differ,
over tiles and half tiles) are also averaged over its frames, TILE_MEMORY of the previous average and the rest
this frame's, at the same tile positions (not reprojected), from the last frame the accumulated input started
at, but where none of a tile's pixels has halves that differ in this frame (its input is exact and comes back
as given): a tile's weight then moves less with this frame's noise, and the output flickers less (`make
bench`, the five temporal pipelines of the day: temporal error lower for each on all four sequences, by up to
6%; relL2 lower on 19 of 20 pairs, 0.5% higher on svgf's fireflies; docs/benchmarks.md). A pipeline that is
not temporal keeps its frame's sums alone, so that its output depends on its frame only. A value the denoiser
left as it came (an exact pixel, a background passed through) stays so; a frame whose halves agree everywhere
comes back as its input. Interpolation lets a tile's neighbours lend it their t at its border, so a region the
tiles reject keeps some of the output within ~half a tile of its edge.

What it costs and gains on ordinary frames (`make bench`, 128x128, 4 spp; docs/benchmarks.md, "Noise
blend"): the blend itself lowered every pipeline's relL2 overall; the 3x3 level and the half tiles,
against a 5x5 level and whole tiles only, lowered it further (up to 20% on one sequence) or raised it by
at most 1.5%, and raised the temporal error on `shadows` by 3-17% and 1-SSIM by up to 3%. On a frame with
one sample per half that hits light with probability 0.3 (a 0/1 signal), the blend of an output within
10% of the truth has relL2 0.026 (0.015 with a 5x5 level and no half tiles): the 3x3 level weighs each
pixel by a mean that its own noise moves more. The PROXY_FLOOR changed relL2 and temporal error by at most 2%, on
fireflies alone, and took bmfr's worst tile on the window hard case from 2.78x the noisy input's to 0.76x.
The half tiles' own weights over their pixels (instead of interpolated between their centres) lowered relL2
on `shadows` and `fireflies` by up to 6% (bilateral, bmfr, statistical), raised it by at most 1.3%
elsewhere, and raised the temporal error on `shadows` by 2-7% (and on the 64-frame `fireflies` of `make
bench-long` by 7%, crossregression, before lights were left out of the clip).
numba kernels; `noise_blend_reference` is the numpy twin.
"""

from __future__ import annotations

import functools

import numba
import numpy as np

from service.kernels.row_ranges import BAND_ROWS, band_scratch, no_sources, put_source, three_row_ranges
from service.metrics import REL_L2_EPS
from service.stages.blend_sums import FLOAT32_MAX, SUM_ROWS, choice_kernel, level_kernel, tile_kernel
from service.stages.dark_tiles import (
    dark_levels,
    dark_mask_reference,
    is_dark,
    one_hit_values,
    refuted,
    refuted_reference,
)
from service.stages.error_estimate import interpolate_tiles, interpolation_matrix, tile_counts, tile_sums
from service.stages.exact import EXACT_RTOL, agree, agrees
from service.stages.input_history import CONFIDENCE, Accumulated, InputHistory, accumulate
from service.stages.outliers import FIREFLY_K, clamp_fireflies_reference
from service.stages.svgf import box_mean

TILE = 16  # tile side, pixels: the hard-case criterion's tile (bench/hard_cases.py)
LEVEL_RADIUS = 1  # the box mean of c that stands in for the reference's level: 3x3 pixels
PROXY_FLOOR = 0.25  # ... and the stand-in is at least this share of it (module docstring)
WORSE = 0.5  # a half tile whose weight is below this (its output estimated worse than its input) overrides
NOISY_SHARE = 0.25  # ... where at least this share of its pixels have halves that differ (module docstring)
HALF_RAMP = 1  # ... over its own pixels, eased over the (2 r + 1)^2 box of the pixels around (module docstring)
ADMIT_K = 10.0  # `firefly_clip`'s admitted value: the clip where within this many |A - B| / 2 of the colour
TILE_MEMORY = 0.3  # a temporal pipeline's tile sums: this share of the previous frames' average (module docstring)


def blend_weights(error_out: np.ndarray, error_in: np.ndarray) -> np.ndarray:
    """Per tile t = Ec / (max(Eo, 0) + Ec), 1 where both are 0. error_out, error_in: (th, tw) float64 weighted
    sums Eo and Ec. Returns (th, tw) float64 in [0, 1]."""
    total = np.maximum(error_out, 0.0) + error_in
    return np.where(total > 0, error_in / np.where(total > 0, total, 1.0), 1.0)


def _check(arrays: list[np.ndarray], tile: int,
           what: str = "noise blend: out, color, the halves, emission and clipped") -> None:
    """ValueError unless tile >= 1 and `arrays` share one (H, W, C) shape; `what` names them in the message."""
    if tile < 1:
        raise ValueError(f"noise blend tile must be >= 1, got {tile}")
    shapes = {x.shape for x in arrays}
    if len(shapes) != 1 or arrays[0].ndim != 3:
        raise ValueError(f"{what} must share one (H, W, C) shape: {shapes}")


def firefly_clip(color: np.ndarray, color_a: np.ndarray, color_b: np.ndarray,
                 emission: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The input with its fireflies clipped, c' (module docstring), twice: less the emission, as `noise_blend`
    takes it back (the colour less e, clipped where the halves differ), and as radiance, which `noise_clamp` admits:
    e + that where the clip moved the value to within ADMIT_K times the pixel's own spread |A - B| / 2 of the
    colour (the two samples of a pixel that found rare bright paths independently differ far more than those of a
    glint that both saw), the colour itself elsewhere. color, color_a, color_b: (H, W, C)
    float32 noisy radiance and its halves; emission: (H, W, C) float32 or None, as given to `noise_blend`.
    Returns two (H, W, C) float32 arrays, linear radiance (the second with the emission, like `color`; at a
    pixel with emission near float32's largest it may be inf, which the clamp never reads: such a pixel keeps
    the denoiser's output or its input there)."""
    arrays = [np.ascontiguousarray(x, dtype=np.float32) for x in (color, color_a, color_b)]
    if emission is not None:
        arrays.append(np.ascontiguousarray(emission, dtype=np.float32))
    _check(arrays, TILE, "firefly clip: color, the halves and emission")
    clipped, admitted = np.empty_like(arrays[0]), np.empty_like(arrays[0])
    _clip_kernel(*arrays[:3], arrays[-1], emission is not None, np.float32(FIREFLY_K), np.float32(EXACT_RTOL),
                 np.float32(ADMIT_K / 2), clipped, admitted)
    return clipped, admitted


def noise_blend(out: np.ndarray, color: np.ndarray, color_a: np.ndarray, color_b: np.ndarray,
                emission: np.ndarray | None = None, tile: int = TILE, history: InputHistory | None = None,
                motion: np.ndarray | None = None, depth: np.ndarray | None = None,
                normal: np.ndarray | None = None, clipped: np.ndarray | None = None) -> np.ndarray:
    """`out` blended per tile with `color` (module docstring). out: (H, W, C) float32 denoised radiance;
    color, color_a, color_b: (H, W, C) float32 noisy radiance and its two halves; emission: (H, W, C)
    float32 or None, the emission in all four (a light's value is no level for its neighbours' weights,
    nor, unless seen whole, for their firefly clip: the blend runs on the radiance less it, and adds it
    back; a pixel with emission keeps `out`, as `noise_clamp` leaves it: there the halves' disagreement is
    the emitter's coverage, not noise the output should take back); all linear, finite. history: a temporal pipeline's
    accumulated input (`service.stages.input_history`), which this frame joins when it has `motion` ((H, W, 2)
    float32, pixels; depth (H, W, 1) and normal (H, W, 3) float32 check the reprojection where given) and
    forgets otherwise. clipped: (H, W, C) float32, `firefly_clip`'s first array for these colour, halves and
    emission, or None to make it here. Returns a new (H, W, C) float32 array."""
    arrays = [np.ascontiguousarray(x, dtype=np.float32) for x in (out, color, color_a, color_b)]
    if emission is not None:
        arrays.append(np.ascontiguousarray(emission, dtype=np.float32))
    if clipped is not None:
        clipped = np.ascontiguousarray(clipped, dtype=np.float32)
    _check(arrays + ([] if clipped is None else [clipped]), tile)
    has_emission = emission is not None
    e = arrays[4] if has_emission else arrays[1]  # not read without emission
    height, width = arrays[0].shape[:2]
    level = np.empty((height, width), np.float32)
    level_kernel(arrays[1], e, has_emission, LEVEL_RADIUS, level)
    if clipped is None:
        clipped = firefly_clip(*arrays[1:4], emission)[0]
    choice = _accumulated(history, clipped, arrays, emission, motion, depth, normal, False)
    if choice is None:
        accumulated, input_error, floor, use = clipped, np.zeros((1, 1)), np.zeros((1, 1)), np.zeros((1, 1), np.bool_)
    else:
        accumulated, input_error, floor = choice
        stats = np.zeros((3, -(-height // tile), -(-width // tile)), np.float64)
        choice_kernel(*arrays[:4], e, has_emission, level, input_error, tile, REL_L2_EPS, PROXY_FLOOR, stats)
        use = takes_accumulated(stats)
    half = half_tile(tile)

    def sums(side: int) -> np.ndarray:  # (SUM_ROWS, th, tw): `tile_kernel`'s sums over tiles of this side
        out = np.zeros((SUM_ROWS, -(-height // side), -(-width // side)), np.float64)
        tile_kernel(*arrays[:4], e, has_emission, level, input_error, floor, use, tile, choice is not None, side,
                    REL_L2_EPS, PROXY_FLOOR, out)
        return out

    fine = this_frame = sums(half)  # the dark pixels are judged by this frame's one-hit values and shares
    if tile == 2 * half:  # an even tile: its sums are those of its 2x2 half tiles
        padded = np.pad(fine, ((0, 0), (0, fine.shape[1] % 2), (0, fine.shape[2] % 2)))
        coarse = padded.reshape(SUM_ROWS, padded.shape[1] // 2, 2, padded.shape[2] // 2, 2).sum(axis=(2, 4))
    else:
        coarse = fine if tile == half else sums(tile)
    fine, coarse = remembered_sums(history, fine, coarse, choice is not None)
    t = blend_weights(coarse[0], np.maximum(coarse[1], coarse[3])).astype(np.float32)
    pixels = tile_counts(height, width, half)
    weights = blend_weights(fine[0], np.maximum(fine[1], fine[3]))
    one_hit, candidates = dark_questions(this_frame, weights, pixels)
    refute = refuted(arrays[0], arrays[2], arrays[3], arrays[4] if has_emission else None, one_hit, candidates, half)
    t_half = half_tile_weights(weights, fine[2], pixels, refute).astype(np.float32)
    result = np.empty_like(arrays[0])
    _blend_kernel(*arrays[:4], e, has_emission, clipped, accumulated, use, tile, choice is not None, t,
                  *_interpolation(height, tile), *_interpolation(width, tile), t_half, dark_levels(one_hit, refute),
                  half, HALF_RAMP, result)
    return result


def _accumulated(history: InputHistory | None, clipped: np.ndarray, arrays: list[np.ndarray],
                 emission: np.ndarray | None, motion: np.ndarray | None, depth: np.ndarray | None,
                 normal: np.ndarray | None, reference: bool) -> Accumulated | None:
    """`input_history.accumulate` of the frame (arrays: out, color and its halves) into `history`, or None: no
    history, or a (new) start of it (its first frame, or a frame without motion)."""
    if history is None:
        return None
    return accumulate(history, clipped, arrays[1], emission, arrays[2], arrays[3], motion, depth, normal,
                      reference=reference)


def remembered_sums(history: InputHistory | None, fine: np.ndarray, coarse: np.ndarray,
                    continued: bool) -> tuple[np.ndarray, np.ndarray]:
    """The blend's sums over half tiles (`fine`, (SUM_ROWS, th', tw') float64) and tiles (`coarse`, (SUM_ROWS, th, tw))
    averaged with the previous frame's as kept in `history` (TILE_MEMORY of the previous average; module
    docstring), and kept there for the next frame. `continued`: the frame joined the accumulated input (it has
    motion and follows the frame before); otherwise the average starts again from this frame. Without a history (a
    pipeline that is not temporal) returns the sums as given. A (half) tile none of whose pixels has halves that
    differ in this frame (row 2 of the sums is 0) takes this frame's sums alone: its input is exact, and it comes
    back as given."""
    if history is None:
        return fine, coarse
    before_fine, before = history.half_tile_sums, history.tile_sums
    if continued and before is not None and before_fine.shape == fine.shape and before.shape == coarse.shape:
        fine = np.where(fine[2] > 0, TILE_MEMORY * before_fine + (1.0 - TILE_MEMORY) * fine, fine)
        coarse = np.where(coarse[2] > 0, TILE_MEMORY * before + (1.0 - TILE_MEMORY) * coarse, coarse)
    history.half_tile_sums, history.tile_sums = fine, coarse
    return fine, coarse


def takes_accumulated(stats: np.ndarray) -> np.ndarray:
    """Per tile whether the blend takes the accumulated input back: the mean of the per-pixel differences d of
    its weighted error and the plain input's, plus CONFIDENCE standard errors, is below 0. stats: (3, th, tw)
    float64, per tile the sum of d, of d^2 and the pixels. Returns (th, tw) bool."""
    total, square, count = stats
    count = np.maximum(count, 1.0)
    mean = total / count
    spread = np.sqrt(np.maximum(square / count - mean * mean, 0.0) / count)
    return mean + CONFIDENCE * spread < 0


def half_tile_weights(weights: np.ndarray, noisy: np.ndarray, pixels: np.ndarray, refute: np.ndarray) -> np.ndarray:
    """Per half tile the weight that overrides the tile's (module docstring): its `weights` (`blend_weights`')
    where below WORSE and at least NOISY_SHARE of the half tile's `pixels` are `noisy` (their halves differ) or
    its dark pixels `refute` the output (`dark_tiles`), else 1. All (th', tw') float64 (`pixels` int64,
    `refute` bool); returns float64 in [0, 1]."""
    return np.where((weights < WORSE) & ((noisy >= NOISY_SHARE * pixels) | refute), weights, 1.0)


def dark_questions(this_frame: np.ndarray, weights: np.ndarray, pixels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """What the dark pixels' test (`dark_tiles`) needs: per half tile its one-hit value, from this frame's sums
    (`this_frame`, (SUM_ROWS, th', tw') float64: not the temporal average, which may remember a brighter past),
    and whether to ask at all: where NOISY_SHARE blocks the override or the `weights` are below WORSE. weights,
    pixels: (th', tw') float64 and int64. Returns ((th', tw') float64, (th', tw') bool)."""
    one_hit = one_hit_values(this_frame[2], this_frame[4], this_frame[5], pixels, NOISY_SHARE)
    return one_hit, (this_frame[2] < NOISY_SHARE * pixels) | (weights < WORSE)


def half_tile(tile: int) -> int:
    """The side of the finer tiles whose weight overrides where it says the output is worse (module docstring)."""
    return max(tile // 2, 1)


@functools.lru_cache(maxsize=32)
def _interpolation(size: int, tile: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per pixel along one axis, the two tiles and the weight of the second that
    `error_estimate.interpolation_matrix` uses: (size,) int64, (size,) int64, (size,) float32."""
    matrix = interpolation_matrix(size, tile)
    first = np.argmax(matrix > 0, axis=1)
    second = np.minimum(first + 1, matrix.shape[1] - 1)
    weight = np.where(second > first, matrix[np.arange(size), second], 0.0)
    return first, second, weight.astype(np.float32)


def firefly_clip_reference(color: np.ndarray, color_a: np.ndarray, color_b: np.ndarray,
                           emission: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Plain-numpy twin of `firefly_clip`."""
    e = np.zeros(color.shape, np.float64) if emission is None else emission.astype(np.float64)
    c = (color.astype(np.float64) - e).astype(np.float32)
    whole = np.zeros(c.shape[:2], np.bool_) if emission is None else agrees(color, emission) & (e != 0).any(axis=-1)
    planes = np.ascontiguousarray(c.transpose(2, 0, 1))
    ranged = np.where(whole[..., None], color, c).astype(np.float32).transpose(2, 0, 1)
    excluded = ((e != 0) & ~whole[..., None]).transpose(2, 0, 1)
    clipped = clamp_fireflies_reference(planes, excluded=excluded, ranged=ranged).transpose(1, 2, 0)
    moved = (color_a != color_b) & (clipped != c)
    clipped = np.where(moved, clipped, c)
    spread = np.float32(ADMIT_K / 2) * np.abs(color_a.astype(np.float32) - color_b)
    near = np.abs(clipped - c) <= spread
    admitted = np.where(moved & near, (e + clipped).astype(np.float32), color.astype(np.float32))
    return clipped, admitted


def noise_blend_reference(out: np.ndarray, color: np.ndarray, color_a: np.ndarray, color_b: np.ndarray,
                          emission: np.ndarray | None = None, tile: int = TILE, history: InputHistory | None = None,
                          motion: np.ndarray | None = None, depth: np.ndarray | None = None,
                          normal: np.ndarray | None = None) -> np.ndarray:
    """Plain-numpy twin of `noise_blend`."""
    given = [out, color, color_a, color_b] + ([] if emission is None else [emission])
    _check(given, tile)
    e = np.zeros(out.shape, np.float64) if emission is None else emission.astype(np.float64)
    o, c, a, b = (x.astype(np.float64) - e for x in (out, color, color_a, color_b))
    height, width = o.shape[:2]
    level = np.minimum(box_mean(c.mean(axis=-1, keepdims=True).astype(np.float32), LEVEL_RADIUS)[..., 0], FLOAT32_MAX)
    proxy = np.maximum(np.maximum(np.minimum(o.mean(axis=-1), level), PROXY_FLOOR * level), 0.0)
    weight = 1.0 / (proxy * proxy + REL_L2_EPS)
    variance = ((a - b) * 0.5) ** 2
    pixel_out, pixel_in = weight * ((o - c) ** 2 - variance).mean(axis=-1), weight * variance.mean(axis=-1)
    clipped = firefly_clip_reference(color, color_a, color_b, emission)[0]
    moved = clipped != c.astype(np.float32)
    arrays = [np.asarray(x, np.float32) for x in (out, color, color_a, color_b)]
    choice = _accumulated(history, clipped, arrays, emission, motion, depth, normal, True)
    frame_input = taken = np.where(moved, e + clipped, color.astype(np.float64))
    least = pixel_in  # per pixel, the floor of the input's error
    if choice is not None:
        accumulated, input_error, floor = choice
        d = weight * input_error - pixel_in
        stats = np.stack([tile_sums(d, tile)[0], tile_sums(d * d, tile)[0], tile_sums(np.ones_like(d), tile)[0]])
        use = np.repeat(np.repeat(takes_accumulated(stats), tile, 0), tile, 1)[:height, :width]
        pixel_in, least = (np.where(use, weight * x, pixel_in) for x in (input_error, floor))
        taken = np.where(use[..., None], e + accumulated, taken)
    half = half_tile(tile)
    noisy_pixels = (variance > 0).any(axis=-1).astype(np.float64)

    lit = np.maximum(c.mean(axis=-1), 0.0) * noisy_pixels
    rows = (pixel_out, pixel_in, noisy_pixels, least, lit, variance.mean(axis=-1))

    def sums(side: int) -> np.ndarray:  # (SUM_ROWS, th, tw), as `tile_kernel`'s
        return np.stack([tile_sums(x, side)[0] for x in rows])

    this_frame = sums(half)
    fine, coarse = remembered_sums(history, this_frame, sums(tile), choice is not None)
    t = blend_weights(coarse[0], np.maximum(coarse[1], coarse[3]))
    pixels = tile_sums(noisy_pixels, half)[1]
    weights = blend_weights(fine[0], np.maximum(fine[1], fine[3]))
    one_hit, candidates = dark_questions(this_frame, weights, pixels)
    refute = refuted_reference(out, color_a, color_b, emission, one_hit, candidates, half)
    t_half = half_tile_weights(weights, fine[2], pixels, refute)
    own = np.repeat(np.repeat(t_half, half, axis=0), half, axis=1)[:height, :width, None].astype(np.float32)
    t = np.minimum(interpolate_tiles(t, tile, height, width), box_mean(own, HALF_RAMP)[..., 0])[..., None]
    dark = np.repeat(np.repeat(dark_levels(one_hit, refute), half, axis=0), half, axis=1)[:height, :width]
    quiet = ((dark >= 0) & dark_mask_reference(color_a, color_b, emission, dark))[..., None]
    t = np.where(quiet, 0.0, t)
    taken = np.where(quiet, frame_input, taken)
    t = np.where((e != 0).any(axis=-1, keepdims=True), 1.0, t)
    blended = np.clip((1.0 - t) * taken + t * out.astype(np.float64), -FLOAT32_MAX, FLOAT32_MAX)
    return np.where(out == color, color, blended).astype(np.float32)


@numba.njit(inline="always", cache=True, error_model="numpy")
def _range_sources(color, e, has_emission, y, rtol, src_lo, src_hi):  # pragma: no cover - jitted
    """Row y's values for its neighbours' firefly ranges, written to src_lo and src_hi ((W * C,) float32): the
    colour less e (color, e: (H, W, C) float32; e only with `has_emission`), but a light seen whole (every
    channel of its colour agrees with e to rtol, float32 relative; some e nonzero) at its colour, its full
    value: a neighbour may be partly covered by it. The other lights' values (e nonzero; module docstring) take
    no part (`row_ranges`: +inf in src_lo, -inf in src_hi), nor does a NaN or a row outside the frame."""
    height, width, channels = color.shape
    n = width * channels
    if y < 0 or y >= height:
        no_sources(src_lo, src_hi)
        return
    rc = color[y].reshape(n)
    if has_emission:
        re = e[y].reshape(n)
        if _any_nonzero(re):
            for x in range(width):
                i = x * channels
                lit, whole = False, True
                for c in range(channels):
                    lit = lit or re[i + c] != 0
                    whole = whole and agree(rc[i + c], re[i + c], rtol)
                for c in range(channels):
                    value = rc[i + c] if lit and whole else rc[i + c] - re[i + c]
                    put_source(src_lo, src_hi, i + c, value, lit and not whole and re[i + c] != 0)
            return
    for i in range(n):  # no light in the row: its colour (less e, all 0); contiguous, vectorises
        put_source(src_lo, src_hi, i, rc[i], False)


@numba.njit(inline="always", cache=True)
def _any_nonzero(row):  # pragma: no cover - jitted
    """Whether some value of `row` ((n,) float32) is nonzero, counted branch-free: a row of zeros costs one
    vectorised pass."""
    count = 0
    for i in range(row.shape[0]):
        count += 1 if row[i] != 0 else 0
    return count > 0


@numba.njit(parallel=True, cache=True, error_model="numpy")
def _clip_kernel(color, a, b, e, has_emission, k, rtol, admit, clipped, admitted):  # pragma: no cover - jitted
    """clipped (H, W, C) float32: the colour less the emission e (with `has_emission`; color, a, b, e (H, W, C)
    float32), clipped like `outliers.clamp_fireflies` (k, float32) where the halves a, b differ, over ranges
    that take a light seen whole at its colour and leave the other lights (e nonzero) out (`_range_sources`,
    rtol: EXACT_RTOL; a value with no neighbour left keeps itself). The range is `outliers.clamp_fireflies`'
    3x3 range, taken here on the interleaved (W * C) rows (`service.kernels.row_ranges`, a task per band of
    rows): through its (C, H, W) planes it cost ~3 ms more a 1280x720 frame (the transposes). admitted (H, W, C)
    float32: e + clipped where the clip moved the value by at most admit |a - b|, the colour elsewhere."""
    height, width, channels = color.shape
    n = width * channels
    for band in numba.prange(-(-height // BAND_ROWS)):
        y0, y1 = band * BAND_ROWS, min((band + 1) * BAND_ROWS, height)
        src_lo, src_hi, lo, hi, all_lo, all_hi = band_scratch(n)
        for yy in (y0 - 1, y0):
            _range_sources(color, e, has_emission, yy, rtol, src_lo[yy % 3], src_hi[yy % 3])
        for y in range(y0, y1):
            _range_sources(color, e, has_emission, y + 1, rtol, src_lo[(y + 1) % 3], src_hi[(y + 1) % 3])
            three_row_ranges(src_lo, src_hi, y, channels, False, lo, hi, all_lo, all_hi)
            rc, ra, rb, rd = color[y].reshape(n), a[y].reshape(n), b[y].reshape(n), clipped[y].reshape(n)
            re = e[y].reshape(n) if has_emission else rc  # not read without emission
            rm = admitted[y].reshape(n)
            for i in range(n):  # branch-free: vectorises
                v = rc[i] - re[i] if has_emission else rc[i]
                spread = k * (hi[i] - lo[i])
                clip = min(max(v, lo[i] - spread), hi[i] + spread) if lo[i] <= hi[i] else v  # no neighbour: itself
                rd[i] = clip if ra[i] != rb[i] else v
                near = abs(rd[i] - v) <= admit * abs(ra[i] - rb[i])  # within the pixel's own spread
                rm[i] = (re[i] + rd[i] if has_emission else rd[i]) if rd[i] != v and near else rc[i]


@numba.njit(parallel=True, cache=True, error_model="numpy")
def _blend_kernel(out, color, a, b, e, has_emission, clipped, accumulated, use, use_tile, has_choice, t,
                  row0, row1, row_w, col0, col1, col_w, tf, dark, half, ramp, result):  # pragma: no cover - jitted
    """result = c' + w (out - c'), w the smaller of t, bilinear between its tiles' centres (the `_interpolation`
    tables), and of tf's mean over the in-frame (2 ramp + 1)^2 box of pixels, each pixel taking its own half
    tile's; c' the emission e (with `has_emission`) plus `accumulated` ((H, W, C) float32) where `use` ((th',
    tw') bool per tile of side use_tile, with `has_choice`) takes it, else plus `clipped` ((H, W, C) float32,
    `_clip_kernel`'s) where the clip moved the value, else the colour. t: (th, tw) and tf: (th', tw') float32
    weights of the tiles and of the half tiles (side `half` pixels); row0, row1, row_w (H,) and col0, col1,
    col_w (W,): `_interpolation`'s tables for t. A pixel dark within its half tile's `dark` level ((th', tw')
    float64, -1: none; `dark_tiles.is_dark`) takes c' without the accumulated input, at weight 0 (no ramp
    inward). A task per row (float64, within float32's range)."""
    height, width, channels = out.shape
    n = width * channels
    for y in numba.prange(height):
        fy = row_w[y]
        y0, y1 = max(y - ramp, 0), min(y + ramp + 1, height)
        band = np.zeros(tf.shape[1], np.float64)  # per half-tile column, the mean of tf over the rows y0..y1-1
        for yy in range(y0, y1):
            for j in range(tf.shape[1]):
                band[j] += tf[yy // half, j]
        band /= y1 - y0
        held = np.empty(width, np.float64)  # per pixel of the row, its half tile's value of band
        for j in range(tf.shape[1]):
            for x in range(j * half, min((j + 1) * half, width)):
                held[x] = band[j]
        top_row, bottom_row = t[row0[y]], t[row1[y]]
        pixel = np.empty(width, np.float32)  # per pixel, its weight: t bilinear between the tiles' centres,
        for x in range(width):
            fx = col_w[x]
            top = top_row[col0[x]] + fx * (top_row[col1[x]] - top_row[col0[x]])
            bottom = bottom_row[col0[x]] + fx * (bottom_row[col1[x]] - bottom_row[col0[x]])
            pixel[x] = top + fy * (bottom - top)
        for x in range(width):  # then at most the half tiles' weights' box mean
            x0, x1 = max(x - ramp, 0), min(x + ramp + 1, width)
            total = 0.0
            for xx in range(x0, x1):
                total += held[xx]
            pixel[x] = min(pixel[x], np.float32(total / (x1 - x0)))
        source = np.zeros(width, np.bool_)  # per pixel, whether c' is the accumulated input
        dark_row = dark[y // half]
        for j in range(dark_row.shape[0]):
            level = dark_row[j]
            if level < 0 and not has_choice:  # no dark pixel, no accumulated input: nothing to change
                continue
            for x in range(j * half, min((j + 1) * half, width)):
                quiet = level >= 0 and is_dark(a, b, e, has_emission, y, x, level)
                if quiet:
                    pixel[x] = np.float32(0)
                source[x] = has_choice and use[y // use_tile, x // use_tile] and not quiet
        ro, rc, rr = out[y].reshape(n), color[y].reshape(n), result[y].reshape(n)
        rd = clipped[y].reshape(n)
        rh = accumulated[y].reshape(n) if has_choice else rd
        base = e[y].reshape(n) if has_emission else np.zeros(n, np.float32)
        if _any_nonzero(base):  # a pixel with emission keeps the output, as the noise clamp leaves it
            for x in range(width):
                for c in range(channels):
                    if base[x * channels + c] != 0:
                        pixel[x] = np.float32(1)
        weights = np.empty(n, np.float32)  # per value, its pixel's weight and source
        history = np.empty(n, np.bool_)
        for x in range(width):
            for c in range(channels):
                weights[x * channels + c] = pixel[x]
                history[x * channels + c] = source[x]
        for i in range(n):  # branch-free: vectorises
            v = rc[i] - base[i]
            own = np.float64(base[i]) + rd[i] if rd[i] != v else np.float64(rc[i])
            taken = np.float64(base[i]) + rh[i] if history[i] else own
            w = np.float64(weights[i])
            mixed = (1.0 - w) * taken + w * ro[i]  # float64, then within float32's range
            mixed = min(max(mixed, -FLOAT32_MAX), FLOAT32_MAX)
            rr[i] = rc[i] if ro[i] == rc[i] else np.float32(mixed)  # left as it came (exact, background)
