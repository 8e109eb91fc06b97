"""Clamp a filter's output to the range of its noisy input over a local window.

Linear regressions (BMFR, FLR, cross-regression) extrapolate: where a feature is an outlier of its
window, the fitted plane can leave the range of every radiance value the fit saw (negative radiance
from non-negative input, overshoot above a firefly's neighbourhood). Clipping each output pixel to the
minimum and maximum of the noisy input over the (2r+1)^2 window around it removes that energy the input
cannot explain, leaves any output inside the data range untouched, and keeps a constant image constant.

The numba kernel works on bands of output rows (one per thread): the min/max over the 2r+1 rows of
each window by van Herk / Gil-Werman (running min/max backward over blocks of 2r+1 rows and forward as
the window moves down: 3 operations per value, whatever r), then over its 2r+1 columns by tripling and doubling
spans on the padded row, where in the interleaved (W, C) row a column offset d is the constant index
shift C d (O(log r) passes). Every pass is contiguous and vectorises; no temporaries of the frame's size.
`local_range_reference` is the plain-numpy twin (separable doubling: O(log r) whole-array operations per
axis).
"""

from __future__ import annotations

from collections.abc import Callable

import numba
import numpy as np

from service.kernels.parallel import rows_per_thread

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


def check_radius(radius: int) -> None:
    """ValueError unless radius >= 0 (pixels)."""
    if radius < 0:
        raise ValueError(f"radius must be >= 0, got {radius}")


def local_range(image: np.ndarray, radius: int) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel min and max of `image` over the (2r+1)^2 window clipped to the frame.

    image: (H, W, C) float32. Returns (lo, hi), both (H, W, C) float32. numba kernel;
    `local_range_reference` is the plain-numpy twin.
    """
    check_radius(radius)
    image = np.ascontiguousarray(image, dtype=np.float32)
    lo, hi = np.empty_like(image), np.empty_like(image)
    _range_kernel(image, image, int(radius), False, rows_per_thread(image.shape[0]), lo, hi)
    return lo, hi


def local_range_reference(image: np.ndarray, radius: int) -> tuple[np.ndarray, np.ndarray]:
    """Plain-numpy twin of `local_range`."""
    check_radius(radius)
    lo = _sliding(np.minimum, _sliding(np.minimum, image, radius, 0), radius, 1)
    hi = _sliding(np.maximum, _sliding(np.maximum, image, radius, 0), radius, 1)
    return lo, hi


def clamp_to_local_range(output: np.ndarray, image: np.ndarray, radius: int) -> np.ndarray:
    """`output` clipped per pixel and channel to the range of `image` over the window of `radius`.

    output, image: (H, W, C) float32 linear radiance (the denoised and the noisy frame). Returns
    (H, W, C) float32. One fused numba pass (no lo/hi frames); `clamp_to_local_range_reference` is the
    plain-numpy twin.
    """
    check_radius(radius)
    image = np.ascontiguousarray(image, dtype=np.float32)
    output = np.ascontiguousarray(output, dtype=np.float32)
    out = np.empty_like(output)
    _range_kernel(image, output, int(radius), True, rows_per_thread(image.shape[0]), out, out)
    return out


def clamp_to_local_range_reference(output: np.ndarray, image: np.ndarray, radius: int) -> np.ndarray:
    """Plain-numpy twin of `clamp_to_local_range`."""
    lo, hi = local_range_reference(image, radius)
    return np.clip(output, lo, hi).astype(np.float32)


@numba.njit(inline="always")
def _backward_scan(flat, first, g, lo, hi):
    """Running min (lo) and max (hi) backward over the g frame rows first .. first + g - 1: lo[i] over rows
    first + i .. first + g - 1; rows outside the frame count as +inf / -inf."""
    height, n = flat.shape
    for step in range(g):
        i = g - 1 - step
        y = first + i
        dst_lo, dst_hi = lo[i], hi[i]
        if 0 <= y < height:
            src = flat[y]
            if step == 0:
                dst_lo[:] = src
                dst_hi[:] = src
            else:
                prev_lo, prev_hi = lo[i + 1], hi[i + 1]
                for j in range(n):
                    v = src[j]
                    dst_lo[j] = v if v < prev_lo[j] else prev_lo[j]
                    dst_hi[j] = v if v > prev_hi[j] else prev_hi[j]
        elif step == 0:
            dst_lo[:] = np.inf
            dst_hi[:] = -np.inf
        else:
            dst_lo[:] = lo[i + 1]
            dst_hi[:] = hi[i + 1]


@numba.njit(inline="always")
def _min_max_pass(lo, hi, step, out_lo, out_hi, n):
    """out_lo[i] = min(lo[i], lo[i + step]), out_hi[i] = max(hi[i], hi[i + step]), i < n."""
    ahead_lo, ahead_hi = lo[step:], hi[step:]
    for i in range(n):
        a, b = ahead_lo[i], lo[i]
        out_lo[i] = a if a < b else b
        a, b = ahead_hi[i], hi[i]
        out_hi[i] = a if a > b else b


@numba.njit(inline="always")
def _min_max_pass3(lo, hi, step, out_lo, out_hi, n):
    """out_lo[i] = min(lo[i], lo[i + step], lo[i + 2 step]), out_hi[i] = max(hi[i], hi[i + step],
    hi[i + 2 step]), i < n."""
    lo_1, hi_1, lo_2, hi_2 = lo[step:], hi[step:], lo[2 * step :], hi[2 * step :]
    for i in range(n):
        a, b, c = lo[i], lo_1[i], lo_2[i]
        m = a if a < b else b
        out_lo[i] = m if m < c else c
        a, b, c = hi[i], hi_1[i], hi_2[i]
        m = a if a > b else b
        out_hi[i] = m if m > c else c


@numba.njit(inline="always")
def row_range(lo, hi, spare_lo, spare_hi, g, shift):
    """Padded rows lo, hi -> min (max) of lo (hi) at i + d shift, d = 0 .. g - 1, for i < len(lo) - (g - 1)
    shift: spans tripled (1, 3, 9, ..) while they fit in g, then doubled or, last, two overlapping spans
    (g = 17: 1, 3, 9, 17, three passes where doubling takes five). Passes alternate between the rows and
    the spare rows (no in-place pass: it would read ahead of what it writes, which keeps LLVM from
    vectorising it; so does swapping the names of the buffers). Returns True when the result is in the
    spare rows."""
    span, spare, length = 1, False, lo.shape[0]
    while span < g:
        if 3 * span <= g:  # tripling
            n = length - (3 * span - 1) * shift
            if spare:
                _min_max_pass3(spare_lo, spare_hi, span * shift, lo, hi, n)
            else:
                _min_max_pass3(lo, hi, span * shift, spare_lo, spare_hi, n)
            span *= 3
        else:  # doubling, or the final overlap
            step = min(span, g - span)
            n = length - (span + step - 1) * shift
            if spare:
                _min_max_pass(spare_lo, spare_hi, step * shift, lo, hi, n)
            else:
                _min_max_pass(lo, hi, step * shift, spare_lo, spare_hi, n)
            span += step
        spare = not spare
    return spare


@numba.njit(inline="always")
def emit_range_row(lo, hi, output, clamp, lo_out, hi_out):
    """One row of n = W C values: lo_out = clip(output, lo, hi) when `clamp`, else lo_out, hi_out = lo, hi
    (lo, hi: at least n values; output, lo_out, hi_out: (W, C) or (n,))."""
    n = lo_out.size
    dst = lo_out.reshape(n)
    if clamp:
        src = output.reshape(n)
        for j in range(n):
            v = src[j]
            v = lo[j] if v < lo[j] else v
            dst[j] = hi[j] if v > hi[j] else v
    else:
        dst[:] = lo[:n]
        hi_out.reshape(n)[:] = hi[:n]


@numba.njit(inline="always")
def range_scratch(radius, width, channels):
    """New float32 scratch (scans, rows) for `window_range` on rows of `width` pixels of `channels`."""
    n = width * channels
    return np.empty((2, 2 * radius + 1, n), np.float32), np.empty((6, n + 2 * radius * channels), np.float32)


@numba.njit(inline="always")
def window_range(flat, channels, y, y0, radius, scans, rows):
    """The min and max over the window of `radius` around every value of row y of flat (H, n) float32,
    n = W C interleaved (C = channels): frame rows y - r ... y + r, clipped to the frame, and r pixels either
    side in the same channel. A band of rows y0, y0 + 1, ... is taken in order, one call per row: frame rows
    go in blocks of g = 2r+1 from the band's first window on (van Herk / Gil-Werman), and a window starting
    at row offset o of block k is the backward scan of block k at o (made at o = 0, kept in scans (2, g, n)
    float32: lo, hi) and the running min / max of block k+1's rows up to o - 1, which each call extends by
    the window's new last row (rows[4], rows[5]; a forward scan of g rows kept as well would put twice the
    scratch in L2). Then along the row (`row_range`) in rows[0:4]
    (lo, hi, spare lo, spare hi); rows: (6, n + 2 C r) float32, both from `range_scratch`. Returns True
    when the result, lo and hi at [0, n), is in rows[2], rows[3], False when in rows[0], rows[1] (the
    caller branches: a chosen name would keep its loops from vectorising)."""
    height, n = flat.shape
    g = 2 * radius + 1
    pad = radius * channels  # +inf / -inf columns each side of a padded row
    k, o = (y - y0) // g, (y - y0) % g
    row_lo, row_hi = rows[0], rows[1]
    mid_lo, mid_hi = row_lo[pad : pad + n], row_hi[pad : pad + n]
    fore_lo, fore_hi = rows[4, :n], rows[5, :n]
    a_lo, a_hi = scans[0, o], scans[1, o]
    if o == 0:
        _backward_scan(flat, y0 - radius + k * g, g, scans[0], scans[1])
        mid_lo[:] = a_lo
        mid_hi[:] = a_hi
        fore_lo[:] = np.inf
        fore_hi[:] = -np.inf
    elif y + radius < height:  # the window's new last row joins the forward part
        src = flat[y + radius]
        for j in range(n):
            v = src[j]
            f_lo = v if v < fore_lo[j] else fore_lo[j]
            f_hi = v if v > fore_hi[j] else fore_hi[j]
            fore_lo[j], fore_hi[j] = f_lo, f_hi
            mid_lo[j] = a_lo[j] if a_lo[j] < f_lo else f_lo
            mid_hi[j] = a_hi[j] if a_hi[j] > f_hi else f_hi
    else:
        for j in range(n):
            mid_lo[j] = a_lo[j] if a_lo[j] < fore_lo[j] else fore_lo[j]
            mid_hi[j] = a_hi[j] if a_hi[j] > fore_hi[j] else fore_hi[j]
    row_lo[:pad] = np.inf  # the padding, which the last row's passes overwrote
    row_lo[pad + n :] = np.inf
    row_hi[:pad] = -np.inf
    row_hi[pad + n :] = -np.inf
    return row_range(row_lo, row_hi, rows[2], rows[3], g, channels)


@numba.njit(parallel=True, cache=True, error_model="numpy")
def _range_kernel(image, output, radius, clamp, rows_per_task, lo_out, hi_out):
    """clamp: lo_out[y] = clip(output[y], lo, hi); else lo_out, hi_out = lo, hi; lo and hi the window range
    of each row (`window_range`), a band of rows_per_task rows per task."""
    height, width, channels = image.shape
    flat = image.reshape(height, width * channels)
    for task in numba.prange(-(-height // rows_per_task)):
        y0 = task * rows_per_task
        scans, rows = range_scratch(radius, width, channels)
        for y in range(y0, min(height, y0 + rows_per_task)):
            if window_range(flat, channels, y, y0, radius, scans, rows):
                emit_range_row(rows[2], rows[3], output[y], clamp, lo_out[y], hi_out[y])
            else:
                emit_range_row(rows[0], rows[1], output[y], clamp, lo_out[y], hi_out[y])
