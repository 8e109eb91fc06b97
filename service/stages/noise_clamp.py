"""Keep a denoiser's output within the noise the two half buffers show at each pixel.

A pixel estimate `color` = (colorA + colorB) / 2 has variance Var(color) = E[(colorA - colorB)^2] / 4
(the halves are independent estimates of the same mean). Where that variance is small the renderer has
already resolved the pixel, and a filter that moves it far (a sky blurred with the horizon, a black
reflection of the void lifted by its bright surround) makes it worse than it came in. So every output
value is clipped to

    color +- k sd,   sd^2 = mean over the 3x3 window (clipped at the border) of (colorA - colorB)^2 / 4,

per channel. The 3x3 mean gives each sd about nine degrees of freedom, so an sd far below the true one
(which would freeze noise in place) is rare; where the halves disagree strongly (fireflies, heavy-tailed
paths) sd is large and the denoiser is free. A region where every sample of both halves was black keeps
black: that is what the samples say. Pixels marked in `keep` (the exact pixels the step took as emission,
`service.stages.exact`) come out exactly as `color`; pixels marked in `free` (a renderer's emission
layer) are not clipped.

What it costs on ordinary frames (the benchmark's trimmed relL2, mean over frames, `python -m bench run
--sequences models/data/samples/shadows out/bench-data/fireflies`, against the commit before the clamp):
NOISE_K = 5 is the tightest of 3, 4 and 5 that keeps every pipeline within 3% of its relL2 before: on the
shadows sample flr 0.0382 -> 0.0389, bmfr 0.0494 -> 0.0496, crossregression 0.0601 -> 0.0600; on the
`fireflies` sequence crossregression 0.0324 -> 0.0330. K = 3 fixes more hard-case tiles but costs flr 8.6% on
the shadows sample.
"""

from __future__ import annotations

import numba
import numpy as np

NOISE_K = 5.0  # half-width of the allowed band, in standard deviations of the pixel estimate
NOISE_RADIUS = 1  # window half-size of the variance estimate, pixels (3x3)


def noise_clamp(
    out: np.ndarray,
    color: np.ndarray,
    color_a: np.ndarray,
    color_b: np.ndarray,
    keep: np.ndarray | None = None,
    free: np.ndarray | None = None,
    k: float = NOISE_K,
) -> np.ndarray:
    """`out` clipped to `color` +- k sd per pixel and channel (module docstring).

    out: (H, W, 3) float32 denoised radiance; color, color_a, color_b: (H, W, 3) float32 noisy radiance
    and its two halves, all linear; keep: (H, W, 3) float32 or None, pixels with any nonzero channel take
    `color`; free: (H, W, 3) float32 or None, pixels with any nonzero channel keep `out` unclipped (a
    renderer's `emission` layer: there the samples' binary coverage of an emitter's edge makes the halves
    agree by chance, and the noise-free emission already tells the denoiser what is exact). Returns a new
    (H, W, 3) float32 array. One parallel numba pass; `noise_clamp_reference` is the numpy twin.
    """
    if not k >= 0:
        raise ValueError(f"noise clamp k must be >= 0, got {k}")
    arrays = [np.ascontiguousarray(x, dtype=np.float32) for x in (out, color, color_a, color_b)]
    masks = [None if m is None else np.ascontiguousarray(m, dtype=np.float32) for m in (keep, free)]
    shapes = {x.shape for x in arrays + [m for m in masks if m is not None]}
    if len(shapes) != 1 or arrays[0].ndim != 3:
        raise ValueError(f"noise clamp: out, color, the halves and masks must share one (H, W, C) shape, got {shapes}")
    result = np.empty_like(arrays[0])
    keep32, free32 = (arrays[0] if m is None else m for m in masks)
    _clamp_kernel(*arrays, keep32, masks[0] is not None, free32, masks[1] is not None, np.float32(k), result)
    return result


def noise_sd_reference(color_a: np.ndarray, color_b: np.ndarray) -> np.ndarray:
    """(H, W, C) float64 sd of the pixel estimate (module docstring); numpy."""
    d2 = (color_a.astype(np.float64) - color_b.astype(np.float64)) ** 2
    height, width = d2.shape[:2]
    total, count = np.zeros_like(d2), np.zeros((height, width, 1))
    r = NOISE_RADIUS
    for dy in range(-r, r + 1):
        for dx in range(-r, r + 1):
            ys, yd = slice(max(dy, 0), height + min(dy, 0)), slice(max(-dy, 0), height + min(-dy, 0))
            xs, xd = slice(max(dx, 0), width + min(dx, 0)), slice(max(-dx, 0), width + min(-dx, 0))
            total[yd, xd] += d2[ys, xs]
            count[yd, xd] += 1.0
    return np.sqrt(total / count / 4.0)


def noise_clamp_reference(
    out: np.ndarray,
    color: np.ndarray,
    color_a: np.ndarray,
    color_b: np.ndarray,
    keep: np.ndarray | None = None,
    free: np.ndarray | None = None,
    k: float = NOISE_K,
) -> np.ndarray:
    """Plain-numpy twin of `noise_clamp`."""
    band = k * noise_sd_reference(color_a, color_b)
    clipped = np.clip(out, color - band, color + band)
    if free is not None:
        clipped = np.where(free.any(axis=-1, keepdims=True), out, clipped)
    if keep is not None:
        clipped = np.where(keep.any(axis=-1, keepdims=True), color, clipped)
    return clipped.astype(np.float32)


@numba.njit(parallel=True, cache=True, error_model="numpy")
def _clamp_kernel(out, color, a, b, keep, has_keep, free, has_free, k, result):  # pragma: no cover - jitted
    """A task per row: the 3-row column sums of (a - b)^2 along the interleaved (W * C) row, then the
    3-column sums as shifts by C, then the clip; pixels with a nonzero `free` value take `out` unclipped,
    those with a nonzero `keep` value take `color`."""
    height, width, channels = out.shape
    n = width * channels
    for y in numba.prange(height):
        y0, y1 = max(y - 1, 0), min(y + 2, height)
        column = np.zeros(n, np.float32)
        for yy in range(y0, y1):
            ra, rb = a[yy].reshape(n), b[yy].reshape(n)
            for i in range(n):
                d = ra[i] - rb[i]
                column[i] += d * d
        ra, rb = a[y].reshape(n), b[y].reshape(n)
        rc, ro, rr = color[y].reshape(n), out[y].reshape(n), result[y].reshape(n)
        scale = np.float32(0.25) / np.float32(y1 - y0)
        inner = scale / np.float32(min(width, 3))  # interior pixels sum three columns
        edge = scale / np.float32(min(width, 2))  # the first and last pixel two (one in a 1-pixel row)
        for i in range(channels, n - channels):  # interior: contiguous, vectorises
            band = k * np.sqrt((column[i - channels] + column[i] + column[i + channels]) * inner)
            rr[i] = min(max(ro[i], rc[i] - band), rc[i] + band)
        for c in range(channels):  # the first and last pixel of the row
            for i in (c, n - channels + c):
                total = column[i]
                if i >= channels:
                    total += column[i - channels]
                if i + channels < n:
                    total += column[i + channels]
                band = k * np.sqrt(total * edge)
                rr[i] = min(max(ro[i], rc[i] - band), rc[i] + band)
        if has_free:
            rf = free[y].reshape(n)
            for x in range(width):
                unclipped = False
                for c in range(channels):
                    unclipped = unclipped or rf[x * channels + c] != 0
                if unclipped:
                    for c in range(channels):
                        rr[x * channels + c] = ro[x * channels + c]
        if has_keep:
            rk = keep[y].reshape(n)
            for x in range(width):
                kept = False
                for c in range(channels):
                    kept = kept or rk[x * channels + c] != 0
                if kept:
                    for c in range(channels):
                        rr[x * channels + c] = rc[x * channels + c]
