"""`Pipeline.step`'s emission split as parallel numba passes.

Denoisers filter the radiance without its emitted part (`emission`, exact and noise-free when the renderer
sends it) and add it back after; the step then checks that the result is finite. As numpy expressions
the subtraction would be one single-threaded full-frame pass per radiance layer, and the sum and the check
two more; here the subtraction from all layers is one parallel pass that reads the emission once (the
pass is memory-bound), and the sum and the check another. A pipeline that reads its radiance layers
in passes of its own can fuse the split into them instead (overriding `Pipeline.denoise_split`;
`crossregression` subtracts row by row with `subtract_row` and adds back with `add_row`).
"""

from __future__ import annotations

import numba
import numpy as np

from service.kernels.simd import float32_to_bits

MAX_LAYERS = 3  # radiance layers one `subtract_emission` pass takes (frame.RADIANCE_LAYERS)


def subtract_emission(layers: list[np.ndarray], emission: np.ndarray) -> list[np.ndarray]:
    """[layer - emission for layer in layers], 1 to MAX_LAYERS layers in one parallel pass.

    layers, emission: (H, W, 3) float32 (any other layout or float dtype is converted first). Returns new
    C-contiguous float32 arrays of that shape, in the order of `layers`."""
    if not 1 <= len(layers) <= MAX_LAYERS:
        raise ValueError(f"emission: takes 1 to {MAX_LAYERS} layers, got {len(layers)}")
    emission = np.ascontiguousarray(emission, np.float32)
    layers = [np.ascontiguousarray(x, np.float32) for x in layers]
    for layer in layers:
        if layer.shape != emission.shape:
            raise ValueError(f"emission: a radiance layer {layer.shape} does not match the emission {emission.shape}")
    rows = emission.shape[0] if emission.ndim > 1 else 1
    flat = [x.reshape(rows, -1) for x in layers]
    out = np.empty((len(layers), *emission.shape), np.float32)
    sources = flat + [flat[0]] * (MAX_LAYERS - len(flat))  # unread beyond len(layers)
    _subtract_kernel(*sources, len(layers), emission.reshape(rows, -1), out.reshape(len(layers), rows, -1))
    return list(out)


@numba.njit(parallel=True, cache=True, error_model="numpy")
def _subtract_kernel(a, b, c, count, emission, out):  # pragma: no cover - jitted
    """out[k] = (a, b, c)[k] - emission for k < count; all (H, N) float32 rows, out (count, H, N); a task per
    row, each emission row read once for every layer."""
    for y in numba.prange(emission.shape[0]):
        e = emission[y]
        subtract_row(a[y], e, out[0, y])
        if count > 1:
            subtract_row(b[y], e, out[1, y])
        if count > 2:
            subtract_row(c[y], e, out[2, y])


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
