"""Temporal stages of SVGF (Schied et al. 2017, secs. 4.1-4.2): accumulation of colour and luminance
moments over reprojected history, and the per-pixel luminance variance that steers the a-trous filter
(`service.stages.atrous`).

    history  n = n_prev + 1 where the reprojection is valid, else 1
    colour   c = lerp(c_prev, c, max(alpha_c, 1/n))          (sec. 4.1, exponential moving average)
    moments  (mu1, mu2) = lerp(prev, (l, l^2), max(alpha_m, 1/n))   (sec. 4.2)
    variance = max(0, mu2 - mu1^2) where n >= 4, else a spatial estimate from a 7x7 edge-aware
               window (sec. 4.2; Falcor `SVGFFilterMoments`), see `estimate_variance`; with the two half
               buffers, the lesser of that and their own estimate (`halves_variance`, an extension).

As an extension, the history is clamped to the current frame's local colour box before blending
(`clamp_history`), which the paper leaves to A-SVGF (Schied 2018) but real-time engines routinely do.

The 1/n floor makes the first frames of a history a plain average rather than a slow blend from
an empty start.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numba import njit, prange

from service.kernels.fill import filled
from service.stages.atrous import LUMINANCE_WEIGHTS, EdgeGuides, edge_aware_filter, luminance

ALPHA_COLOR = 0.2  # Schied 2017 sec. 4.1: blend weight of the new frame in the colour history
ALPHA_MOMENTS = 0.2  # Schied 2017 sec. 4.2: blend weight of the new frame in the moment history
MIN_HISTORY = 4  # frames; Schied 2017 sec. 4.2: below it the variance is estimated spatially
HALVES_RADIUS = 1  # pixels: `halves_variance` averages over 3x3 (docs/benchmarks.md)
MOMENTS_RADIUS = 3  # pixels; 7x7 spatial moment window (Falcor SVGFFilterMoments)
MOMENTS_SIGMA_LUMINANCE = 10.0  # Falcor SVGFFilterMoments: constant phi_l of the spatial estimate
MOMENTS_DEPTH_SCALE = 3.0  # Falcor SVGFFilterMoments: phi_z = 3 |grad z| |p - q|


@dataclass(frozen=True)
class TemporalParams:
    alpha_color: float = ALPHA_COLOR  # minimum weight of the current frame in the colour average
    alpha_moments: float = ALPHA_MOMENTS  # minimum weight of the current frame in the moment average
    min_history: int = MIN_HISTORY  # frames of history needed for the temporal variance estimate
    sigma_normal: float = 128.0  # sigma_n of the spatial estimate's edge-stopping (as the a-trous filter)
    sigma_depth: float = 1.0  # sigma_z of the spatial estimate (times MOMENTS_DEPTH_SCALE)
    clamp_radius: int = 1  # window half-size of the history clamp, pixels (extension; see clamp_history)
    clamp_spread: float | None = 1.0  # history clamp box: local mean +- this * local std; None: no clamp

    def __post_init__(self) -> None:
        for name in ("alpha_color", "alpha_moments"):
            if not 0.0 < getattr(self, name) <= 1.0:
                raise ValueError(f"{name} must be in (0, 1], got {getattr(self, name)}")


def luminance_moments(color: np.ndarray) -> np.ndarray:
    """(H, W, 3) float32 linear RGB -> (H, W, 2) float32 first and second moment (l, l^2) of luminance."""
    lum = luminance(color)
    return np.stack([lum, lum * lum], axis=-1)


def accumulate_numpy(
    color: np.ndarray,
    moments: np.ndarray,
    prev_color: np.ndarray,
    prev_moments: np.ndarray,
    prev_history: np.ndarray,
    valid: np.ndarray,
    params: TemporalParams,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Reference implementation of `accumulate` in numpy (same arguments and results)."""
    history = np.where(valid, prev_history + np.float32(1.0), np.float32(1.0)).astype(np.float32)
    inverse = np.float32(1.0) / history
    alpha_c = np.maximum(np.float32(params.alpha_color), inverse)[..., None]
    alpha_m = np.maximum(np.float32(params.alpha_moments), inverse)[..., None]
    keep = valid[..., None]
    out_color = np.where(keep, prev_color + alpha_c * (color - prev_color), color)
    out_moments = np.where(keep, prev_moments + alpha_m * (moments - prev_moments), moments)
    return out_color.astype(np.float32), out_moments.astype(np.float32), history


@njit(parallel=True, cache=True, error_model="numpy")
def _accumulate_kernel(color, moments, prev_color, prev_moments, prev_history, valid, alpha_color, alpha_moments):
    height, width, _ = color.shape
    out_color = np.empty((height, width, 3), np.float32)
    out_moments = np.empty((height, width, 2), np.float32)
    history = np.empty((height, width), np.float32)
    one = np.float32(1.0)
    for y in prange(height):
        for x in range(width):
            keep = valid[y, x]
            n = prev_history[y, x] + one if keep else one
            history[y, x] = n
            alpha_c, alpha_m = max(alpha_color, one / n), max(alpha_moments, one / n)
            for c in range(3):
                prev = prev_color[y, x, c]
                out_color[y, x, c] = prev + alpha_c * (color[y, x, c] - prev) if keep else color[y, x, c]
            for c in range(2):
                prev = prev_moments[y, x, c]
                out_moments[y, x, c] = prev + alpha_m * (moments[y, x, c] - prev) if keep else moments[y, x, c]
    return out_color, out_moments, history


def accumulate(
    color: np.ndarray,
    moments: np.ndarray,
    prev_color: np.ndarray,
    prev_moments: np.ndarray,
    prev_history: np.ndarray,
    valid: np.ndarray,
    params: TemporalParams,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Blend the current frame into its reprojected history (Schied 2017 secs. 4.1-4.2).

    color: (H, W, 3) float32 current (demodulated) radiance; moments: (H, W, 2) float32 from
    `luminance_moments`; prev_color, prev_moments, prev_history: the same and (H, W) float32 history
    lengths in frames, reprojected from the previous frame; valid: (H, W) bool reprojection validity.
    Returns (color, moments, history) of shapes (H, W, 3), (H, W, 2), (H, W), float32. Where invalid
    the history restarts: history 1, colour and moments of the current frame. Compiled (numba, rows in
    parallel); parity with `accumulate_numpy` is tested.
    """
    return _accumulate_kernel(
        *(np.ascontiguousarray(a, np.float32) for a in (color, moments, prev_color, prev_moments, prev_history)),
        np.ascontiguousarray(valid, np.bool_),
        np.float32(params.alpha_color),
        np.float32(params.alpha_moments),
    )


def box_mean(values: np.ndarray, radius: int) -> np.ndarray:
    """Mean of (H, W, C) float32 `values` over the in-frame part of each pixel's (2r+1)^2 window.

    Separable sums of shifted slices (no padding): cheap for the small radii it serves."""
    height, width = values.shape[:2]
    out = values.astype(np.float32, copy=True)
    count = np.ones((height, width, 1), np.float32)
    for axis, size in ((0, height), (1, width)):
        src, src_count = out.copy(), count.copy()
        for shift in range(1, min(radius, size - 1) + 1):
            for lo, hi in ((shift, 0), (0, shift)):  # neighbour above/left, then below/right
                dst = [slice(None)] * 2
                nb = [slice(None)] * 2
                dst[axis], nb[axis] = slice(lo, size - hi), slice(hi, size - lo)
                out[tuple(dst)] += src[tuple(nb)]
                count[tuple(dst)] += src_count[tuple(nb)]
    return out / count


def clamp_history_numpy(
    prev_color: np.ndarray, prev_moments: np.ndarray, color: np.ndarray, radius: int, spread: float
) -> tuple[np.ndarray, np.ndarray]:
    """Reference implementation of `clamp_history` in numpy (same arguments and results)."""
    mean = box_mean(color, radius)
    std = np.sqrt(np.maximum(box_mean(color * color, radius) - mean * mean, np.float32(0.0)))
    half = np.float32(spread) * std
    clamped = np.clip(prev_color, mean - half, mean + half)
    lum_old, lum_new = luminance(prev_color), luminance(clamped)
    second = prev_moments[..., 1] - lum_old * lum_old + lum_new * lum_new
    return clamped, np.stack([lum_new, second], axis=-1).astype(np.float32)


@njit(parallel=True, cache=True, error_model="numpy")
def _clamp_kernel(prev_color, prev_moments, color, radius, spread):
    """`clamp_history_numpy` row by row: separable box sums of colour and colour^2 over the flat (H, 3W) rows, a
    column offset dx being a flat offset 3 dx (contiguous slices, SIMD)."""
    height, width, _ = color.shape
    flat = color.reshape(height, 3 * width)
    prev_flat = prev_color.reshape(height, 3 * width)
    clamped = np.empty((height, width, 3), np.float32)
    out_moments = np.empty((height, width, 2), np.float32)
    clamped_flat = clamped.reshape(height, 3 * width)
    wr, wg, wb = np.float32(LUMINANCE_WEIGHTS[0]), np.float32(LUMINANCE_WEIGHTS[1]), np.float32(LUMINANCE_WEIGHTS[2])
    for yy in prange(height):
        y = np.int64(yy)
        column_sum = flat[y].copy()
        column_sum2 = np.empty(3 * width, np.float32)
        row = flat[y]
        for i in range(3 * width):
            column_sum2[i] = row[i] * row[i]
        rows = 1
        for shift in range(1, radius + 1):
            for yn in (y - shift, y + shift):
                if 0 <= yn < height:
                    rows += 1
                    other = flat[yn]
                    for i in range(3 * width):
                        column_sum[i] += other[i]
                        column_sum2[i] += other[i] * other[i]
        box = column_sum.copy()
        box2 = column_sum2.copy()
        count = filled(3 * width, 1.0, np.float32)
        for shift in range(1, radius + 1):
            for dx in (-shift, shift):
                x0, x1 = 3 * max(0, -dx), 3 * min(width, width - dx)
                if x0 >= x1:
                    continue
                b, b2, n = box[x0:x1], box2[x0:x1], count[x0:x1]
                s, s2 = column_sum[x0 + 3 * dx:x1 + 3 * dx], column_sum2[x0 + 3 * dx:x1 + 3 * dx]
                for t in range(x1 - x0):
                    b[t] += s[t]
                    b2[t] += s2[t]
                    n[t] += np.float32(1.0)
        prev_row, out_row = prev_flat[y], clamped_flat[y]
        for i in range(3 * width):
            total = count[i] * np.float32(rows)
            mean = box[i] / total
            half = spread * np.sqrt(max(box2[i] / total - mean * mean, np.float32(0.0)))
            out_row[i] = min(max(prev_row[i], mean - half), mean + half)
        for x in range(width):
            lum_old = wr * prev_color[y, x, 0] + wg * prev_color[y, x, 1] + wb * prev_color[y, x, 2]
            lum_new = wr * clamped[y, x, 0] + wg * clamped[y, x, 1] + wb * clamped[y, x, 2]
            out_moments[y, x, 0] = lum_new
            out_moments[y, x, 1] = prev_moments[y, x, 1] - lum_old * lum_old + lum_new * lum_new
    return clamped, out_moments


def clamp_history(
    prev_color: np.ndarray, prev_moments: np.ndarray, color: np.ndarray, radius: int, spread: float
) -> tuple[np.ndarray, np.ndarray]:
    """Clamp the reprojected colour history to the current frame's local colour box, mean +- spread * std
    over a (2r+1)^2 window, per channel. An extension to SVGF (the colour clamping of temporal
    anti-aliasing, Karis 2014) that cuts the lag of moving shadows and highlights, which the motion of
    the surface does not carry. The moment history is shifted with it (first moment to the clamped
    luminance, second moment keeping its variance), so the change does not read as noise.

    prev_color: (H, W, 3), prev_moments: (H, W, 2) reprojected history; color: (H, W, 3) current frame;
    all float32. Returns (color, moments) history of the same shapes, float32.

    Compiled (numba, rows in parallel); parity with `clamp_history_numpy` is tested.
    """
    return _clamp_kernel(
        np.ascontiguousarray(prev_color, np.float32),
        np.ascontiguousarray(prev_moments, np.float32),
        np.ascontiguousarray(color, np.float32),
        int(radius),
        np.float32(spread),
    )


def _bounding_box(mask: np.ndarray, margin: int) -> tuple[slice, slice]:
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    height, width = mask.shape
    return (
        slice(max(0, rows[0] - margin), min(height, rows[-1] + margin + 1)),
        slice(max(0, cols[0] - margin), min(width, cols[-1] + margin + 1)),
    )


def halves_variance(color_a: np.ndarray, color_b: np.ndarray, radius: int = HALVES_RADIUS) -> np.ndarray:
    """Variance of the luminance of (A + B) / 2 from the two half estimates alone: the mean over each pixel's
    (2 radius + 1)^2 window of (l(A) - l(B))^2 / 4 (A and B independent, each of variance s^2: the mean's is
    s^2 / 2 = E[(A - B)^2] / 4).

    color_a, color_b: (H, W, 3) float32 linear radiance, as the filtered colour is (demodulated and scaled
    alike). Returns (H, W) float32 >= 0 (+inf where the square overflows). Unlike the spatial estimate of
    `estimate_variance`, it does not count an edge in the picture (a thin reflection, a shadow's border) as
    noise: both halves show the edge. It trusts the halves to be independent, as the step's noise clamp does."""
    diff = luminance(color_a) - luminance(color_b)
    return box_mean((np.float32(0.25) * diff * diff)[..., None], radius)[..., 0]


def estimate_variance(
    moments: np.ndarray,
    current_moments: np.ndarray,
    history: np.ndarray,
    color: np.ndarray,
    guides: EdgeGuides,
    params: TemporalParams,
    halves: Callable[[tuple[slice, slice]], np.ndarray] | None = None,
) -> np.ndarray:
    """Luminance variance per pixel of the accumulated colour (Schied 2017 sec. 4.2).

    moments: (H, W, 2) accumulated moments and history: (H, W) from `accumulate`; current_moments:
    (H, W, 2) moments of the current frame alone; color: (H, W, 3) current frame (its luminance steers
    the spatial weights); guides: EdgeGuides; all float32; halves: None, or a function of a (rows, columns)
    slice pair giving `halves_variance` over that crop of the current frame, in the units of `color`'s
    luminance squared (the halves demodulated and scaled as `color` is). Returns (H, W) float32 >= 0:
    max(0, mu2 - mu1^2) of the accumulated moments where history >= min_history; elsewhere (sec. 4.2)
    a spatial estimate: the current frame's moments averaged over a 7x7 edge-aware window, which
    gives the variance of one frame, divided by the history length, since the accumulated colour
    averages that many frames. (Falcor averages the accumulated moments and multiplies by 4 / history;
    on a moving shadow that counts the change as noise and blurs it away.) Only the bounding box of the
    short-history pixels is filtered, and only there are the halves read. With `halves`, the lesser of the
    spatial estimate and halves / history: the spatial window counts the picture's own edges as noise,
    which blurs detail no G-buffer shows (near-mirror reflections under a sun: the `glints` hard case's
    worst tile, `python -m bench.hard_cases table`, 1.18x the noisy input's -> 1.0x). `make bench`,
    2026-11-27: relL2 0.5-2.3% lower on its four sequences, temporal error 2% and 0.9% lower on shadows and
    disocclusion, 0.1% higher on fireflies.
    """
    variance = np.maximum(moments[..., 1] - moments[..., 0] ** 2, np.float32(0.0))
    short = history < params.min_history
    if not short.any():
        return variance
    box = _bounding_box(short, MOMENTS_RADIUS)
    crop = EdgeGuides(*(np.ascontiguousarray(a[box]) for a in (guides.depth, guides.depth_gradient, guides.normal)))
    lum = luminance(color[box])
    filtered = edge_aware_filter(
        np.ascontiguousarray(current_moments[box]),
        lum,
        np.full(lum.shape, MOMENTS_SIGMA_LUMINANCE, np.float32),
        crop,
        np.ones(2 * MOMENTS_RADIUS + 1, np.float32),
        1,
        params.sigma_depth * MOMENTS_DEPTH_SCALE,
        params.sigma_normal,
    )
    spatial = np.maximum(filtered[..., 1] - filtered[..., 0] ** 2, np.float32(0.0)) / history[box]
    if halves is not None:
        spatial = np.minimum(spatial, halves(box) / history[box])
    variance[box][short[box]] = spatial[short[box]]
    return variance
