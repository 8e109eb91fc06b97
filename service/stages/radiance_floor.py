"""No denoised radiance below what the renderer sent: the step's floor (Pipeline.step).

A filter with negative weights (a local regression's fitted plane, a kernel predicted by a network, a
block fit) extrapolates across a step of 1e3 in radiance: next to a visible light or a bright wall seen
through thin bars, it puts -30 in a pixel whose true radiance is 0.07, a black ring of relative error 1e5.
Radiance is not negative, so the step clips the denoised colour below at the lowest value of the frame's
input colour, or 0 when that is higher: for a renderer's ordinary non-negative output the floor is 0, and
a frame with negative input (a negative light, a difference render) is clipped no lower than it came.
Against a non-negative reference the clip can only lower each pixel's error.

Measured with `python -m bench run` (relL2 0.1% trimmed, mean over sequences; out/bench/val-s54a -> val-s54b,
report-s53b -> report-s54b, 2026-11-29). On the 11 held-out `data/val` sequences (128x128) the worst 16x16
tile against the noisy input: flr 1542x -> 110x, bmfr 553x -> 72x, bilateral 860x -> 52x, statistical 1032x
-> 32x; relL2 flr 0.1195 -> 0.1175, bmfr 0.1232 -> 0.1175, bilateral 0.1147 -> 0.1114, statistical 0.1206 ->
0.1143, auto 0.1081 -> 0.1085 (its candidates' error estimates move), the others unchanged. On `make bench`'s
four sequences every relL2 is unchanged to 3 digits. Time at 1280x720: about 1 ms (two parallel passes, one
for the input's minimum, one for the clip).
"""

from __future__ import annotations

import numba
import numpy as np


def radiance_floor(out: np.ndarray, color: np.ndarray) -> np.ndarray:
    """`out` clipped below at min(0, min(color)).

    out: (H, W, C) float32 denoised linear radiance (NaN and -inf stay, for the step's finite check); color:
    (H, W, C) float32 the frame's finite input radiance. Returns a new (H, W, C) C-contiguous float32 array."""
    if out.shape != color.shape or out.ndim != 3:
        raise ValueError(f"radiance floor: out {out.shape} and color {color.shape} must share one (H, W, C) shape")
    out = np.ascontiguousarray(out, np.float32)
    color = np.ascontiguousarray(color, np.float32)
    rows = out.shape[0]
    clipped = np.empty_like(out)
    _floor_kernel(out.reshape(rows, -1), color.reshape(rows, -1), clipped.reshape(rows, -1))
    return clipped


@numba.njit(parallel=True, cache=True, error_model="numpy")
def _floor_kernel(out, color, clipped):  # pragma: no cover - jitted
    """clipped = max(out, floor) with floor = min(0, min(color)); all (H, N) float32, a task per row. NaN in
    `out` stays NaN (`v < floor` is false), and -inf stays -inf: a denoiser's non-finite output is not hidden."""
    rows = color.shape[0]
    lows = np.zeros(rows, np.float32)
    for y in numba.prange(rows):
        low = np.float32(0.0)
        for v in color[y]:
            if v < low:
                low = v
        lows[y] = low
    floor = lows.min()
    for y in numba.prange(rows):
        src, dst = out[y], clipped[y]
        for i in range(dst.shape[0]):
            v = src[i]
            dst[i] = floor if v < floor and v > -np.inf else v
