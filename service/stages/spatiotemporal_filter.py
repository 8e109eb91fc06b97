"""The spatiotemporal filter of the cross-regression denoiser (Choi et al. 2024, sec. 4.2, eqs. 8-10).

Each pilot estimate (A and B, log1p radiance) is averaged over an 11x11 window with cross-bilateral
weights whose four bandwidths the network predicts per centre pixel c (eq. 9, read as the exponential
of minus the sum of the four normalised squared differences, as the authors' code computes it):

    m_i^A = exp(-kA_c |fA_i - fA_c|^2 - kAlb_c |rho_i - rho_c|^2 - kN_c |n_i - n_c|^2 - kP_c |p_i - p_c|^2 / r^2)

with k = 1 / (theta^2 + eps) the precisions the network head emits (see service.layout.CROSSREG_OUTPUTS)
and r = 5 the window half-size (positions normalised by it, as in the authors' code). The spatial mean is
blended with the reprojected previous output by theta_alpha (eq. 8); where reprojection failed the
weight of the current frame is 1. The A and B results are combined by their weight sums (eq. 10).

With `pilot_bandwidth` b > 0 (ours; crossreg's option of that name) the pilot-colour precisions kA and kB are
at least 1 / (b s^2 + PRECISION_EPS), s^2 the pilots' local disagreement: half the mean, over the channels and
the 5x5 pixels around, of (fA - fB)^2. A neighbour whose pilot differs by more than sqrt(b) s then weighs at
most 1/e, however wide the network made the bandwidth: where the pilots agree that a shadow's edge is there (an
edge no G-buffer shows), the filter stops at it; where they are noisy (s large), the floor is low and the
network's bandwidth stands. The pilots' errors correlate (docs/crossreg_authors.md), so s^2 is smaller than
either pilot's variance; b = 32 was chosen from 16, 32 and 64 on the 64-frame sequences (docs/benchmarks.md,
"Long sequences": crossreg's temporal error on `shadows` -7%, relL2 on `textures` -4%, no sequence worse by
more than 0.3%). The torch twin (models/train/filter.py) has the floor too, held to this one by a parity test;
online training goes through the network's own precisions (trained through the floor it did worse).

Layout: channel planes (C, H, W), the layout of the network's input and output tensors (service.layout),
so the filter reads the U-Net's input planes and its output as they are. Neighbours outside the frame are
left out (no padding), as in service.kernels.window; the centre always has weight 1, so every
normalisation is safe.

Speed: the numba kernel takes bands of rows in parallel and each row in tiles of columns. A per-thread
scratch holds a ring with the 2 radius + 1 image rows of the window (their 12 feature planes over the
tile's columns, widened by the radius) and the tile's precisions, every plane a row of a compile-time
constant stride, so LLVM addresses all of them from one base pointer and vectorizes the fused
weight-and-accumulate loop (16 lanes with AVX-512); each step down a band copies one new image row into
the ring. exp is a polynomial (no SVML on our CPUs; relative error of a weight < 5e-6). Eqs. 8 and 10 are
applied in the same pass. `reference=True` runs the plain-numpy twins (whole-plane shifts, np.exp) that
the tests hold the kernels to. This numpy/numba module is the inference side; models/train/filter.py is
the same filter in torch for training, held to this one by a parity test.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from service.kernels.window import overlap, window_offsets
from service.stages.range_clamp import check_radius, local_range_reference, row_range
from service.stages.svgf import box_mean

FILTER_RADIUS = 5  # Choi 2024 eq. 8: 11x11 denoising window; authors' code FILTER_WIDTH = 11
N_PRECISIONS = 5  # colour A, colour B, albedo, normal, position (layout.CROSSREG_OUTPUTS[:5])
SCREEN_RADIUS = 3  # 7x7 window of the history screening (authors' code: temporal_screening win_curr = 7)
SPREAD_RADIUS = 2  # the pilots' local disagreement s^2: mean over 5x5 pixels (module docstring)
PRECISION_EPS = 1e-4  # ... the floor 1 / (b s^2 + eps) is at most 1e4 where the pilots agree exactly
MAX_PILOT_BANDWIDTH = 1e4  # largest `pilot_bandwidth`


@dataclass(frozen=True)
class FilterOutput:
    """What the filter produces, all in log1p radiance space unless stated; planes (C, H, W).

    color: (3, H, W) float32, the final output f(x) of eq. 10 (temporally blended).
    color_a, color_b: (3, H, W) float32, the per-pilot outputs of eq. 8 (used by the loss).
    weight_a, weight_b: (H, W) float32 >= 1, the weight sums of eq. 10.
    """

    color: np.ndarray
    color_a: np.ndarray
    color_b: np.ndarray
    weight_a: np.ndarray
    weight_b: np.ndarray


_U = np.uint64  # unsigned indices: numba then skips the negative-index wraparound and LLVM vectorizes
_F32 = np.float32
EXP_FLOOR = -18.4  # exp(-18.4) = 1e-8: weights below are negligible next to the centre's 1


@numba.njit(inline="always", fastmath=True, cache=True)
def _exp_neg(x):  # pragma: no cover - jitted
    """exp(x) for x <= 0, vectorizable (no SVML here): exp(x/32)^32, degree-8 Taylor on [-0.575, 0].

    Relative error < 5e-6 for x >= EXP_FLOOR; below it returns ~1e-8 instead of a smaller number."""
    t = max(x, _F32(EXP_FLOOR)) * _F32(1.0 / 32.0)
    p = _F32(1.0 / 40320.0)
    p = p * t + _F32(1.0 / 5040.0)
    p = p * t + _F32(1.0 / 720.0)
    p = p * t + _F32(1.0 / 120.0)
    p = p * t + _F32(1.0 / 24.0)
    p = p * t + _F32(1.0 / 6.0)
    p = p * t + _F32(0.5)
    p = p * t + _F32(1.0)
    p = p * t + _F32(1.0)
    p = p * p
    p = p * p
    p = p * p
    p = p * p
    return p * p


# Per-thread scratch of the filter kernel, in rows of _STRIDE floats (a compile-time constant, so every row is
# a constant offset from a loop-invariant base and LLVM needs one pointer for all of them): a ring of
# 2 radius + 1 slots, image row y in slot y % (2 radius + 1), each holding the _FEATURES planes of that row
# over the tile's columns widened by the radius (column X of the tile starting at t0 at X - t0 + pad), then
# the tile's precisions (column t0 + i at i).
_STRIDE = 288  # floats; 1152 bytes, a multiple of the 64-byte vector
MAX_RADIUS = 64  # largest filter radius the scratch takes (tiles of >= 160 pixels)
_FEATURES = 12  # planes per ring slot: pilot A (3), pilot B (3), albedo (3), normal (3)
_PA, _PB, _ALB, _NRM = 0, 3, 6, 9  # their first rows in a slot
_KA, _KB, _KALB, _KN, _KP = 0, 1, 2, 3, 4  # rows of the precisions (layout.CROSSREG_OUTPUTS order)
_ACC_ROWS = 8  # sum of weight x pilot A (3), weight A, sum of weight x pilot B (3), weight B
_BAND = 48  # image rows per parallel task; the ring is filled anew (2 radius rows) once per band and tile


@numba.njit(inline="always", cache=True)
def _aligned_empty(size):  # pragma: no cover - jitted
    """(size,) float32 scratch starting on a 64-byte boundary, so the centre's vector loads are aligned."""
    buffer = np.empty(size + 16, np.float32)
    start = (-(buffer.ctypes.data // 4)) % 16
    return buffer[start : start + size]


@numba.njit(inline="always", cache=True)
def _load_planes(planes, y, x0, x1, scratch, base):  # pragma: no cover - jitted
    """scratch[base + c * _STRIDE + j] = planes[c, y, x0 + j] for every plane c and j < x1 - x0."""
    for c in range(planes.shape[0]):
        source, target = planes[c, y], scratch[base + c * _STRIDE :]
        for j in range(x1 - x0):
            target[_U(j)] = source[_U(x0 + j)]


@numba.njit(inline="always", cache=True)
def _load_slot(pilot_a, pilot_b, albedo, normal, y, x0, x1, scratch, base):  # pragma: no cover - jitted
    """The _FEATURES planes of image row y, columns [x0, x1), into the ring slot at `base`."""
    _load_planes(pilot_a, y, x0, x1, scratch, base + _PA * _STRIDE)
    _load_planes(pilot_b, y, x0, x1, scratch, base + _PB * _STRIDE)
    _load_planes(albedo, y, x0, x1, scratch, base + _ALB * _STRIDE)
    _load_planes(normal, y, x0, x1, scratch, base + _NRM * _STRIDE)


@numba.njit(inline="always", fastmath=True, cache=True)
def _accumulate(scratch, acc, i0, i1, centre, neighbour, precisions, pos):  # pragma: no cover - jitted
    """Eq. 9 weights of the tile's centres i in [i0, i1) (slot columns centre + i) against their neighbours
    (slot columns neighbour + i), added with the weighted neighbour pilots into acc. precisions: scratch
    index of the tile's precision rows. pos: |p_i - p_c|^2 / r^2 of this offset."""
    for k in range(i1 - i0):
        i = _U(i0 + k)
        c = _U(centre) + i
        n = _U(neighbour) + i
        p = _U(precisions) + i
        dist_a = _F32(0.0)
        dist_b = _F32(0.0)
        dist_alb = _F32(0.0)
        dist_n = _F32(0.0)
        for ch in range(3):
            o = _U((_PA + ch) * _STRIDE)
            d = scratch[n + o] - scratch[c + o]
            dist_a += d * d
            o = _U((_PB + ch) * _STRIDE)
            d = scratch[n + o] - scratch[c + o]
            dist_b += d * d
            o = _U((_ALB + ch) * _STRIDE)
            d = scratch[n + o] - scratch[c + o]
            dist_alb += d * d
            o = _U((_NRM + ch) * _STRIDE)
            d = scratch[n + o] - scratch[c + o]
            dist_n += d * d
        shared = (
            scratch[p + _U(_KALB * _STRIDE)] * dist_alb
            + scratch[p + _U(_KN * _STRIDE)] * dist_n
            + scratch[p + _U(_KP * _STRIDE)] * pos
        )
        wa = _exp_neg(-(scratch[p + _U(_KA * _STRIDE)] * dist_a + shared))
        wb = _exp_neg(-(scratch[p + _U(_KB * _STRIDE)] * dist_b + shared))
        for ch in range(3):
            acc[i + _U(ch * _STRIDE)] += wa * scratch[n + _U((_PA + ch) * _STRIDE)]
            acc[i + _U((4 + ch) * _STRIDE)] += wb * scratch[n + _U((_PB + ch) * _STRIDE)]
        acc[i + _U(3 * _STRIDE)] += wa
        acc[i + _U(7 * _STRIDE)] += wb


@numba.njit(inline="always", fastmath=True, cache=True)
def _finish(
    acc, params, min_alpha, previous, valid, y, t0, count, color, color_a, color_b, weight_a, weight_b
):  # pragma: no cover - jitted
    """Eqs. 8 and 10 for the tile's centres (t0 + i, i < count) of row y, from the sums in acc (row views
    and unsigned indices, so the loops vectorize); alpha at least min_alpha."""
    alpha_row, valid_row = params[N_PRECISIONS, y, t0:], valid[y, t0:]
    sums_wa, sums_wb = acc[3 * _STRIDE :], acc[7 * _STRIDE :]
    for c in range(3):
        sums_a, sums_b = acc[c * _STRIDE :], acc[(4 + c) * _STRIDE :]
        history, out, out_a, out_b = previous[c, y, t0:], color[c, y, t0:], color_a[c, y, t0:], color_b[c, y, t0:]
        for i in range(count):
            i = _U(i)
            wa, wb = sums_wa[i], sums_wb[i]
            alpha = max(alpha_row[i], min_alpha) if valid_row[i] else _F32(1.0)
            kept = (_F32(1.0) - alpha) * history[i]
            a = alpha * (sums_a[i] / wa) + kept
            b = alpha * (sums_b[i] / wb) + kept
            out_a[i], out_b[i] = a, b
            out[i] = (a * wa + b * wb) / (wa + wb)
    weight_a[y, t0 : t0 + count] = sums_wa[:count]
    weight_b[y, t0 : t0 + count] = sums_wb[:count]


@numba.njit(parallel=True, fastmath=True, cache=True, error_model="numpy")
def _filter_kernel(
    pilot_a, pilot_b, albedo, normal, params, min_alpha, previous, valid, radius, color, color_a, color_b, weight_a,
    weight_b,
):  # pragma: no cover - jitted
    """Bands of rows in parallel, each in tiles of columns; arguments as `_filter_reference`."""
    _, height, width = pilot_a.shape
    slots, slot = 2 * radius + 1, _FEATURES * _STRIDE
    pad = 16 * ((radius + 15) // 16)  # >= radius, keeps the centre columns 64-byte aligned
    tile = _STRIDE - pad - radius
    precisions = slots * slot  # scratch index of the precision rows
    inv_r2 = _F32(1.0) / _F32(max(radius, 1) * max(radius, 1))
    for band in numba.prange((height + _BAND - 1) // _BAND):
        scratch = _aligned_empty(precisions + N_PRECISIONS * _STRIDE)
        acc = _aligned_empty(_ACC_ROWS * _STRIDE)
        y0, y1 = band * _BAND, min(height, (band + 1) * _BAND)
        for t0 in range(0, width, tile):
            count = min(width, t0 + tile) - t0
            x0, x1 = max(0, t0 - radius), min(width, t0 + count + radius)  # columns any centre of the tile sees
            shift = pad - t0 + x0  # slot column of x0
            for yy in range(max(0, y0 - radius), min(height, y0 + radius)):  # the window of row y0, but y0 + r
                _load_slot(pilot_a, pilot_b, albedo, normal, yy, x0, x1, scratch, (yy % slots) * slot + shift)
            for y in range(y0, y1):
                if y + radius < height:  # completes the window of row y
                    base = ((y + radius) % slots) * slot + shift
                    _load_slot(pilot_a, pilot_b, albedo, normal, y + radius, x0, x1, scratch, base)
                _load_planes(params[:N_PRECISIONS], y, t0, t0 + count, scratch, precisions)
                acc[:] = 0.0
                for yy in range(max(0, y - radius), min(height, y + radius + 1)):
                    dy2 = _F32((yy - y) * (yy - y))
                    for dx in range(-radius, radius + 1):
                        pos = (_F32(dx * dx) + dy2) * inv_r2
                        i0, i1 = max(0, -dx - t0), min(count, width - dx - t0)
                        centre, neighbour = (y % slots) * slot + pad, (yy % slots) * slot + pad + dx
                        _accumulate(scratch, acc, i0, i1, centre, neighbour, precisions, pos)
                _finish(acc, params, min_alpha, previous, valid, y, t0, count, color, color_a, color_b, weight_a,
                        weight_b)


def _filter_reference(
    pilot_a, pilot_b, albedo, normal, params, min_alpha, previous, valid, radius, color, color_a, color_b, weight_a,
    weight_b,
) -> None:
    """Plain-numpy twin of `_filter_kernel`: whole-plane shifts over the window and np.exp.

    Inputs as `spatiotemporal_filter` (planes, contiguous float32; previous zeros and valid all False when
    there is no history); writes color, color_a, color_b (3, H, W) and weight_a, weight_b (H, W) in place.
    """
    _, height, width = pilot_a.shape
    sums = np.zeros((_ACC_ROWS, height, width), np.float32)
    inv_r2 = 1.0 / max(radius, 1) ** 2
    for dy, dx in window_offsets(radius):
        pair = overlap(height, width, dy, dx)
        if pair is None:
            continue
        centre, neighbour = pair

        def dist(planes, centre=centre, neighbour=neighbour):
            diff = planes[(slice(None), *neighbour)] - planes[(slice(None), *centre)]
            return (diff * diff).sum(axis=0)

        k = params[(slice(None), *centre)]
        shared = k[_KALB] * dist(albedo) + k[_KN] * dist(normal) + k[_KP] * np.float32((dy * dy + dx * dx) * inv_r2)
        for first, pilot, k_pilot in ((0, pilot_a, k[_KA]), (4, pilot_b, k[_KB])):
            weight = np.exp(-(k_pilot * dist(pilot) + shared))
            sums[(slice(first, first + 3), *centre)] += weight * pilot[(slice(None), *neighbour)]
            sums[(first + 3, *centre)] += weight
    weight_a[:], weight_b[:] = sums[3], sums[7]
    alpha = np.where(valid, np.maximum(params[N_PRECISIONS], min_alpha), np.float32(1.0))
    history = (np.float32(1.0) - alpha) * previous
    color_a[:] = alpha * (sums[0:3] / weight_a) + history
    color_b[:] = alpha * (sums[4:7] / weight_b) + history
    color[:] = (color_a * weight_a + color_b * weight_b) / (weight_a + weight_b)


def check_pilot_bandwidth(bandwidth: float) -> None:
    """Raise ValueError unless 0 <= bandwidth <= MAX_PILOT_BANDWIDTH (this filter's and its torch twin's check)."""
    if not 0 <= bandwidth <= MAX_PILOT_BANDWIDTH:
        raise ValueError(f"pilot_bandwidth must be in [0, {MAX_PILOT_BANDWIDTH:g}], got {bandwidth}")


def pilot_precision_floor(pilot_a: np.ndarray, pilot_b: np.ndarray, bandwidth: float) -> np.ndarray:
    """The floor of the pilot-colour precisions (module docstring): 1 / (bandwidth s^2 + PRECISION_EPS).
    pilot_a, pilot_b: (3, H, W) float32 log1p radiance; bandwidth > 0. Returns (H, W) float32."""
    disagreement = ((pilot_a - pilot_b) ** 2).mean(axis=0)[..., None]
    spread = 0.5 * box_mean(disagreement, SPREAD_RADIUS)[..., 0]
    return (1.0 / (np.float32(bandwidth) * spread + np.float32(PRECISION_EPS))).astype(np.float32)


def spatiotemporal_filter(
    pilot_a: np.ndarray,
    pilot_b: np.ndarray,
    albedo: np.ndarray,
    normal: np.ndarray,
    params: np.ndarray,
    previous: np.ndarray | None = None,
    valid: np.ndarray | None = None,
    radius: int = FILTER_RADIUS,
    *,
    min_alpha: float = 0.0,
    pilot_bandwidth: float = 0.0,
    reference: bool = False,
) -> FilterOutput:
    """Eqs. 8-10: cross-bilateral spatial means of both pilots, temporal blend, A/B combination.

    pilot_a, pilot_b: (3, H, W) float32, log1p radiance. albedo: (3, H, W) float32 in [0, 1]; normal:
        (3, H, W) float32 unit world-space normal.
    params: (6, H, W) float32, the network output in layout.CROSSREG_OUTPUTS order (5 precisions > 0,
        then alpha in (0, 1), the weight of the current frame).
    previous: (3, H, W) float32, the previous output reprojected to this frame, log1p radiance, finite;
        None on the first frame. valid: (H, W) bool, where `previous` is usable; None means nowhere.
    radius: window half-size in pixels, 0 to MAX_RADIUS.
    min_alpha: floor of alpha in [0, 1] (crossreg's option of that name; the torch twin takes it too, so
        that online training learns the filter that is served); 0 leaves alpha as the network gave it.
    pilot_bandwidth: b in [0, MAX_PILOT_BANDWIDTH], the floor of the pilot-colour precisions (module
        docstring); 0 leaves them as the network gave them (the paper's filter).
    reference: run the plain-numpy twin instead of numba (slow; for tests).
    Returns FilterOutput (log1p space, planes). Contiguous float32 inputs (views into the network's input
    planes, say) are used without a copy.
    """
    if not 0 <= radius <= MAX_RADIUS:
        raise ValueError(f"filter radius must be in [0, {MAX_RADIUS}], got {radius}")
    if not 0 <= min_alpha <= 1:
        raise ValueError(f"min_alpha must be in [0, 1], got {min_alpha}")
    check_pilot_bandwidth(pilot_bandwidth)
    _, height, width = pilot_a.shape
    if previous is None or valid is None:
        previous, valid = np.zeros((3, height, width), np.float32), np.zeros((height, width), bool)
    shapes = [x.shape for x in (pilot_a, pilot_b, albedo, normal, previous, params, valid)]
    if shapes != [(3, height, width)] * 5 + [(N_PRECISIONS + 1, height, width), (height, width)]:
        raise ValueError(f"spatiotemporal_filter: inconsistent input shapes {shapes}")  # the kernel does not check
    inputs = [np.ascontiguousarray(a, np.float32) for a in (pilot_a, pilot_b, albedo, normal, params, previous)]
    if pilot_bandwidth > 0:  # on a copy: the network's output stays as it came
        inputs[4] = inputs[4].copy()
        np.maximum(inputs[4][:2], pilot_precision_floor(inputs[0], inputs[1], pilot_bandwidth), out=inputs[4][:2])
    out = FilterOutput(
        *(np.empty((3, height, width), np.float32) for _ in range(3)),
        *(np.empty((height, width), np.float32) for _ in range(2)),
    )
    run = _filter_reference if reference else _filter_kernel
    run(*inputs[:5], np.float32(min_alpha), inputs[5], np.ascontiguousarray(valid, bool), int(radius),
        out.color, out.color_a, out.color_b, out.weight_a, out.weight_b)  # fmt: skip
    return out


@numba.njit(inline="always", cache=True)
def _screen_channel(plane, history, y, radius, padded, inside):  # pragma: no cover - jitted
    """inside[x] &= history[y, x] within the min-max of plane (H, W) over the window around (y, x): column
    extrema over the window's rows, then along the row by `range_clamp.row_range`.

    padded: (4, W + 2 radius) float32 scratch (rows lo, hi and their spares); inside: (W,) uint8."""
    height, width = plane.shape
    y0, y1 = max(0, y - radius), min(height, y + radius + 1)
    pad_lo, pad_hi = padded[0], padded[1]
    for x in range(radius):  # columns outside the frame never win (row_range overwrote them last time)
        pad_lo[x] = pad_lo[radius + width + x] = np.inf
        pad_hi[x] = pad_hi[radius + width + x] = -np.inf
    first = plane[y0]
    for x in range(width):
        pad_lo[_U(radius + x)] = pad_hi[_U(radius + x)] = first[_U(x)]
    for yy in range(y0 + 1, y1):
        row = plane[yy]
        for x in range(width):
            v, a, b = row[_U(x)], pad_lo[_U(radius + x)], pad_hi[_U(radius + x)]
            pad_lo[_U(radius + x)] = v if v < a else a
            pad_hi[_U(radius + x)] = v if v > b else b
    if row_range(pad_lo, pad_hi, padded[2], padded[3], 2 * radius + 1, 1):  # branches: the loops vectorise
        _within(history[y], padded[2], padded[3], inside)
    else:
        _within(history[y], pad_lo, pad_hi, inside)


@numba.njit(inline="always", cache=True)
def _within(row, lo, hi, inside):  # pragma: no cover - jitted
    """inside[x] &= lo[x] <= row[x] <= hi[x], x < len(inside)."""
    for x in range(inside.shape[0]):
        v = row[_U(x)]
        inside[_U(x)] &= np.uint8((v >= lo[_U(x)]) & (v <= hi[_U(x)]))


@numba.njit(parallel=True, cache=True, error_model="numpy")
def _screen_kernel(current, history, valid, radius, masks, screened):  # pragma: no cover - jitted
    """Rows in parallel, every channel's window extrema, the comparison and the selection fused (1D row
    views and unsigned indices, so the loops vectorize); arguments as `_screen_reference`."""
    channels, height, width = current.shape
    per_group = channels // masks.shape[0]
    for y in numba.prange(height):
        padded = np.empty((4, width + 2 * radius), np.float32)
        inside = np.empty(width, np.uint8)
        for g in range(masks.shape[0]):
            inside[:] = valid[y]
            for c in range(g * per_group, (g + 1) * per_group):
                _screen_channel(current[c], history[c], y, radius, padded, inside)
            masks[g, y] = inside != 0
            for c in range(g * per_group, (g + 1) * per_group):
                out, kept, fallback = screened[c, y], history[c, y], current[c, y]
                for x in range(width):
                    out[_U(x)] = kept[_U(x)] if inside[_U(x)] else fallback[_U(x)]


def _screen_reference(current, history, valid, radius, masks, screened) -> None:
    """Plain-numpy twin of `_screen_kernel` (window extrema by `range_clamp.local_range_reference`).
    Arguments as `screen_history`; writes masks and screened in place."""
    channels, height, width = current.shape
    lo, hi = (x.transpose(2, 0, 1) for x in local_range_reference(current.transpose(1, 2, 0), radius))
    inside = (history >= lo) & (history <= hi)
    groups = masks.shape[0]
    masks[:] = valid & inside.reshape(groups, channels // groups, height, width).all(axis=1)
    screened[:] = np.where(np.repeat(masks, channels // groups, axis=0), history, current)


def screen_history(
    current: np.ndarray,
    history: np.ndarray,
    valid: np.ndarray,
    radius: int = SCREEN_RADIUS,
    groups: int = 1,
    *,
    reference: bool = False,
) -> tuple[np.ndarray, np.ndarray]:
    """Where reprojected `history` is still plausible: `valid` and, in every channel of a group, within the
    min-max range of `current` over the (2 radius + 1)^2 window around the pixel (cut at the frame edge).

    From the authors' code (temporal_screening), not the paper's text: it rejects history that motion
    vectors carry correctly but whose shading changed (a moving shadow on a static floor). We compare
    with <= where the authors compare strictly, so flat regions (all-black background) keep their history.
    current, history: (C, H, W) float32 planes in the same (log1p) space, C = groups x channels per group
    (several quantities screened in one pass); valid: (H, W) bool. reference: run the plain-numpy twin.
    Returns (masks, screened): masks (groups, H, W) bool, one per group of consecutive channels; screened
    (C, H, W) float32, `history` where its group's mask holds and `current` elsewhere.
    """
    channels, height, width = current.shape
    if channels % groups:
        raise ValueError(f"{channels} channels do not split into {groups} groups")
    if history.shape != current.shape or valid.shape != (height, width):
        raise ValueError(f"screen_history: current {current.shape}, history {history.shape} and valid "
                         f"{valid.shape} do not agree")  # fmt: skip  # the kernel does not check indices
    check_radius(radius)
    masks = np.empty((groups, height, width), bool)
    screened = np.empty((channels, height, width), np.float32)
    run = _screen_reference if reference else _screen_kernel
    run(np.ascontiguousarray(current, np.float32), np.ascontiguousarray(history, np.float32),
        np.ascontiguousarray(valid, bool), int(radius), masks, screened)  # fmt: skip
    return masks, screened
