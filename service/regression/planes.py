"""Channel-first planes, the layout of the regressions: (C, H, W) float32, so that the numba kernels stream
along x. Conversions from and to (H, W, C) pixels (`to_planes`, `from_planes`, `channel_planes` with
albedo demodulation, `interleave_row` for one row inside a kernel), per-channel standardisation
(`standardise`) and the 8-neighbour mean (`neighbour_mean`). Each numba pass has a `*_reference` twin.
"""

from __future__ import annotations

import numba
import numpy as np

from service.kernels.window import overlap, window_offsets
from service.stages.albedo import albedo_factor, demodulate


def neighbour_mean(planes: np.ndarray) -> np.ndarray:
    """Mean of the up-to-8 neighbours of each pixel in its 3x3 window, the pixel itself excluded.

    planes: (K, H, W) float32. Neighbours outside the frame are left out of the mean; a 1x1 frame has no
    neighbour and gets its own value. Returns (K, H, W) float32.
    """
    k, height, width = planes.shape
    total = np.zeros_like(planes)
    count = np.zeros((height, width), np.float32)
    for dy, dx in window_offsets(1):
        if dy == 0 and dx == 0:
            continue
        pair = overlap(height, width, dy, dx)
        if pair is None:
            continue
        (cy, cx), (ny, nx) = pair
        total[:, cy, cx] += planes[:, ny, nx]
        count[cy, cx] += 1.0
    lonely = count == 0
    total[:, lonely] = planes[:, lonely]
    return total / np.maximum(count, 1.0)


def to_planes(image: np.ndarray) -> np.ndarray:
    """(H, W, C) -> contiguous (C, H, W) float32."""
    return np.ascontiguousarray(np.moveaxis(np.asarray(image, np.float32), -1, 0))


def from_planes(planes: np.ndarray) -> np.ndarray:
    """(C, H, W) -> contiguous (H, W, C) float32."""
    return np.ascontiguousarray(np.moveaxis(planes, 0, -1), dtype=np.float32)


def standardise(planes: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """Each plane minus its mean, over its standard deviation (planes that do not vary become 0).

    planes: (K, H, W) float32. A regression with a constant term is unchanged by this affine change of
    features; it puts every feature on unit scale, which the absolute ridge floor and float32 moments need.
    out: (K, H, W) float32 to write into (`planes` itself: in place), or None for a new array. Returns it.
    numba kernel (float64 sums, parallel over blocks of every plane); `standardise_reference` is the
    plain-numpy twin.
    """
    planes = np.ascontiguousarray(planes, dtype=np.float32)
    out = np.empty_like(planes) if out is None else out
    if planes.size:
        _standardise_kernel(planes.reshape(planes.shape[0], -1), out.reshape(planes.shape[0], -1))
    return out


def standardise_reference(planes: np.ndarray) -> np.ndarray:
    """Plain-numpy twin of `standardise`."""
    if planes.shape[0] == 0:
        return np.ascontiguousarray(planes, dtype=np.float32)
    mean = planes.reshape(planes.shape[0], -1).mean(axis=1, dtype=np.float64)
    centred = planes - mean[:, None, None].astype(np.float32)
    flat = centred.reshape(planes.shape[0], -1)
    std = np.sqrt(np.einsum("kn,kn->k", flat, flat, dtype=np.float64) / max(flat.shape[1], 1))
    std = np.where(std > 1e-12 * (np.abs(mean) + 1.0), std, np.inf)
    centred /= std[:, None, None].astype(np.float32)
    return np.ascontiguousarray(centred, dtype=np.float32)


STANDARDISE_BLOCK = 1 << 16  # values per task of `_standardise_kernel`


@numba.njit(parallel=True, cache=True, fastmath=True, error_model="numpy")
def _standardise_kernel(flat, out):
    """flat, out: (K, N) float32, N >= 1. Per row, float64 sums of d = x - x0 and d^2 over blocks (x0: the
    row's first value, so the variance loses nothing to cancellation), then (x - mean) / std."""
    count, n = flat.shape
    blocks = -(-n // STANDARDISE_BLOCK)
    partial = np.empty((count, blocks, 2))  # no array expressions outside the prange loops: each would be
    for task in numba.prange(count * blocks):  # a parallel region of its own (~30 us apiece)
        k, lo = task // blocks, (task % blocks) * STANDARDISE_BLOCK
        src, first = flat[k, lo : min(n, lo + STANDARDISE_BLOCK)], np.float64(flat[k, 0])
        linear, square = 0.0, 0.0
        for j in range(src.shape[0]):
            d = np.float64(src[j]) - first
            linear += d
            square += d * d
        partial[task // blocks, task % blocks, 0] = linear
        partial[task // blocks, task % blocks, 1] = square
    mean32 = np.empty(count, np.float32)
    inv = np.empty(count, np.float32)
    for k in range(count):
        linear, square = 0.0, 0.0
        for b in range(blocks):
            linear += partial[k, b, 0]
            square += partial[k, b, 1]
        shift = linear / n
        mean = np.float64(flat[k, 0]) + shift
        std = np.sqrt(max(square / n - shift * shift, 0.0))
        mean32[k] = np.float32(mean)
        inv[k] = np.float32(1.0 / std) if std > 1e-12 * (abs(mean) + 1.0) else np.float32(0.0)
    for task in numba.prange(count * blocks):
        k, lo = task // blocks, (task % blocks) * STANDARDISE_BLOCK
        hi = min(n, lo + STANDARDISE_BLOCK)
        src, dst, m, s = flat[k, lo:hi], out[k, lo:hi], mean32[k], inv[k]
        for j in range(hi - lo):
            dst[j] = (src[j] - m) * s


def channel_planes(image: np.ndarray, albedo: np.ndarray | None = None, out: np.ndarray | None = None) -> np.ndarray:
    """`to_planes(image)`, or `to_planes(demodulate(image, albedo))` when `albedo` is given, in one pass.

    image: (H, W, C) float32 (linear radiance when demodulated); albedo: (H, W, C) float32 in [0, 1], or
    None; out: (C, H, W) float32 to write into (e.g. a slice of a larger stack of planes), or None.
    Returns the (C, H, W) float32 planes. numba kernel (parallel over rows, the same float32 division as
    `albedo.demodulate`); `channel_planes_reference` is the plain-numpy twin.
    """
    image = np.ascontiguousarray(image, dtype=np.float32)
    if out is None:
        out = np.empty((image.shape[2], *image.shape[:2]), np.float32)
    divisor = image if albedo is None else np.ascontiguousarray(albedo, dtype=np.float32)
    _channel_planes_kernel(image, divisor, albedo is not None, out)
    return out


def channel_planes_reference(
    image: np.ndarray, albedo: np.ndarray | None = None, out: np.ndarray | None = None
) -> np.ndarray:
    """Plain-numpy twin of `channel_planes`."""
    planes = to_planes(image if albedo is None else demodulate(image, albedo))
    if out is None:
        return planes
    out[...] = planes
    return out


@numba.njit(parallel=True, cache=True, error_model="numpy")
def _channel_planes_kernel(image, albedo, divide, out):
    """out[m, y, x] = image[y, x, m], divided by `albedo_factor(albedo[y, x, m])` when `divide`."""
    height, width, channels = image.shape
    for y in numba.prange(height):
        src, factor = image[y].reshape(width * channels), albedo[y].reshape(width * channels)
        if channels == 3 and divide:  # a constant stride: LLVM vectorises the strided loads together
            d0, d1, d2 = out[0, y], out[1, y], out[2, y]
            for x in range(width):
                d0[x] = src[3 * x] / albedo_factor(factor[3 * x])
                d1[x] = src[3 * x + 1] / albedo_factor(factor[3 * x + 1])
                d2[x] = src[3 * x + 2] / albedo_factor(factor[3 * x + 2])
        elif channels == 3:
            d0, d1, d2 = out[0, y], out[1, y], out[2, y]
            for x in range(width):
                d0[x] = src[3 * x]
                d1[x] = src[3 * x + 1]
                d2[x] = src[3 * x + 2]
        else:
            for m in range(channels):
                dst = out[m, y]
                for x in range(width):
                    i = x * channels + m
                    dst[x] = src[i] / albedo_factor(factor[i]) if divide else src[i]


@numba.njit(inline="always")
def interleave_row(line, albedo, modulate, out):
    """out[x, m] = line[m, x]: a row of planes (C, W) float32 into a row of pixels (W, C), times
    `albedo_factor(albedo[x, m])` when `modulate` (`albedo.remodulate`, fused into the store).
    For 3 channels the flag is tested outside the loops: tested inside, it kept them from vectorising."""
    channels, width = line.shape
    dst, factor = out.reshape(width * channels), albedo.reshape(width * channels)
    if channels == 3:  # a constant stride: the strided stores vectorise together
        s0, s1, s2 = line[0], line[1], line[2]
        if modulate:
            for x in range(width):
                dst[3 * x] = s0[x] * albedo_factor(factor[3 * x])
                dst[3 * x + 1] = s1[x] * albedo_factor(factor[3 * x + 1])
                dst[3 * x + 2] = s2[x] * albedo_factor(factor[3 * x + 2])
        else:
            for x in range(width):
                dst[3 * x] = s0[x]
                dst[3 * x + 1] = s1[x]
                dst[3 * x + 2] = s2[x]
    else:
        for m in range(channels):
            src = line[m]
            for x in range(width):
                i = x * channels + m
                dst[i] = src[x] * albedo_factor(factor[i]) if modulate else src[x]
