"""Keep a denoiser's output within the noise the two half buffers show at each pixel.

A pixel estimate `color` = (colorA + colorB) / 2 has variance Var(color) = E[(colorA - colorB)^2] / 4
(the halves are independent estimates of the same mean). Where that variance is small the renderer has
already resolved the pixel, and a filter that moves it far (a sky blurred with the horizon, a black
reflection of the void lifted by its bright surround) makes it worse than it came in. So every output
value is clipped to

    color +- k sd,   sd^2 = mean over the 3x3 window (clipped at the border) of (colorA - colorB)^2 / 4,

per channel (a band beyond float32, from half differences above ~1e19, does not clip). The 3x3 mean
gives each sd about nine degrees of freedom, so an sd far below the true one (which would freeze noise in
place) is rare; where the halves disagree strongly (fireflies, heavy-tailed paths) sd is large and the
denoiser is free. A region where every sample of both halves was black keeps
black: that is what the samples say. Exact pixels (`service.stages.exact`) come out exactly as `color`;
other pixels with emission in the renderer's `emission` layer are not clipped.

With the G-buffer (`normal`, and `depth` where the frame has it) the same holds per surface: a pixel whose
halves are equal (every channel, exactly), and whose 3x3 neighbours on its own surface (both background, or
both surface hits whose normals' directions are within SURFACE_COS, whatever their lengths: a normal averaged
over a pixel's samples is short, and depths within SURFACE_DEPTH of the pixel's, relative: the reprojection's
consistency test and thresholds, but by the normals' directions where it takes their dot product as it is) all
have equal halves too, comes out as `color`; exact pixels and pixels with emission are then treated as above.
The other surface's noise says nothing about this pixel's: on `make bench`'s `fireflies`, frame 7, a column one
pixel wide of a box's side that no light reaches (every sample black) stands beside the lit floor, whose noise
widened the 3x3 band enough to let svgf's bleed through (0.1 where the input and the reference are 0: 51x the
input's error over the 16x16 tile, kpn 16x, flr 6x). Where the samples of a surface's pixels are this few and
all agree (a dim region at 1-2 spp), the output is the input, as in a black region. What it costs (`make
bench`, every pipeline, against the clamp without it): relL2 at most 0.25% higher (auto on shadows), lower on
fireflies (svgf -5.6%, rae -4.0%, kpn -1.2%), disocclusion and textures unchanged; the hard cases all pass as
before, relL2 from -2.0% (crossreg on `caustics`) to +4.3% (rae on `window`; docs/benchmarks.md, "Noise clamp
per surface"). It takes 1.5 ms more of a 1280x720 frame.

What it costs on ordinary frames, together with the other guards of `Pipeline.step` (the benchmark's
trimmed relL2, mean over frames, `make bench`, against the commit before the guards): NOISE_K = 5 is the
tightest of 3, 4 and 5 that kept every pipeline within 3% of its relL2 before. On the shadows sample flr
0.0382 -> 0.0388, bmfr 0.0494 -> 0.0494, crossregression 0.0601 -> 0.0598; on the `fireflies` sequence
crossregression 0.0324 -> 0.0330, while bmfr improves there, 0.150 -> 0.071. An earlier
version with K = 3 cost flr 8.6% on the shadows sample.
"""

from __future__ import annotations

import numba
import numpy as np

from service.kernels.window import overlap, window_offsets
from service.stages.exact import EXACT_MIN, EXACT_RTOL, agree, any_agree, exact_mask, pixel_exact
from service.stages.reprojection import DEPTH_FLOOR, NORMAL_HIT, ReprojectionParams, surface_hit
from service.stages.svgf import box_mean

NOISE_K = 5.0  # half-width of the allowed band, in standard deviations of the pixel estimate
NOISE_RADIUS = 1  # window half-size of the variance estimate, pixels (3x3)
# Two pixels are on one surface (module docstring) at the reprojection's thresholds for a consistent tap: the
# cosine between their normals' directions at least SURFACE_COS, depths within SURFACE_DEPTH of the pixel's (relative)
SURFACE_COS = ReprojectionParams.normal_cos_min
SURFACE_DEPTH = ReprojectionParams.depth_tolerance
_COS2 = np.float32(SURFACE_COS**2)  # the kernel compares dot^2 with cos^2 |n|^2 |m|^2 (dot > 0): no square root


def noise_clamp(
    out: np.ndarray,
    color: np.ndarray,
    color_a: np.ndarray,
    color_b: np.ndarray,
    emission: np.ndarray | None = None,
    k: float = NOISE_K,
    exact: bool = True,
    *,
    normal: np.ndarray | None = None,
    depth: np.ndarray | None = None,
) -> np.ndarray:
    """`out` clipped to `color` +- k sd per pixel and channel (module docstring).

    out: (H, W, 3) float32 denoised radiance; color, color_a, color_b: (H, W, 3) float32 noisy radiance and
    its two halves; emission: the renderer's (H, W, 3) float32 emission layer or None; all linear. Exact
    pixels (`service.stages.exact.exact_mask(color_a, color_b, color, emission)`) take `color`; pixels
    with emission keep `out` unclipped (there the samples' binary coverage of an emitter's edge can make
    the halves agree by chance, and the emission split already tells the denoiser what is exact). Returns
    a new (H, W, 3) float32 array. One parallel numba pass; `noise_clamp_reference` is the numpy twin.
    exact=False: the caller knows that no pixel is exact (`exact.exact_emission` found none in a frame
    without an emission layer), and the per-pixel test is skipped. normal: (H, W, 3) float32 (zero where
    nothing was hit) and depth: (H, W, 1) float32 or None: pixels whose own surface's 3x3 samples all agree
    come out as `color` (module docstring); depth is used only with normal (its shape is checked either way).
    """
    if not 0 <= k < np.inf:
        raise ValueError(f"noise clamp k must be finite and >= 0, got {k}")
    arrays = [np.ascontiguousarray(x, dtype=np.float32) for x in (out, color, color_a, color_b)]
    if emission is not None:
        arrays.append(np.ascontiguousarray(emission, dtype=np.float32))
    shapes = {x.shape for x in arrays}
    if len(shapes) != 1 or arrays[0].ndim != 3:
        raise ValueError(f"noise clamp: out, color, the halves and emission must share one (H, W, C) shape: {shapes}")
    result = np.empty_like(arrays[0])
    e = arrays[4] if emission is not None else arrays[1]
    use_normal, use_depth = normal is not None, normal is not None and depth is not None
    normal, depth = _gbuffer(normal, depth, arrays[0].shape)
    agreeing = np.empty(arrays[0].shape[:2] if use_normal else (1, 1), np.uint8)
    if use_normal:
        _agreeing_kernel(arrays[2], arrays[3], agreeing)
    _clamp_kernel(*arrays[:4], e, emission is not None, exact or emission is not None, np.float32(k),
                  np.float32(EXACT_RTOL), np.float32(EXACT_MIN), agreeing, normal, depth, use_normal, use_depth,
                  result)
    return result


def _gbuffer(normal: np.ndarray | None, depth: np.ndarray | None,
             shape: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray]:
    """normal (H, W, 3) and depth (H, W, 1) as contiguous float32 for the kernel (placeholders of one pixel
    where not given); ValueError where their shape does not match the frame's (H, W)."""
    pair = []
    for name, layer, channels in (("normal", normal, 3), ("depth", depth, 1)):
        if layer is None:
            pair.append(np.zeros((1, 1, channels), np.float32))
            continue
        if layer.shape != (*shape[:2], channels):
            raise ValueError(f"noise clamp: {name} {layer.shape} does not match the frame {shape[:2]}")
        pair.append(np.ascontiguousarray(layer, np.float32))
    return pair[0], pair[1]


def quiet_mask_reference(color_a: np.ndarray, color_b: np.ndarray, normal: np.ndarray,
                         depth: np.ndarray | None = None) -> np.ndarray:
    """(H, W) bool: pixels whose halves are equal, as are those of every 3x3 neighbour on their surface (module
    docstring); numpy twin of `_agreeing_kernel` and `_quiet`. color_a, color_b, normal (H, W, 3) and depth (H, W, 1) or
    None, float32."""
    height, width = color_a.shape[:2]
    same_halves = (color_a == color_b).all(axis=-1)
    hit = surface_hit(normal)
    z = None if depth is None else depth[..., 0].astype(np.float32)
    quiet = same_halves.copy()
    for dy, dx in window_offsets(1):
        pair = overlap(height, width, dy, dx)
        if pair is None or (dy, dx) == (0, 0):
            continue
        centre, neighbour = pair
        both = hit[centre] & hit[neighbour]
        dot = (normal[centre] * normal[neighbour]).sum(axis=-1)
        lengths = (normal[centre] * normal[centre]).sum(axis=-1) * (normal[neighbour] * normal[neighbour]).sum(axis=-1)
        aligned = (dot > 0) & (dot * dot >= _COS2 * lengths)
        same = (hit[centre] == hit[neighbour]) & (~both | aligned)
        if z is not None:
            near = np.abs(z[neighbour] - z[centre]) <= np.float32(SURFACE_DEPTH) * np.maximum(
                np.abs(z[centre]), np.float32(DEPTH_FLOOR))
            same &= ~both | near
        quiet[centre] &= ~same | same_halves[neighbour]
    return quiet


def noise_sd_reference(color_a: np.ndarray, color_b: np.ndarray) -> np.ndarray:
    """(H, W, C) float32 sd of the pixel estimate (module docstring); numpy (`svgf.box_mean`)."""
    d = color_a.astype(np.float32) - color_b.astype(np.float32)
    return np.sqrt(box_mean(d * d, NOISE_RADIUS) / np.float32(4.0))


def noise_clamp_reference(
    out: np.ndarray,
    color: np.ndarray,
    color_a: np.ndarray,
    color_b: np.ndarray,
    emission: np.ndarray | None = None,
    k: float = NOISE_K,
    *,
    normal: np.ndarray | None = None,
    depth: np.ndarray | None = None,
) -> np.ndarray:
    """Plain-numpy twin of `noise_clamp`."""
    band = k * noise_sd_reference(color_a, color_b)
    clipped = np.clip(out, color - band, color + band)
    if normal is not None:
        clipped = np.where(quiet_mask_reference(color_a, color_b, normal, depth)[..., None], color, clipped)
    if emission is not None:
        clipped = np.where((emission != 0).any(axis=-1, keepdims=True), out, clipped)
    exact = exact_mask(color_a, color_b, color, emission)
    return np.where(exact[..., None], color, clipped).astype(np.float32)


@numba.njit(parallel=True, cache=True, error_model="numpy")
def _agreeing_kernel(a, b, agreeing):  # pragma: no cover - jitted
    """agreeing (H, W) uint8: 1 where the halves a, b ((H, W, C) float32) have the same value, every channel.
    A task per row."""
    height, width, channels = a.shape
    n = width * channels
    for y in numba.prange(height):
        ra, rb, flags = a[y].reshape(n), b[y].reshape(n), agreeing[y]
        for x in range(width):
            same = True
            for c in range(channels):
                same = same and ra[x * channels + c] == rb[x * channels + c]
            flags[x] = same


@numba.njit(inline="always", cache=True)
def _quiet(agreeing, normal, depth, use_depth, y, x):  # pragma: no cover - jitted
    """Whether every 3x3 neighbour of pixel (y, x) on its surface (module docstring) has halves that agree.
    agreeing: (H, W) uint8 (`_agreeing_kernel`); normal (H, W, 3), depth (H, W, 1) float32."""
    height, width = agreeing.shape
    n0, n1, n2 = normal[y, x, 0], normal[y, x, 1], normal[y, x, 2]
    own = n0 * n0 + n1 * n1 + n2 * n2
    hit = own > np.float32(NORMAL_HIT)
    z = depth[y, x, 0] if use_depth else np.float32(0)
    reach = np.float32(SURFACE_DEPTH) * max(abs(z), np.float32(DEPTH_FLOOR))
    for yy in range(max(y - 1, 0), min(y + 2, height)):
        for xx in range(max(x - 1, 0), min(x + 2, width)):
            if agreeing[yy, xx]:
                continue  # whatever its surface
            m0, m1, m2 = normal[yy, xx, 0], normal[yy, xx, 1], normal[yy, xx, 2]
            other = m0 * m0 + m1 * m1 + m2 * m2
            if (other > np.float32(NORMAL_HIT)) != hit:
                continue  # background beside a surface hit: another surface
            dot = n0 * m0 + n1 * m1 + n2 * m2
            if hit and not (dot > 0 and dot * dot >= _COS2 * (own * other)):
                continue
            if hit and use_depth and not abs(depth[yy, xx, 0] - z) <= reach:
                continue
            return False  # a neighbour on this surface whose halves differ
    return True


@numba.njit(inline="always", cache=True)
def _may_be_exact(ra, rb, rc, re, has_emission, rtol):  # pragma: no cover - jitted
    """Whether a pixel of a row ((W * C,) float32 halves ra, rb, colour rc, emission re) may take the exact
    pass of `_clamp_kernel`: with `has_emission`, some value has emission or a colour of 0; without, some
    value's halves agree (`agree`, rtol). Counted branch-free: a row with none costs one vectorised pass."""
    count = 0
    if has_emission:
        for i in range(rc.shape[0]):
            count += 1 if re[i] != 0 or rc[i] == 0 else 0
        return count > 0
    return any_agree(ra, rb, rtol)


@numba.njit(parallel=True, cache=True, error_model="numpy")
def _clamp_kernel(out, color, a, b, e, has_emission, exact, k, rtol, floor, agreeing, normal, depth, use_normal,
                  use_depth, result):  # pragma: no cover - jitted
    """A task per row: the 3-row column sums of (a - b)^2 along the interleaved (W * C) row, then the
    3-column sums as shifts by C, then the clip; with `use_normal`, pixels whose surface's 3x3 halves agree
    (`_quiet` on `agreeing`, (H, W) uint8) take `color`; unless `exact` is False (and so `has_emission`),
    exact pixels take `color`, other pixels with emission take `out` unclipped."""
    height, width, channels = out.shape
    n = width * channels
    for y in numba.prange(height):
        y0, y1 = max(y - 1, 0), min(y + 2, height)
        column = np.zeros(n, np.float32)
        for yy in range(y0, y1):
            ra, rb = a[yy].reshape(n), b[yy].reshape(n)
            for i in range(n):
                d = ra[i] - rb[i]
                column[i] += d * d
        ra, rb = a[y].reshape(n), b[y].reshape(n)
        rc, ro, rr = color[y].reshape(n), out[y].reshape(n), result[y].reshape(n)
        scale = np.float32(0.25) / np.float32(y1 - y0)
        inner = scale / np.float32(min(width, 3))  # interior pixels sum three columns
        edge = scale / np.float32(min(width, 2))  # the first and last pixel two (one in a 1-pixel row)
        for i in range(channels, n - channels):  # interior: contiguous, vectorises
            band = k * np.sqrt((column[i - channels] + column[i] + column[i + channels]) * inner)
            rr[i] = min(max(ro[i], rc[i] - band), rc[i] + band)
        for c in range(channels):  # the first and last pixel of the row
            for i in (c, n - channels + c):
                total = column[i]
                if i >= channels:
                    total += column[i - channels]
                if i + channels < n:
                    total += column[i + channels]
                band = k * np.sqrt(total * edge)
                rr[i] = min(max(ro[i], rc[i] - band), rc[i] + band)
        if use_normal:
            for x in range(width):  # the pixel's own halves first: in most frames few pixels have equal ones
                if agreeing[y, x] and _quiet(agreeing, normal, depth, use_depth, y, x):
                    for c in range(channels):
                        rr[x * channels + c] = rc[x * channels + c]
        re = e[y].reshape(n)
        if not exact or not _may_be_exact(ra, rb, rc, re, has_emission, rtol):
            continue
        for x in range(width):
            i = x * channels
            if has_emission:  # an exact pixel is all emission: without any, only a black colour can be
                emitted, black = False, True
                for c in range(channels):
                    emitted = emitted or re[i + c] != 0
                    black = black and rc[i + c] == 0
                if not emitted:
                    if black and pixel_exact(ra, rb, i, channels, rtol, floor):  # (a repaired NaN colour)
                        for c in range(channels):
                            rr[i + c] = rc[i + c]
                    continue
                keep = pixel_exact(ra, rb, i, channels, rtol, floor)
                for c in range(channels):
                    keep = keep and agree(rc[i + c], re[i + c], rtol)
                src = rc if keep else ro  # exact: the input; other emission: unclipped
                for c in range(channels):
                    rr[i + c] = src[i + c]
            elif pixel_exact(ra, rb, i, channels, rtol, floor):
                for c in range(channels):
                    rr[i + c] = rc[i + c]
