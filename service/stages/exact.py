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

Emitter edges, partly covered by geometry, usually have halves that differ: they are ordinary noisy
pixels to this stage, and the firefly clamps of the denoisers handle them. At low spp, though, every
sample of an edge pixel may hit the emitter (at 1 spp per half, with probability coverage^2): its halves
agree and it is kept at its noisy value, as noisy as it came in but not worse. With the renderer's
`emission` layer such a pixel is recognised (its colour is not all emission) and left to the denoiser.
"""

from __future__ import annotations

import numba
import numpy as np

EXACT_RTOL = 1e-6  # halves agree within this relative difference per channel (a few float32 roundings)
EXACT_MIN = 1e-6  # radiance: at least one channel above this, so that black pixels are not "exact"


def exact_mask(color_a: np.ndarray, color_b: np.ndarray, color: np.ndarray | None = None,
               emission: np.ndarray | None = None) -> np.ndarray:
    """(H, W) bool: pixels whose half estimates agree and are not black, and, when the renderer's `emission`
    is given, whose `color` is all emission.

    color_a, color_b, color, emission: (H, W, 3) float32 linear radiance (halves, full estimate, the
    renderer's noise-free emission; `color` is needed with `emission`). In every channel |a - b| <=
    EXACT_RTOL * max(|a|, |b|) (and |color - emission| <= EXACT_RTOL * max(|color|, |emission|)), and
    max(|a|) > EXACT_MIN. With an emission layer, the second test rejects an emitter's edge pixel whose few
    samples all happened to hit the emitter: the halves agree, the converged emission says otherwise.
    numpy reference of `exact_emission`'s test.
    """
    mask = agrees(color_a, color_b) & (np.abs(color_a.astype(np.float32)).max(axis=-1) > np.float32(EXACT_MIN))
    if emission is not None:
        mask &= agrees(color, emission)
    return mask


def agrees(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """(H, W) bool: every channel of u and v ((H, W, C), any real dtype, compared in float32) agrees to
    EXACT_RTOL relative (`agree`'s test); numpy."""
    u, v = u.astype(np.float32), v.astype(np.float32)
    return (np.abs(u - v) <= np.float32(EXACT_RTOL) * np.maximum(np.abs(u), np.abs(v))).all(axis=-1)


def exact_emission(color_a: np.ndarray, color_b: np.ndarray, color: np.ndarray) -> np.ndarray | None:
    """The exact pixels of a frame without an emission layer, as one, or None when it has none.

    color_a, color_b, color: (H, W, 3) float32 linear radiance (halves and full estimate). Returns
    (H, W, 3) float32: `color` where `exact_mask(color_a, color_b)` holds, 0 elsewhere; None when no pixel
    is exact (the common case, which then costs one read of the halves). numba passes; `exact_mask` is
    their reference.
    """
    a = np.ascontiguousarray(color_a, dtype=np.float32)
    b = np.ascontiguousarray(color_b, dtype=np.float32)
    rtol, floor = np.float32(EXACT_RTOL), np.float32(EXACT_MIN)
    if not _any_exact(a, b, rtol, floor):
        return None
    out = np.zeros(a.shape, np.float32)
    _fill_exact(a, b, np.ascontiguousarray(color, dtype=np.float32), rtol, floor, out)
    return out


@numba.njit(inline="always")
def agree(u, v, rtol):  # pragma: no cover - jitted
    """Whether float32 u and v agree to `rtol` relative (the test of `exact_mask`)."""
    return abs(u - v) <= rtol * max(abs(u), abs(v))


@numba.njit(inline="always")
def pixel_exact(a, b, i, channels, rtol, floor):  # pragma: no cover - jitted
    """Whether the pixel of interleaved rows a, b ((W * C,) float32) starting at index i is exact."""
    exact, bright = True, False
    for c in range(channels):
        exact = exact and agree(a[i + c], b[i + c], rtol)
        bright = bright or abs(a[i + c]) > floor
    return exact and bright


@numba.njit(inline="always")
def any_agree(ra, rb, rtol):  # pragma: no cover - jitted
    """Whether some value of rows ra, rb ((N,) float32) agrees (`agree`), as every channel of an exact pixel
    does. Counted branch-free: one vectorised pass, so that a row with none skips the per-pixel test."""
    count = 0
    for i in range(ra.shape[0]):
        count += 1 if agree(ra[i], rb[i], rtol) else 0
    return count > 0


@numba.njit(parallel=True, cache=True, error_model="numpy")
def _any_exact(a, b, rtol, floor):  # pragma: no cover - jitted
    height, width, channels = a.shape
    found = np.zeros(height, np.bool_)
    for y in numba.prange(height):
        ra, rb = a[y].reshape(width * channels), b[y].reshape(width * channels)
        if not any_agree(ra, rb, rtol):
            continue
        for x in range(width):
            if pixel_exact(ra, rb, x * channels, channels, rtol, floor):
                found[y] = True
                break
    return found.any()


@numba.njit(parallel=True, cache=True, error_model="numpy")
def _fill_exact(a, b, c, rtol, floor, out):  # pragma: no cover - jitted
    height, width, channels = a.shape
    for y in numba.prange(height):
        n = width * channels
        ra, rb, rc, ro = a[y].reshape(n), b[y].reshape(n), c[y].reshape(n), out[y].reshape(n)
        if not any_agree(ra, rb, rtol):
            continue
        for x in range(width):
            i = x * channels
            if pixel_exact(ra, rb, i, channels, rtol, floor):
                for k in range(channels):
                    ro[i + k] = rc[i + k]
