"""The noisy input accumulated over a sequence, for the noise blend of temporal pipelines.

`service.stages.noise_blend` takes part of the noisy input back where the halves say the denoiser's output is
worse. That input has the full noise of one frame. A temporal pipeline can take back a better input: the
frame's input (its fireflies clipped, less its emission) averaged with the same pixels of the frames before,
reprojected by `motion` (bilinear, taps checked against depth and normal, `service.stages.reprojection`).
The average is exponential, the newest frame weighing a = max(1 / n, ALPHA_MIN), n the frames in it so far
(a plain mean for the first frames; Schied et al. 2017 sec. 4.1 average their colour history the same way),
and the history h is clamped to the range of the frame's clipped input over the 3x3 pixels around before it
is mixed in (a lighting change, a disocclusion the depth test missed: the history cannot bring back what
the frame's samples say is gone). The accumulated input is y = (1 - a) clamp(h) + a c'.

Its error needs no reference either. With c the frame's input (less emission, unclipped), v its variance
from the halves (c's noise; ((A - B) / 2)^2 per pixel and channel) and h independent of this frame's samples,
E[(h - c)^2] - v = E[(h - mu)^2], so per pixel and channel

    (1 - a)^2 ((h - c)^2 - v) + a^2 v

estimates E[(y - mu)^2] for the unclamped history; the clamp depends on this frame's samples, and at low
sample counts (a 3x3 range of zeros where the truth is not) the clamped average can be worse than it says.
The estimate of one pixel is noisy and can be negative; the average's true error is at least a^2 v (its
share of this frame's noise), and the blend's tile sums are held at least at that floor. The blend compares
it per tile with v, the plain input's, and takes the accumulated input only where it is better by
CONFIDENCE standard errors of the per-pixel differences (noise_blend's module docstring): a tile of moving
shadow, where the history lags, keeps the frame's own input. Lights (pixels with emission) are left out of
the clamp's range: a light's colour less its emission can be far from its neighbours' radiance (the firefly
clip of noise_blend leaves them out too, but for a light seen whole, which enters at its colour).

What it gains (`make bench`, 128x128, 8 frames, 4 spp; docs/benchmarks.md "Accumulated input"):
measured there for each temporal pipeline, against the blend with the plain input.
numba kernel; `accumulate(..., reference=True)` runs its numpy twin.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from service.kernels.row_ranges import BAND_ROWS, band_scratch, no_sources, put_source, three_row_ranges
from service.kernels.window import window_range
from service.stages.reprojection import reproject, reproject_numpy

ALPHA_MIN = 0.2  # the newest frame's least weight in the average (Schied et al. 2017, sec. 4.1: 0.2)
CLAMP_RADIUS = 1  # the history is clamped to the clipped input's range over (2 r + 1)^2 pixels: 3x3 (the kernel's only)
CONFIDENCE = 2.0  # standard errors by which a tile's accumulated input must be estimated better (noise_blend)


@dataclass
class InputHistory:
    """The accumulated input of a sequence's frames so far, owned by the pipeline's sequence state; buffer, depth
    and normal are replaced by each `accumulate`, the tile sums by each blend. buffer: (H, W, C + 1) float32, the
    accumulated input less emission (radiance) and, last, the frames in it; depth: (H, W, 1) float32 or None,
    normal: (H, W, 3) float32 or None, the last frame's (the next reprojection checks its taps against them).
    half_tile_sums, tile_sums: the noise blend's sums averaged over the frames (`noise_blend.remembered_sums`),
    (noise_blend.SUM_ROWS, th', tw') float64 over half tiles and (SUM_ROWS, th, tw) over tiles, or None. Empty: no
    frame yet."""

    buffer: np.ndarray | None = None
    depth: np.ndarray | None = None
    normal: np.ndarray | None = None
    half_tile_sums: np.ndarray | None = None
    tile_sums: np.ndarray | None = None

    def clear(self) -> None:
        """Forget the frames so far (a frame without halves, or one the pipeline refused: the next frame's motion
        points to a frame that is not in it)."""
        self.buffer, self.depth, self.normal = None, None, None
        self.half_tile_sums, self.tile_sums = None, None


Accumulated = tuple[np.ndarray, np.ndarray, np.ndarray]  # what `accumulate` returns: input, error, floor


def accumulate(history: InputHistory, clipped: np.ndarray, color: np.ndarray, emission: np.ndarray | None,
               color_a: np.ndarray, color_b: np.ndarray, motion: np.ndarray | None, depth: np.ndarray | None = None,
               normal: np.ndarray | None = None, *, reference: bool = False) -> Accumulated | None:
    """Add a frame to `history` and return its accumulated input and that input's error (module docstring).

    clipped: (H, W, C) float32, the frame's input less emission, fireflies clipped (noise_blend); color,
    color_a, color_b: (H, W, C) float32 linear radiance and its halves; emission: (H, W, C) float32 or None,
    the emission in all three; motion: (H, W, 2) float32 backward motion, pixels, or None (the history starts
    again from this frame: nothing to reproject it by); depth (H, W, 1), normal (H, W, 3) float32 or None.
    All finite. `reference`: the numpy twin's arithmetic.
    Returns None on a (new) start, else (accumulated (H, W, C) float32 radiance less emission; error (H, W)
    float64 its estimated squared error, radiance^2, the channels' mean, which can be negative: an unbiased
    estimate of a small error; floor (H, W) float64, a^2 v's channel mean, a lower bound of its true error).
    """
    height, width, channels = clipped.shape
    previous = history.buffer
    if previous is not None and (previous.shape != (height, width, channels + 1) or
                                 (history.depth is None) != (depth is None) or
                                 (history.normal is None) != (normal is None)):
        previous = None  # another size or other layers: a new start
    if previous is None or motion is None:
        result = None
        buffer = np.concatenate([clipped, np.ones((height, width, 1))], axis=-1).astype(np.float32)
    else:
        warp = reproject_numpy if reference else reproject
        warped, valid = warp(previous, motion, depth=depth, prev_depth=history.depth, normal=normal,
                             prev_normal=history.normal)
        buffer = np.empty((height, width, channels + 1), np.float32)
        error, floor = np.empty((height, width), np.float64), np.empty((height, width), np.float64)
        e = clipped if emission is None else np.ascontiguousarray(emission, np.float32)  # not read without
        step = _accumulate_reference if reference else _accumulate_kernel
        step(np.ascontiguousarray(clipped, np.float32), np.ascontiguousarray(color, np.float32), e,
             emission is not None, np.ascontiguousarray(color_a, np.float32), np.ascontiguousarray(color_b, np.float32),
             warped, valid, np.float64(ALPHA_MIN), buffer, error, floor)
        result = np.ascontiguousarray(buffer[..., :channels]), error, floor
    history.buffer, history.depth, history.normal = buffer, depth, normal
    return result


@numba.njit(inline="always", cache=True, error_model="numpy")
def _clamp_sources(clipped, e, has_emission, y, src_lo, src_hi):  # pragma: no cover - jitted
    """Row y of clipped ((H, W, C) float32) for the clamp's ranges, written to src_lo, src_hi ((W * C,) float32):
    lights (e nonzero, with `has_emission`) take no part (`row_ranges`: +inf, -inf), nor a NaN or a row outside the
    frame."""
    height, width, channels = clipped.shape
    n = width * channels
    if y < 0 or y >= height:
        no_sources(src_lo, src_hi)
        return
    rc = clipped[y].reshape(n)
    re = e[y].reshape(n) if has_emission else rc  # not read without emission
    for i in range(n):  # branch-free: vectorises
        put_source(src_lo, src_hi, i, rc[i], has_emission and re[i] != 0)


@numba.njit(parallel=True, cache=True, error_model="numpy")
def _accumulate_kernel(clipped, color, e, has_emission, a, b, warped, valid, alpha_min,
                       buffer, error, floor):  # pragma: no cover - jitted
    """Per pixel, a task per band of rows (`service.kernels.row_ranges`): buffer (H, W, C + 1) float32 the
    accumulated input and its frame count, error and floor (H, W) float64 its estimate and a^2 v (module
    docstring), from warped (H, W, C + 1) float32 the reprojected history, valid (H, W) bool, clipped, color, a,
    b (H, W, C) float32 and e (H, W, C) the emission (read with `has_emission`; lights left out of the clamp's
    3x3 range); float64 arithmetic."""
    height, width, channels = clipped.shape
    n = width * channels
    for band in numba.prange(-(-height // BAND_ROWS)):
        y0, y1 = band * BAND_ROWS, min((band + 1) * BAND_ROWS, height)
        src_lo, src_hi, lo, hi, all_lo, all_hi = band_scratch(n)
        for yy in (y0 - 1, y0):
            _clamp_sources(clipped, e, has_emission, yy, src_lo[yy % 3], src_hi[yy % 3])
        for y in range(y0, y1):
            _clamp_sources(clipped, e, has_emission, y + 1, src_lo[(y + 1) % 3], src_hi[(y + 1) % 3])
            three_row_ranges(src_lo, src_hi, y, channels, True, lo, hi, all_lo, all_hi)
            for x in range(width):
                n_frames = np.float64(warped[y, x, channels]) + 1.0 if valid[y, x] else 1.0
                alpha = max(1.0 / n_frames, alpha_min) if valid[y, x] else 1.0
                total = 0.0
                least = 0.0
                for c in range(channels):
                    own = np.float64(clipped[y, x, c])
                    low, high = np.float64(lo[x * channels + c]), np.float64(hi[x * channels + c])
                    if low > high:  # lights all around: the frame's own value
                        low, high = own, own
                    h = np.float64(warped[y, x, c])
                    half = (np.float64(a[y, x, c]) - b[y, x, c]) * 0.5
                    variance = half * half
                    value = np.float64(color[y, x, c]) - e[y, x, c] if has_emission else np.float64(color[y, x, c])
                    buffer[y, x, c] = np.float32((1.0 - alpha) * min(max(h, low), high) + alpha * own)
                    total += (1.0 - alpha) ** 2 * ((h - value) ** 2 - variance) + alpha * alpha * variance
                    least += alpha * alpha * variance
                buffer[y, x, channels] = np.float32(n_frames)
                error[y, x] = total / channels
                floor[y, x] = least / channels


def _accumulate_reference(clipped, color, e, has_emission, a, b, warped, valid, alpha_min, buffer, error,
                          floor) -> None:
    """Plain-numpy twin of `_accumulate_kernel` (same arguments; writes buffer, error and floor)."""
    channels = clipped.shape[2]
    c64 = clipped.astype(np.float64)
    lo, hi = window_range(c64, CLAMP_RADIUS, excluded=(e != 0) if has_emission else None)
    empty = lo > hi  # lights all around: the frame's own value
    lo, hi = np.where(empty, c64, lo), np.where(empty, c64, hi)
    n = np.where(valid, warped[..., channels].astype(np.float64) + 1.0, 1.0)
    alpha = np.where(valid, np.maximum(1.0 / n, alpha_min), 1.0)[..., None]
    h = warped[..., :channels].astype(np.float64)
    variance = ((a.astype(np.float64) - b) * 0.5) ** 2
    value = color.astype(np.float64) - (e if has_emission else 0.0)
    buffer[..., :channels] = (1.0 - alpha) * np.clip(h, lo, hi) + alpha * c64
    buffer[..., channels] = n
    error[...] = ((1.0 - alpha) ** 2 * ((h - value) ** 2 - variance) + alpha * alpha * variance).mean(axis=-1)
    floor[...] = (alpha * alpha * variance).mean(axis=-1)
