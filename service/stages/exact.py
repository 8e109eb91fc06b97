"""Pixels the renderer computed exactly, found from the two half buffers: an emission layer for frames
that carry none.

Most renderers write no `emission` layer. Without it a directly visible light (radiance 1e3 beside
surfaces of radiance 1) enters every regression and filter as data: the fits extrapolate across the
step (black rings, blown-out blocks) and the filters spread it into a glow. Yet such a pixel needs no
denoising. Every sample of a pixel that sees an emitter with a black BSDF (or a constant sky) is the same
number, so the two independent half estimates `colorA` and `colorB` agree to rounding, while any pixel
with Monte Carlo noise has halves that differ (two continuous random estimates are equal with
probability zero). A pixel whose halves agree and are not black is exact: the pipeline step treats its
value as emission (subtracts it, denoises the rest, adds it back), so the pixel comes out as it went in
and none of its radiance reaches a neighbour's fit. Black pixels whose halves agree (no light found at
low spp) are noise, not exact, and stay in.

Emitter edges, partly covered by geometry, have halves that differ: they are ordinary noisy pixels to
this stage, and the firefly clamps of the denoisers handle them.
"""

from __future__ import annotations

import numba
import numpy as np

EXACT_RTOL = 1e-6  # halves agree within this relative difference per channel (a few float32 roundings)
EXACT_MIN = 1e-6  # radiance: at least one channel above this, so that black pixels are not "exact"


def exact_mask(color_a: np.ndarray, color_b: np.ndarray) -> np.ndarray:
    """(H, W) bool: pixels whose half estimates agree and are not black.

    color_a, color_b: (H, W, 3) float32 linear radiance of the two half buffers. A pixel is exact when
    |a - b| <= EXACT_RTOL * max(|a|, |b|) in every channel and max(|a|) > EXACT_MIN. numpy reference of
    `exact_emission`'s test.
    """
    a, b = color_a.astype(np.float32), color_b.astype(np.float32)
    agree = (np.abs(a - b) <= np.float32(EXACT_RTOL) * np.maximum(np.abs(a), np.abs(b))).all(axis=-1)
    return agree & (np.abs(a).max(axis=-1) > np.float32(EXACT_MIN))


def exact_emission(color_a: np.ndarray, color_b: np.ndarray, color: np.ndarray) -> np.ndarray | None:
    """The frame's exact pixels as an emission layer, or None when it has none.

    color_a, color_b, color: (H, W, 3) float32 linear radiance (halves and full estimate). Returns
    (H, W, 3) float32: `color` where `exact_mask` holds, 0 elsewhere; None when no pixel is exact (the
    common case, which then costs one read of the halves). One numba pass; `exact_mask` is its reference.
    """
    a = np.ascontiguousarray(color_a, dtype=np.float32)
    b = np.ascontiguousarray(color_b, dtype=np.float32)
    c = np.ascontiguousarray(color, dtype=np.float32)
    out = np.zeros_like(c)
    if not _exact_kernel(a, b, c, np.float32(EXACT_RTOL), np.float32(EXACT_MIN), out):
        return None
    return out


@numba.njit(parallel=True, cache=True, error_model="numpy")
def _exact_kernel(a, b, c, rtol, floor, out):
    height, width, channels = a.shape
    found = np.zeros(height, np.bool_)
    for y in numba.prange(height):
        for x in range(width):
            agree, bright = True, False
            for k in range(channels):
                u, v = a[y, x, k], b[y, x, k]
                if abs(u - v) > rtol * max(abs(u), abs(v)):
                    agree = False
                if abs(u) > floor:
                    bright = True
            if agree and bright:
                found[y] = True
                for k in range(channels):
                    out[y, x, k] = c[y, x, k]
    return found.any()
