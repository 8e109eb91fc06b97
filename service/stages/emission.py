"""`Pipeline.step`'s emission split as parallel numba passes.

Denoisers filter the radiance without its emitted part (`emission`, exact and noise-free when the renderer
sends it) and add it back after; the step then checks that the result is finite. As numpy expressions
the subtraction would be one single-threaded full-frame pass per radiance layer, and the sum and the check
two more; here the subtraction from all layers is one parallel pass that reads the emission once (the
pass is memory-bound), and the sum and the check another.

Where a small emitter covers part of a pixel, the emission layer holds the covered part exactly but the
colour holds the input's few samples of that coverage: the pixel's remainder (colour - emission) is the
coverage's noise, +-L/spp for a light of radiance L (at 4 spp beside a light of 2667: -444 and +600 where the
reference's remainder is 1.9), and every filter spread it into the neighbours. At a pixel with emission the
remainder of each layer is therefore clipped, per channel, to [min(0, lo), hi], lo and hi the layer's own
range over its 8 neighbours without emission (their remainder is the layer itself); a pixel with no such
neighbour (inside a light or a sky) keeps it. Cost: a mask pass and a scan per row on frames with an `emission`
layer, the clip only at an emitter's edge; in accuracy, on frames without emitters none; on
`make bench`'s `fireflies` and data/val's `veiled_light` every pipeline's relL2 fell (docs/benchmarks.md,
"The remainder at an emitter's edge").
"""

from __future__ import annotations

import numba
import numpy as np

from service.kernels.simd import float32_to_bits

MAX_LAYERS = 3  # radiance layers one `subtract_emission` pass takes (frame.RADIANCE_LAYERS)


def subtract_emission(layers: list[np.ndarray], emission: np.ndarray) -> list[np.ndarray]:
    """[layer - emission for layer in layers], clipped at pixels with emission to the layer's range over their
    neighbours without emission (the module's docstring), 1 to MAX_LAYERS layers in one parallel pass.

    layers, emission: (H, W, 3) float32 finite radiance (any other layout or float dtype is converted first;
    frames come repaired); a pixel has emission where any channel of `emission` is not 0. Returns new
    C-contiguous float32 arrays of that shape, in the order of `layers`. The numpy twin is
    `subtract_emission_reference`."""
    if not 1 <= len(layers) <= MAX_LAYERS:
        raise ValueError(f"emission: takes 1 to {MAX_LAYERS} layers, got {len(layers)}")
    emission = np.ascontiguousarray(emission, np.float32)
    layers = [np.ascontiguousarray(x, np.float32) for x in layers]
    for layer in layers:
        if layer.shape != emission.shape:
            raise ValueError(f"emission: a radiance layer {layer.shape} does not match the emission {emission.shape}")
    if emission.ndim != 3 or emission.shape[2] != 3:
        raise ValueError(f"emission: expected (H, W, 3) layers, got {emission.shape}")
    out = np.empty((len(layers), *emission.shape), np.float32)
    sources = layers + [layers[0]] * (MAX_LAYERS - len(layers))  # unread beyond len(layers)
    emitting = np.empty(emission.shape[:2], np.bool_)
    _emitting_kernel(emission, emitting)
    _subtract_kernel(*sources, len(layers), emission, emitting, out)
    return list(out)


def subtract_emission_reference(layers: list[np.ndarray], emission: np.ndarray) -> list[np.ndarray]:
    """Plain-numpy twin of `subtract_emission` (same arguments and result)."""
    emission = np.asarray(emission, np.float32)
    h, w = emission.shape[:2]
    emitting = np.any(emission != 0, axis=-1)
    out = []
    for layer in layers:
        layer = np.asarray(layer, np.float32)
        less = layer - emission
        lo = np.full(layer.shape, np.inf, np.float32)
        hi = np.full(layer.shape, -np.inf, np.float32)
        padded = np.pad(layer, ((1, 1), (1, 1), (0, 0)))
        dark = np.pad(~emitting, 1)  # neighbours without emission; outside the frame: none
        for dy in range(3):
            for dx in range(3):
                if dy == dx == 1:
                    continue
                take = dark[dy:dy + h, dx:dx + w, None]
                value = padded[dy:dy + h, dx:dx + w]
                lo = np.where(take, np.minimum(lo, value), lo)
                hi = np.where(take, np.maximum(hi, value), hi)
        clip = emitting[..., None] & (hi >= lo)
        out.append(np.where(clip, np.clip(less, np.minimum(lo, 0), hi), less).astype(np.float32))
    return out


@numba.njit(parallel=True, cache=True, error_model="numpy")
def _emitting_kernel(emission, emitting):  # pragma: no cover - jitted
    """emitting (H, W) bool: whether any channel of emission (H, W, 3) float32 is not 0; a task per row."""
    for y in numba.prange(emission.shape[0]):
        for x in range(emission.shape[1]):
            emitting[y, x] = emission[y, x, 0] != 0 or emission[y, x, 1] != 0 or emission[y, x, 2] != 0


@numba.njit(parallel=True, cache=True, error_model="numpy")
def _subtract_kernel(a, b, c, count, emission, emitting, out):  # pragma: no cover - jitted
    """out[k] = (a, b, c)[k] - emission for k < count, clipped at the pixels `emitting` (H, W) bool marks that
    have a neighbour it does not (`_clip_pixel`); all (H, W, 3) float32, out (count, H, W, 3); a task per row,
    each emission row read once for every layer."""
    height, width = emitting.shape
    for y in numba.prange(height):
        e = emission[y].reshape(3 * width)
        subtract_row(a[y].reshape(3 * width), e, out[0, y].reshape(3 * width))
        if count > 1:
            subtract_row(b[y].reshape(3 * width), e, out[1, y].reshape(3 * width))
        if count > 2:
            subtract_row(c[y].reshape(3 * width), e, out[2, y].reshape(3 * width))
        y0, y1 = max(y - 1, 0), min(y + 2, height)
        column = np.empty(width, np.bool_)  # every pixel of the column's rows y0 ... y1 - 1 emitting
        for x in range(width):
            column[x] = emitting[y0, x] and emitting[y1 - 1, x] and emitting[y, x]
        for x in range(width):
            if not emitting[y, x]:
                continue
            x0, x1 = max(x - 1, 0), min(x + 2, width)
            # a neighbour without emission (inside a light or a sky: none, the common case there)
            if not (column[x0] and column[x] and column[x1 - 1]):
                _clip_pixel(a, emitting, y0, y1, x0, x1, out[0, y, x])
                if count > 1:
                    _clip_pixel(b, emitting, y0, y1, x0, x1, out[1, y, x])
                if count > 2:
                    _clip_pixel(c, emitting, y0, y1, x0, x1, out[2, y, x])


@numba.njit(inline="always")
def _clip_pixel(layer, emitting, y0, y1, x0, x1, dst):  # pragma: no cover - jitted
    """dst (3,) float32, a pixel's remainder, clipped per channel to [min(0, lo), hi] of `layer` (H, W, 3) over
    the pixels of rows y0 ... y1 - 1 and columns x0 ... x1 - 1 that `emitting` (H, W) bool does not mark (at
    least one; the pixel itself is marked)."""
    for ch in range(3):
        lo, hi = np.float32(np.inf), np.float32(-np.inf)
        for yy in range(y0, y1):
            for xx in range(x0, x1):
                if not emitting[yy, xx]:
                    v = layer[yy, xx, ch]
                    lo = min(lo, v)
                    hi = max(hi, v)
        dst[ch] = min(max(dst[ch], min(lo, np.float32(0))), hi)


@numba.njit(inline="always")
def subtract_row(src, emission, dst):  # pragma: no cover - jitted
    """dst = src - emission, rows (N,) float32."""
    for i in range(dst.shape[0]):
        dst[i] = src[i] - emission[i]


def add_emission(color: np.ndarray, emission: np.ndarray) -> tuple[np.ndarray, bool]:
    """(color + emission, whether every value of the sum is finite), in one pass.

    color, emission: (H, W, 3) float32 (any other layout or float dtype is converted first). The sum is a
    new C-contiguous float32 array of that shape."""
    color, emission = np.ascontiguousarray(color, np.float32), np.ascontiguousarray(emission, np.float32)
    if color.shape != emission.shape:
        raise ValueError(f"emission: the colour {color.shape} does not match the emission {emission.shape}")
    out = np.empty(color.shape, np.float32)
    rows = color.shape[0] if color.ndim > 1 else 1
    finite = _add_kernel(color.reshape(rows, -1), emission.reshape(rows, -1), out.reshape(rows, -1))
    return out, bool(finite)


@numba.njit(parallel=True, cache=True, error_model="numpy")
def _add_kernel(color, emission, out):  # pragma: no cover - jitted
    """out = color + emission, all (H, N) float32, a task per row (`add_row`); returns whether every value of
    out is finite."""
    bad = 0
    for y in numba.prange(out.shape[0]):
        bad += add_row(color[y], emission[y], out[y])
    return bad == 0


@numba.njit(inline="always")
def add_row(src, emission, dst):  # pragma: no cover - jitted
    """dst = src + emission, rows (N,) float32 (dst may be src); returns the count of non-finite values of dst
    (`nonfinite`)."""
    bad = 0
    for i in range(dst.shape[0]):
        v = src[i] + emission[i]
        dst[i] = v
        bad += nonfinite(v)
    return bad


@numba.njit(inline="always")
def nonfinite(v):  # pragma: no cover - jitted
    """Whether float32 v is NaN or infinite: its exponent bits all set (an integer test, which vectorises where
    a float test would need fast-math)."""
    return (float32_to_bits(v) & 0x7F800000) == 0x7F800000
