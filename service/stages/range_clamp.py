"""Clamp a filter's output to the range of its noisy input over a local window.

Linear regressions (BMFR, FLR, cross-regression) extrapolate: where a feature is an outlier of its
window, the fitted plane can leave the range of every radiance value the fit saw (negative radiance
from non-negative input, overshoot above a firefly's neighbourhood). Clipping each output pixel to the
minimum and maximum of the noisy input over the (2r+1)^2 window around it removes that energy the input
cannot explain, leaves any output inside the data range untouched, and keeps a constant image constant.
The sliding min/max is separable and uses the doubling trick: O(log r) whole-array operations per axis.
"""

from __future__ import annotations

from collections.abc import Callable

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


def local_range(image: np.ndarray, radius: int) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel min and max of `image` over the (2r+1)^2 window clipped to the frame.

    image: (H, W, C) float32. Returns (lo, hi), both (H, W, C) float32.
    """
    if radius < 0:
        raise ValueError(f"radius must be >= 0, got {radius}")
    lo = _sliding(np.minimum, _sliding(np.minimum, image, radius, 0), radius, 1)
    hi = _sliding(np.maximum, _sliding(np.maximum, image, radius, 0), radius, 1)
    return lo, hi


def clamp_to_local_range(output: np.ndarray, image: np.ndarray, radius: int) -> np.ndarray:
    """`output` clipped per pixel and channel to the range of `image` over the window of `radius`.

    output, image: (H, W, C) float32 linear radiance (the denoised and the noisy frame). Returns
    (H, W, C) float32.
    """
    lo, hi = local_range(image, radius)
    return np.clip(output, lo, hi)
