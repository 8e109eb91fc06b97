"""Outlier suppression before a filter: the two clamps the regressions use, for any (H, W, C) image.

A firefly (one sample of 1e3 among samples of 1) is a value no filter should average in: a bilateral or
t-test filter spreads it into a bright disc of its window, a temporal filter into its history. The
regressions (bmfr, flr, cross-regression) clamp their inputs with `clamp_fireflies` (isolated values,
against the 3x3 neighbour range, widened by k times that range; our addition, not in the papers) and
`clamp_outlier_clusters` (small clusters, against a sigma-clipped 7x7 statistic of the log-compressed
signal), in that order, through `clamp_outlier_planes`; the filters without a regression (bilateral,
statistical, svgf) and the networks kpn and rae call `clamp_outliers` on their colour, demodulated by the
frame's albedo where it has one (bmfr and flr clamp their demodulated planes too). A directly visible
light is not clipped when the frame carries its emission: the renderer's `emission` layer, or, for a frame
with both halves and no emission layer, its exact pixels (`service.stages.exact`, taken out by
`Pipeline.step`).

Judged on the demodulated colour instead of the radiance (2026-11-27, `python -m bench run` on make bench's
four sequences, 128x128, 4 spp): relL2 lower or unchanged on every sequence for bilateral, statistical,
svgf and kpn (by at most 2%: statistical on textures 0.0142 -> 0.0139, bilateral on fireflies 0.0414 ->
0.0406), temporal error within 1%; bilateral's and statistical's worst tile on the bulb hard case 1.86x and 1.21x
the noisy input's -> 0.90x and 0.91x (`python -m bench.hard_cases table`). Its time: at 1280x720
(`textures` and `fireflies` frames tiled up, both with some sky, so both clamps run) about 75-80 ms against
21 ms on the radiance alone.
"""

from __future__ import annotations

import numba
import numpy as np

from service.kernels.row_ranges import BAND_ROWS, band_scratch, no_sources, put_source, three_row_ranges
from service.kernels.simd import (
    bits_to_float32,
    float32_to_bits,
)
from service.kernels.window import window_range
from service.regression.planes import from_planes, to_planes
from service.stages.albedo import ALBEDO_EPS, albedo_factor
from service.stages.svgf import box_mean

FIREFLY_K = 2.0  # clamp_fireflies: neighbour ranges (max - min) a value may lie beyond its neighbours


def check_firefly_k(k: float | None) -> None:
    """The one check of a stage option `firefly_k`: > 0, or None (clamp off)."""
    if k is not None and not k > 0:
        raise ValueError(f"firefly_k must be > 0 or None, got {k}")


def clamp_fireflies(planes: np.ndarray, k: float = FIREFLY_K) -> np.ndarray:
    """Clip every value to [lo - k (hi - lo), hi + k (hi - lo)], lo and hi the smallest and largest of its
    up-to-8 neighbours in the 3x3 window (the pixel itself excluded; frame border: those that exist).

    planes: (C, H, W) float32 radiance (any sign), per channel. An isolated outlier (a firefly of 1e6, or
    -1e6) is brought back to its neighbourhood; a constant image, a 1x1 frame and any value within the
    spread of its neighbours are unchanged. numba kernel; `clamp_fireflies_reference` is its numpy twin.
    Returns (C, H, W) float32.
    """
    out = np.empty_like(planes, dtype=np.float32)
    _clamp_kernel(np.ascontiguousarray(planes, dtype=np.float32), np.float32(k), out)
    return out


def clamp_fireflies_reference(planes: np.ndarray, k: float = FIREFLY_K, excluded: np.ndarray | None = None,
                              ranged: np.ndarray | None = None) -> np.ndarray:
    """Plain-numpy twin of `clamp_fireflies`. planes: (C, H, W) float32. excluded: (C, H, W) bool or None, values
    left out of their neighbours' ranges (the noise blend's lights but those seen whole); a value with no
    neighbour left keeps itself. ranged: (C, H, W) float32 or None, the values the ranges are taken over (default
    `planes`; the noise blend's lights seen whole at their full value)."""
    last = None if excluded is None else np.moveaxis(excluded, 0, -1)  # (H, W, C) views, as window_range takes them
    source = np.moveaxis(planes if ranged is None else ranged, 0, -1)
    lo, hi = (np.moveaxis(x, -1, 0) for x in window_range(source, centre=False, excluded=last))
    ok = lo <= hi
    spread = np.float32(k) * np.where(ok, hi - lo, 0)
    out = np.clip(planes, np.where(ok, lo, planes) - spread, np.where(ok, hi, planes) + spread)
    return np.where(ok, out, planes).astype(np.float32)


@numba.njit(inline="always")
def _plane_sources(planes, c, y, src_lo, src_hi):  # pragma: no cover - jitted
    """Row y of channel c of planes ((C, H, W) float32) as its neighbours' range sources, written to src_lo and
    src_hi ((W,) float32): a NaN takes no part (+inf, -inf), nor does a row outside the frame."""
    if y < 0 or y >= planes.shape[1]:
        no_sources(src_lo, src_hi)
        return
    row = planes[c, y]
    for x in range(row.shape[0]):  # branch-free: vectorises
        put_source(src_lo, src_hi, x, row[x], False)


@numba.njit(parallel=True, cache=True, error_model="numpy")
def _clamp_kernel(planes, k, out):  # pragma: no cover - jitted
    """out (C, H, W) float32: `clamp_fireflies` of planes (C, H, W) float32, k float32. The 8-neighbour ranges
    come from `service.kernels.row_ranges`, a task per band of rows of a channel."""
    channels, height, width = planes.shape
    bands = -(-height // BAND_ROWS)
    for task in numba.prange(channels * bands):
        c, y0 = task // bands, (task % bands) * BAND_ROWS
        y1 = min(y0 + BAND_ROWS, height)
        src_lo, src_hi, lo, hi, all_lo, all_hi = band_scratch(width)
        for yy in (y0 - 1, y0):
            _plane_sources(planes, c, yy, src_lo[yy % 3], src_hi[yy % 3])
        for y in range(y0, y1):
            _plane_sources(planes, c, y + 1, src_lo[(y + 1) % 3], src_hi[(y + 1) % 3])
            three_row_ranges(src_lo, src_hi, y, 1, False, lo, hi, all_lo, all_hi)
            src, dst = planes[c, y], out[c, y]
            for x in range(width):  # branch-free: vectorises
                v = src[x]
                spread = k * (hi[x] - lo[x])
                dst[x] = min(max(v, lo[x] - spread), hi[x] + spread) if lo[x] <= hi[x] else v  # no neighbour: itself


ROBUST_RADIUS = 3  # clamp_outlier_clusters: window half-size, pixels (7x7: a 3x3 cluster is 9/49 of it)


ROBUST_CLIP = 1.5  # first pass keeps |t - mean| <= 1.5 std: a cluster under ~30% of the window is left out


ROBUST_K = 3.0  # second pass: a value may lie k clipped stds beyond the clipped mean (compressed units) ...


ROBUST_MARGIN = 1.0  # ... plus this margin, in compressed units (a factor e = 2.7 above the local level)


def radiance_scale(planes: np.ndarray) -> float:
    """Typical magnitude of a frame: the median of |value| over a 4x4-strided subsample (cheap at 720p),
    floored at 1e-6. planes: (C, H, W) float32 radiance. Below this scale the log transform of
    `clamp_outlier_clusters` is about linear."""
    sample = np.abs(planes[:, ::4, ::4]).ravel()
    if not sample.size:
        return 1e-6
    half = sample.size // 2  # the median by one partition (np.median partitions at two indices)
    part = np.partition(sample, half)
    median = float(part[half]) if sample.size % 2 else 0.5 * (float(part[:half].max()) + float(part[half]))
    return max(median, 1e-6)


def clamp_outlier_clusters(
    planes: np.ndarray,
    radius: int = ROBUST_RADIUS,
    k: float = ROBUST_K,
    clip: float = ROBUST_CLIP,
    margin: float = ROBUST_MARGIN,
) -> np.ndarray:
    """Clip values that stand out from a robust local statistic of the range-compressed signal.

    `clamp_fireflies` compares a value with its 8 neighbours, so a cluster of outliers (several bright
    samples side by side, or the emitter-edge residual left by subtracting a differently sampled emission
    buffer) shields itself. Here, per channel, on t = sign(x) log(1 + |x| / s) (s = `radiance_scale`, so
    log-like above the frame's typical level and linear near 0; signed, so negative outliers too), over
    the (2r+1)^2 window clipped to the frame:
      1. mean m and std d of t;
      2. one sigma-clipping step: the clipped mean m' and std d' of the t with |t - m| <= clip * d only.
         A group of outliers covering less than ~1 / (1 + clip^2) of the window (31% for clip 1.5) lies
         outside m +- clip * d and drops out, so it cannot raise the statistic it is judged by;
      3. t is clipped to m' +- (k d' + margin) and mapped back to radiance.
    Values inside that band, a constant image and smooth gradients are unchanged; structures that fill
    more than ~1/3 of the window count as signal. Limitation: thin bright detail (a 1-2 pixel line more
    than e^(k d' + margin) above its surround) is clipped too: the regressions fed by this blur such detail
    anyway unless a G-buffer explains it.

    planes: (C, H, W) float32 radiance (any sign). Returns (C, H, W) float32. numba kernel: t in float32
    by a vectorised log (`_log_fast`, relative error ~1e-7), box sums and statistics in float64, fused per
    band of rows; matches `clamp_outlier_clusters_reference`, the plain-numpy twin, to ~1e-6 relative.
    """
    if radius < 0:
        raise ValueError(f"radius must be >= 0, got {radius}")
    planes = np.ascontiguousarray(planes, dtype=np.float32)
    out = np.empty_like(planes)
    if planes.size:
        _cluster_kernel(planes, radiance_scale(planes), int(radius), float(k), float(clip), float(margin), out)
    return out


def _box_mean_reference(planes: np.ndarray, radius: int) -> np.ndarray:
    """Mean over the (2r+1)^2 window clipped to the frame, of (C, H, W) float64 planes (cumulative sums)."""
    _, height, width = planes.shape
    total = planes
    for axis, n in ((1, height), (2, width)):
        c = np.cumsum(total, axis=axis)
        c = np.concatenate([np.zeros_like(np.take(c, [0], axis=axis)), c], axis=axis)
        hi = np.minimum(np.arange(n) + radius + 1, n)
        lo = np.maximum(np.arange(n) - radius, 0)
        total = np.take(c, hi, axis=axis) - np.take(c, lo, axis=axis)
    ys, xs = np.arange(height), np.arange(width)
    count = np.outer(np.minimum(ys + radius, height - 1) - np.maximum(ys - radius, 0) + 1,
                     np.minimum(xs + radius, width - 1) - np.maximum(xs - radius, 0) + 1)  # fmt: skip
    return total / count


def clamp_outlier_clusters_reference(
    planes: np.ndarray,
    radius: int = ROBUST_RADIUS,
    k: float = ROBUST_K,
    clip: float = ROBUST_CLIP,
    margin: float = ROBUST_MARGIN,
) -> np.ndarray:
    """Plain-numpy twin of `clamp_outlier_clusters`."""
    if radius < 0:
        raise ValueError(f"radius must be >= 0, got {radius}")
    planes = np.asarray(planes, np.float32)
    if not planes.size:
        return planes.copy()
    s = radiance_scale(planes)
    t = np.sign(planes) * np.log1p(np.abs(planes.astype(np.float64)) / s)
    mean = _box_mean_reference(t, radius)
    std = np.sqrt(np.maximum(_box_mean_reference(t * t, radius) - mean * mean, 0.0))
    keep = (np.abs(t - mean) <= clip * std).astype(np.float64)
    n = np.maximum(_box_mean_reference(keep, radius), 1e-12)  # the centre of a window is never all out
    mean = np.where(n > 1e-9, _box_mean_reference(t * keep, radius) / n, mean)
    std = np.sqrt(np.maximum(_box_mean_reference(t * t * keep, radius) / n - mean * mean, 0.0))
    bound = k * std + margin
    clipped = np.clip(t, mean - bound, mean + bound)
    back = np.sign(clipped) * s * np.expm1(np.abs(clipped))
    return np.where(clipped == t, planes, back).astype(np.float32)


@numba.njit(inline="always", fastmath=True)
def _log_fast(v):
    """log(v) for finite float32 v >= 1, relative error ~1e-7 (Cephes logf polynomial). Vectorisable,
    unlike a call to logf: v = 2^e m with m in [sqrt(1/2), sqrt(2)), log v = e ln 2 + log m."""
    bits = float32_to_bits(v)
    e = np.float32((bits >> np.int32(23)) - np.int32(127))
    m = bits_to_float32((bits & np.int32(0x7FFFFF)) | np.int32(0x3F800000))  # [1, 2)
    big = m > np.float32(1.4142135623730951)
    m = m * np.float32(0.5) if big else m
    e = e + np.float32(1.0) if big else e
    f = m - np.float32(1.0)
    z = f * f
    p = np.float32(7.0376836292e-2)
    p = p * f - np.float32(1.1514610310e-1)
    p = p * f + np.float32(1.1676998740e-1)
    p = p * f - np.float32(1.2420140846e-1)
    p = p * f + np.float32(1.4249322787e-1)
    p = p * f - np.float32(1.6668057665e-1)
    p = p * f + np.float32(2.0000714765e-1)
    p = p * f - np.float32(2.4999993993e-1)
    p = p * f + np.float32(3.3333331174e-1)
    y = p * f * z - np.float32(2.12194440e-4) * e - np.float32(0.5) * z
    return f + y + np.float32(0.693359375) * e


ROBUST_BAND = 16  # rows per task of `_cluster_kernel`: running column sums over the band, 2r rows of halo


@numba.njit(inline="always")
def _box_rows(padded, radius, width, out):
    """out[x] = sum of padded[x .. x + 2r]: a row of width + 2r with r zeros each side, so the window
    is clipped to the frame. Shifted adds, two per pass over `out`, on views indexed from 0 (no
    negative-index fix-up): contiguous along x, vectorises."""
    first = padded[0:]
    for x in range(width):
        out[x] = first[x]
    for d in range(1, 2 * radius + 1, 2):
        a, b = padded[d:], padded[d + 1 :]
        for x in range(width):
            out[x] += a[x] + b[x]


@numba.njit(inline="always")
def _add_row(cols, t, keep, second, sign, width, pad):
    """cols[:, pad + x] += sign * [t, t^2] (first sweep) or sign * [keep, t keep, t^2 keep] (second)."""
    if second:
        c0, c1, c2 = cols[0, pad:], cols[1, pad:], cols[2, pad:]  # views: the loop vectorises
        for x in range(width):
            a, w = np.float64(t[x]), sign * np.float64(keep[x])
            c0[x] += w
            c1[x] += w * a
            c2[x] += w * a * a
    else:
        c0, c1 = cols[0, pad:], cols[1, pad:]
        for x in range(width):
            a = np.float64(t[x])
            c0[x] += sign * a
            c1[x] += sign * a * a


@numba.njit(parallel=True, cache=True, fastmath=True, error_model="numpy")
def _cluster_kernel(planes, s, radius, k, clip, margin, out):
    """Three sweeps over all channels: t (float32, fast log); box sums of [t, t^2] -> mean, std -> keep
    mask; box sums of [keep, t keep, t^2 keep] -> clipped mean, std -> clip. Box sums: float64 running
    column sums over bands of ROBUST_BAND rows, then 2r+1 shifted adds along x."""
    channels, height, width = planes.shape
    inv_s = np.float32(1.0 / s)
    t = np.empty((channels, height, width), np.float32)
    keep = np.empty((channels, height, width), np.uint8)
    inv_nx = np.empty(width)
    for x in range(width):
        inv_nx[x] = 1.0 / (min(x + radius, width - 1) - max(x - radius, 0) + 1)
    for row in numba.prange(channels * height):
        src, dst = planes[row // height, row % height], t[row // height, row % height]
        for x in range(width):
            v = src[x]
            a = _log_fast(np.float32(1.0) + abs(v) * inv_s)
            dst[x] = a if v >= 0 else -a
    bands = (height + ROBUST_BAND - 1) // ROBUST_BAND
    for second in range(2):
        for task in numba.prange(channels * bands):
            c, y0 = task // bands, (task % bands) * ROBUST_BAND
            cols = np.zeros((3, width + 2 * radius))  # running sums over the window's rows, r zeros each side
            box = np.empty((3, width))
            for y in range(max(0, y0 - radius), min(height, y0 + radius)):
                _add_row(cols, t[c, y], keep[c, y], second, 1.0, width, radius)
            for y in range(y0, min(height, y0 + ROBUST_BAND)):
                if y + radius < height:
                    _add_row(cols, t[c, y + radius], keep[c, y + radius], second, 1.0, width, radius)
                inv_ny = 1.0 / (min(y + radius, height - 1) - max(y - radius, 0) + 1)
                for q in range(3 if second else 2):
                    _box_rows(cols[q], radius, width, box[q])
                tr = t[c, y]
                if second == 0:
                    kr = keep[c, y]
                    for x in range(width):
                        ic = inv_nx[x] * inv_ny
                        m = box[0, x] * ic
                        d = np.sqrt(max(box[1, x] * ic - m * m, 0.0))
                        kr[x] = 1 if abs(tr[x] - m) <= clip * d else 0
                else:
                    clipped = box[0]  # reused: box[0] is read before it is overwritten
                    src, dst = planes[c, y], out[c, y]
                    changed = 0
                    for x in range(width):  # branch-free: vectorises
                        ic = inv_nx[x] * inv_ny
                        n = max(box[0, x] * ic, 1e-12)
                        w = ic / n  # one division: means of t keep and t^2 keep over the kept fraction
                        # No value kept: only when the window's std rounds to 0, all its t equal the first
                        # mean to rounding, and t itself (unchanged) is what the reference's fallback gives.
                        m = box[1, x] * w if n > 1e-9 else np.float64(tr[x])
                        d = np.sqrt(max(box[2, x] * w - m * m, 0.0))
                        bound = k * d + margin
                        a = np.float64(tr[x])
                        b = min(max(a, m - bound), m + bound)
                        clipped[x] = b
                        changed += b != a
                        dst[x] = src[x]
                    if changed:  # rarely clipped: expm1 only there
                        for x in range(width):
                            b = clipped[x]
                            if b != tr[x]:
                                e = s * np.expm1(abs(b))
                                dst[x] = e if b >= 0 else -e
                if y - radius >= 0:
                    _add_row(cols, t[c, y - radius], keep[c, y - radius], second, -1.0, width, radius)


def clamp_outlier_planes(planes: np.ndarray, firefly_k: float | None = FIREFLY_K, robust: bool = True) -> np.ndarray:
    """(C, H, W) float32 radiance planes (any sign) with isolated outliers clipped (`clamp_fireflies`, k =
    firefly_k; None: off) and then small clusters of them (`clamp_outlier_clusters`; robust=False: off).
    Returns (C, H, W) float32; a constant image and smooth gradients are unchanged."""
    if firefly_k is not None:
        planes = clamp_fireflies(planes, firefly_k)
    if robust:  # clusters of outliers, which the 3x3 clamp cannot see
        planes = clamp_outlier_clusters(planes)
    return planes


def _sky(image: np.ndarray, albedo: np.ndarray) -> np.ndarray:
    """(H, W) bool: pixels whose albedo ((H, W, C) float32) is below ALBEDO_EPS in every channel and whose
    radiance ((H, W, C) float32) is not 0 in some channel. numba, a task per row."""
    sky = np.empty(image.shape[:2], np.bool_)
    _sky_kernel(image, albedo, sky)
    return sky


@numba.njit(parallel=True, cache=True, error_model="numpy")
def _sky_kernel(image, albedo, sky):  # pragma: no cover - jitted
    height, width, channels = image.shape
    for y in numba.prange(height):
        for x in range(width):
            unlit, shows = True, False
            for c in range(channels):
                unlit = unlit and albedo[y, x, c] < ALBEDO_EPS
                shows = shows or image[y, x, c] != 0
            sky[y, x] = unlit and shows


@numba.njit(parallel=True, cache=True, error_model="numpy")
def _demodulated_planes(image, albedo, planes):  # pragma: no cover - jitted
    """planes (C, H, W) float32: `albedo.demodulate` of image by albedo ((H, W, C) float32), planar."""
    height, width, channels = image.shape
    for y in numba.prange(height):
        for c in range(channels):
            row = planes[c, y]
            for x in range(width):
                row[x] = image[y, x, c] / albedo_factor(albedo[y, x, c])


@numba.njit(parallel=True, cache=True, error_model="numpy")
def _lowered_kernel(image, albedo, kept, out):  # pragma: no cover - jitted
    """out (H, W, C) float32: where the clamp moved a demodulated value (kept, (C, H, W) float32, against image's
    demodulated by albedo, both (H, W, C) float32), its remodulation if that is closer to 0, and where image is
    NaN; image elsewhere (`clamp_outliers`)."""
    height, width, channels = image.shape
    for y in numba.prange(height):
        for x in range(width):
            for c in range(channels):
                value, factor = image[y, x, c], albedo_factor(albedo[y, x, c])
                k = kept[c, y, x]
                back = k * factor
                lowered = (k != value / factor and abs(back) < abs(value)) or np.isnan(value)
                out[y, x, c] = back if lowered else value


def clamp_outliers(image: np.ndarray, firefly_k: float = FIREFLY_K,
                   halves: tuple[np.ndarray, np.ndarray] | None = None, albedo: np.ndarray | None = None) -> np.ndarray:
    """`image` ((H, W, C) float32 linear radiance, any sign) through `clamp_outlier_planes` with both clamps.

    halves: None, or (A, B), each (H, W, C) float32, the two half-sample estimates whose mean is `image`
    (less the same emission). A firefly is one rare sample, so it is in one half only; a value both halves
    show (a small glint, seen again by the other half's samples) is signal. With the halves, a value
    clipped below min(A, B) is brought back up to it (never above `image`), per channel: the glint survives
    at the level both halves vouch for, a one-half firefly is clipped as before.
    albedo: None, or the frame's (H, W, C) float32 albedo: the clamps then judge the demodulated image
    (`albedo.demodulate`, as the filters see it) and the clipped values are remodulated where that brings
    them closer to 0 (or the value was NaN); the others keep their bits. A bright texel among dark ones is
    texture, not a firefly, and a firefly at a pixel the surface only partly covers (a silhouette's edge,
    albedo 0.1) stands out against its neighbours' irradiance where its radiance did not. A value is never
    raised: a surface pixel seen among sky pixels of albedo 0 (irradiance radiance / ALBEDO_EPS) is dark
    against their irradiance, and lifted to it and remodulated by its own albedo it would become a firefly.
    Pixels whose albedo is below ALBEDO_EPS in every channel (the sky, the void, black paint) have radiance
    that is no albedo times an irradiance. Where one of them shows light (a sky, not the black void), every
    pixel within ROBUST_RADIUS of it is judged on its radiance as without the albedo: a silhouette's edge
    pixel (albedo 0.1, radiance 0.9 of which the sky gave 0.8) would have an irradiance of 9 against its
    neighbours' 1 and come out dark, a sky pixel seen through a gap would be bright against the surfaces'
    irradiance only because its albedo is 0. Returns (H, W, C) float32 (inputs are judged as float32).
    """
    for name, other in (("halves", halves or ()), ("albedo", () if albedo is None else (albedo,))):
        if any(np.shape(x) != image.shape for x in other):
            raise ValueError(f"clamp_outliers: the {name} {[np.shape(x) for x in other]} must match {image.shape}")
    image = np.ascontiguousarray(image, dtype=np.float32)
    albedo = None if albedo is None else np.ascontiguousarray(albedo, dtype=np.float32)
    sky = None if albedo is None else _sky(image, albedo)
    by_radiance = None
    if albedo is None or sky.any():
        by_radiance = from_planes(clamp_outlier_planes(to_planes(image), firefly_k))
    if albedo is None:
        clamped = by_radiance
    else:
        flat = np.empty((image.shape[2], *image.shape[:2]), np.float32)
        _demodulated_planes(image, albedo, flat)
        clamped = np.empty_like(image)
        _lowered_kernel(image, albedo, clamp_outlier_planes(flat, firefly_k), clamped)
        if by_radiance is not None:
            near = box_mean(sky[..., None].astype(np.float32), ROBUST_RADIUS) > 0
            clamped = np.where(near, by_radiance, clamped)
    if halves is None:
        return clamped
    color_a, color_b = halves
    shown = np.minimum(np.minimum(color_a, color_b), image)
    return np.maximum(clamped, shown, out=clamped)
