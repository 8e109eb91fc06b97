"""Clamp a filter's output to the range of its noisy input over a local window.

Linear regressions (BMFR, FLR, cross-regression) extrapolate: where a feature is an outlier of its
window, the fitted plane can leave the range of every radiance value the fit saw (negative radiance
from non-negative input, overshoot above a firefly's neighbourhood). Clipping each output pixel to the
minimum and maximum of the noisy input over the (2r+1)^2 window around it removes that energy the input
cannot explain, leaves any output inside the data range untouched, and keeps a constant image constant.

The numba kernel works row by row (parallel over output rows): the min/max over the 2r+1 rows of the
window into a row buffer, then over the 2r+1 columns, where in the interleaved (W, C) row a column
offset d is the constant index shift C d, so both passes are contiguous and vectorise. O(r) per value,
no temporaries of the frame's size. `local_range_reference` is the plain-numpy twin (separable doubling:
O(log r) whole-array operations per axis).
"""

from __future__ import annotations

from collections.abc import Callable

import numba
import numpy as np

Reduce = Callable[[np.ndarray, np.ndarray], np.ndarray]


def _sliding(op: Reduce, image: np.ndarray, radius: int, axis: int) -> np.ndarray:
    """op (np.minimum/np.maximum) over the window [i - r, i + r] along `axis`, borders clipped."""
    n = image.shape[axis]
    width = 2 * radius + 1
    pad = [(0, 0)] * image.ndim
    pad[axis] = (radius, radius)
    acc = np.pad(image, pad, mode="edge")  # edge values lie inside the data range: same as clipping
    span = 1  # acc[i] = op over padded[i : i + span]
    while 2 * span <= width:
        length = acc.shape[axis]
        acc = op(np.take(acc, np.arange(0, length - span), axis), np.take(acc, np.arange(span, length), axis))
        span *= 2
    rest = width - span
    return op(np.take(acc, np.arange(0, n), axis), np.take(acc, np.arange(rest, rest + n), axis))


def _check_radius(radius: int) -> None:
    if radius < 0:
        raise ValueError(f"radius must be >= 0, got {radius}")


def local_range(image: np.ndarray, radius: int) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel min and max of `image` over the (2r+1)^2 window clipped to the frame.

    image: (H, W, C) float32. Returns (lo, hi), both (H, W, C) float32. numba kernel;
    `local_range_reference` is the plain-numpy twin.
    """
    _check_radius(radius)
    image = np.ascontiguousarray(image, dtype=np.float32)
    lo, hi = np.empty_like(image), np.empty_like(image)
    _range_kernel(image, image, int(radius), False, lo, hi)
    return lo, hi


def local_range_reference(image: np.ndarray, radius: int) -> tuple[np.ndarray, np.ndarray]:
    """Plain-numpy twin of `local_range`."""
    _check_radius(radius)
    lo = _sliding(np.minimum, _sliding(np.minimum, image, radius, 0), radius, 1)
    hi = _sliding(np.maximum, _sliding(np.maximum, image, radius, 0), radius, 1)
    return lo, hi


def clamp_to_local_range(output: np.ndarray, image: np.ndarray, radius: int) -> np.ndarray:
    """`output` clipped per pixel and channel to the range of `image` over the window of `radius`.

    output, image: (H, W, C) float32 linear radiance (the denoised and the noisy frame). Returns
    (H, W, C) float32. One fused numba pass (no lo/hi frames); `clamp_to_local_range_reference` is the
    plain-numpy twin.
    """
    _check_radius(radius)
    image = np.ascontiguousarray(image, dtype=np.float32)
    output = np.ascontiguousarray(output, dtype=np.float32)
    out = np.empty_like(output)
    _range_kernel(image, output, int(radius), True, out, out)
    return out


def clamp_to_local_range_reference(output: np.ndarray, image: np.ndarray, radius: int) -> np.ndarray:
    """Plain-numpy twin of `clamp_to_local_range`."""
    lo, hi = local_range_reference(image, radius)
    return np.clip(output, lo, hi).astype(np.float32)


@numba.njit(inline="always")
def _fold(lo, hi, src_lo, src_hi, n):
    """lo = min(lo, src_lo), hi = max(hi, src_hi) over the first n values."""
    for i in range(n):
        a, b = src_lo[i], src_hi[i]
        lo[i] = a if a < lo[i] else lo[i]
        hi[i] = b if b > hi[i] else hi[i]


@numba.njit(parallel=True, cache=True)
def _range_kernel(image, output, radius, clamp, lo_out, hi_out):
    """clamp: lo_out[y] = clip(output[y], lo, hi); else lo_out, hi_out = lo, hi."""
    height, width, channels = image.shape
    n = width * channels
    flat = image.reshape(height, n)
    for y in numba.prange(height):
        vlo = flat[max(0, y - radius)].copy()  # min / max over the window's rows
        vhi = vlo.copy()
        for yy in range(max(0, y - radius) + 1, min(height, y + radius + 1)):
            _fold(vlo, vhi, flat[yy], flat[yy], n)
        lo, hi = vlo.copy(), vhi.copy()  # then over its columns: offset d is the index shift C d
        for d in range(1, min(radius, width - 1) + 1):
            m = n - d * channels  # loops index 1-D views by the counter only, so LLVM vectorises them
            _fold(lo[:m], hi[:m], vlo[n - m :], vhi[n - m :], m)
            _fold(lo[n - m :], hi[n - m :], vlo[:m], vhi[:m], m)
        if clamp:
            src, dst = output[y].reshape(n), lo_out[y].reshape(n)
            for i in range(n):
                v = src[i]
                v = lo[i] if v < lo[i] else v
                dst[i] = hi[i] if v > hi[i] else v
        else:
            lo_out[y].reshape(n)[:] = lo
            hi_out[y].reshape(n)[:] = hi
