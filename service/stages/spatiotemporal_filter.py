"""The spatiotemporal filter of the cross-regression denoiser (Choi et al. 2024, sec. 4.2, eqs. 8-10).

Each pilot estimate (A and B, log1p radiance) is averaged over an 11x11 window with cross-bilateral
weights whose four bandwidths the network predicts per centre pixel c (eq. 9, read as the exponential
of minus the sum of the four normalised squared differences, as the authors' code computes it):

    m_i^A = exp(-kA_c |fA_i - fA_c|^2 - kAlb_c |rho_i - rho_c|^2 - kN_c |n_i - n_c|^2 - kP_c |p_i - p_c|^2 / r^2)

with k = 1 / (theta^2 + eps) the precisions the network head emits (see service.layout.CROSSREG_OUTPUTS)
and r = 5 the window half-size (positions normalised by it, as in the authors' code). The spatial mean is
blended with the reprojected previous output by theta_alpha (eq. 8); where reprojection failed the
weight of the current frame is 1. The A and B results are combined by their weight sums (eq. 10).

Neighbours outside the frame are left out (no padding), as in service.stages.window; the centre always
has weight 1, so every normalisation is safe. The numba kernel works on row-planar (H, C, W) copies with
a polynomial exp (no SVML on our CPUs), so LLVM vectorizes it: ~0.5-1 s at 1280x720 on 2 busy cores,
versus ~2 s for a scalar loop; relative error of a weight < 5e-6. This numpy/numba module is the inference side;
models/train/filter.py is the same filter in torch for training, held to this one by a parity test.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

FILTER_RADIUS = 5  # Choi 2024 eq. 8: 11x11 denoising window; authors' code FILTER_WIDTH = 11
N_PRECISIONS = 5  # colour A, colour B, albedo, normal, position (layout.CROSSREG_OUTPUTS[:5])


@dataclass(frozen=True)
class FilterOutput:
    """What the filter produces, all in log1p radiance space unless stated.

    color: (H, W, 3) float32, the final output f(x) of eq. 10 (temporally blended).
    color_a, color_b: (H, W, 3) float32, the per-pilot outputs of eq. 8 (used by the loss).
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


# Row-planar layout of the kernel input: (H, 17, W), channel rows in this order.
_PA, _PB, _ALB, _NRM, _KA, _KB, _KALB, _KN, _KP = 0, 3, 6, 9, 12, 13, 14, 15, 16


@numba.njit(inline="always", fastmath=True, cache=True)
def _row_weights(cy, ny, dx, x0, x1, pos, weights):  # pragma: no cover - jitted
    """Eq. 9 weights of centre row `cy` against neighbour row `ny` shifted by dx, for x in [x0, x1)."""
    for i in range(x1 - x0):
        x = _U(x0 + i)
        xx = _U(x0 + dx + i)
        dist_a = _F32(0.0)
        dist_b = _F32(0.0)
        dist_alb = _F32(0.0)
        dist_n = _F32(0.0)
        for c in range(3):
            c = _U(c)
            d = ny[_U(_PA) + c, xx] - cy[_U(_PA) + c, x]
            dist_a += d * d
            d = ny[_U(_PB) + c, xx] - cy[_U(_PB) + c, x]
            dist_b += d * d
            d = ny[_U(_ALB) + c, xx] - cy[_U(_ALB) + c, x]
            dist_alb += d * d
            d = ny[_U(_NRM) + c, xx] - cy[_U(_NRM) + c, x]
            dist_n += d * d
        shared = cy[_U(_KALB), x] * dist_alb + cy[_U(_KN), x] * dist_n + cy[_U(_KP), x] * pos
        weights[_U(0), x] = _exp_neg(-(cy[_U(_KA), x] * dist_a + shared))
        weights[_U(1), x] = _exp_neg(-(cy[_U(_KB), x] * dist_b + shared))


@numba.njit(inline="always", fastmath=True, cache=True)
def _row_accumulate(ny, dx, x0, x1, weights, acc):  # pragma: no cover - jitted
    for i in range(x1 - x0):
        x = _U(x0 + i)
        xx = _U(x0 + dx + i)
        wa = weights[_U(0), x]
        wb = weights[_U(1), x]
        acc[_U(0), x] += wa * ny[_U(_PA), xx]
        acc[_U(1), x] += wa * ny[_U(_PA + 1), xx]
        acc[_U(2), x] += wa * ny[_U(_PA + 2), xx]
        acc[_U(3), x] += wa
        acc[_U(4), x] += wb * ny[_U(_PB), xx]
        acc[_U(5), x] += wb * ny[_U(_PB + 1), xx]
        acc[_U(6), x] += wb * ny[_U(_PB + 2), xx]
        acc[_U(7), x] += wb


@numba.njit(parallel=True, fastmath=True, cache=True)
def _sums_kernel(planes, radius, out):  # pragma: no cover - jitted
    """planes: (H, 17, W) float32 row-planar inputs; out: (H, 8, W) float32 <- sumA(3), wA, sumB(3), wB."""
    height, _, width = planes.shape
    inv_r2 = _F32(1.0) / _F32(max(radius, 1) * max(radius, 1))
    for y in numba.prange(height):
        acc = np.zeros((8, width), np.float32)
        weights = np.empty((2, width), np.float32)
        cy = planes[y]
        for yy in range(max(0, y - radius), min(height, y + radius + 1)):
            dy2 = _F32((yy - y) * (yy - y))
            ny = planes[yy]
            for dx in range(-radius, radius + 1):
                pos = (_F32(dx * dx) + dy2) * inv_r2
                x0, x1 = max(0, -dx), min(width, width - dx)
                _row_weights(cy, ny, dx, x0, x1, pos, weights)
                _row_accumulate(ny, dx, x0, x1, weights, acc)
        out[y] = acc


def cross_bilateral_sums(
    pilot_a: np.ndarray,
    pilot_b: np.ndarray,
    albedo: np.ndarray,
    normal: np.ndarray,
    precisions: np.ndarray,
    radius: int = FILTER_RADIUS,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Weighted sums of eqs. 8-9 over the (2 radius + 1)^2 window, neighbours outside the frame left out.

    pilot_a, pilot_b: (H, W, 3) float32, pilot estimates in log1p radiance.
    albedo: (H, W, 3) float32 in [0, 1]; normal: (H, W, 3) float32 unit world-space normal.
    precisions: (H, W, 5) float32 > 0: kA, kB, kAlbedo, kNormal, kPosition (layout.CROSSREG_OUTPUTS[:5]).
    Returns (sum_a (H, W, 3), weight_a (H, W), sum_b (H, W, 3), weight_b (H, W)), float32; weights >= 1.
    """
    height, width = pilot_a.shape[:2]
    planes = np.concatenate([pilot_a, pilot_b, albedo, normal, precisions], axis=-1, dtype=np.float32)
    planes = np.ascontiguousarray(planes.transpose(0, 2, 1))
    out = np.empty((height, 8, width), np.float32)
    _sums_kernel(planes, int(radius), out)
    out = out.transpose(0, 2, 1)
    return out[..., 0:3], out[..., 3], out[..., 4:7], out[..., 7]


def spatiotemporal_filter(
    pilot_a: np.ndarray,
    pilot_b: np.ndarray,
    albedo: np.ndarray,
    normal: np.ndarray,
    params: np.ndarray,
    previous: np.ndarray | None = None,
    valid: np.ndarray | None = None,
    radius: int = FILTER_RADIUS,
) -> FilterOutput:
    """Eqs. 8-10: cross-bilateral spatial means of both pilots, temporal blend, A/B combination.

    pilot_a, pilot_b: (H, W, 3) float32, log1p radiance. albedo, normal: (H, W, 3) float32.
    params: (H, W, 6) float32, the network output in layout.CROSSREG_OUTPUTS order (5 precisions > 0,
        then alpha in (0, 1), the weight of the current frame).
    previous: (H, W, 3) float32, the previous output reprojected to this frame, log1p radiance; None on
        the first frame. valid: (H, W) bool, where `previous` is usable; None means nowhere.
    Returns FilterOutput (log1p space).
    """
    sum_a, w_a, sum_b, w_b = cross_bilateral_sums(pilot_a, pilot_b, albedo, normal, params[..., :N_PRECISIONS], radius)
    spatial_a = sum_a / w_a[..., None]
    spatial_b = sum_b / w_b[..., None]
    if previous is None or valid is None:
        color_a, color_b = spatial_a, spatial_b
    else:
        alpha = np.where(valid, params[..., N_PRECISIONS], np.float32(1.0))[..., None].astype(np.float32)
        history = (np.float32(1.0) - alpha) * previous
        color_a = alpha * spatial_a + history
        color_b = alpha * spatial_b + history
    total = (w_a + w_b)[..., None]
    color = (color_a * w_a[..., None] + color_b * w_b[..., None]) / total
    return FilterOutput(color.astype(np.float32), color_a, color_b, w_a, w_b)


SCREEN_RADIUS = 3  # 7x7 window of the history screening (authors' code: temporal_screening win_curr = 7)


def _window_extrema(image: np.ndarray, radius: int) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel min and max over the (2 radius + 1)^2 window, per channel, the window cut at the frame edge.

    image: (H, W, C) float32. Returns (min, max), both (H, W, C) float32.
    """
    lo = np.empty_like(image)
    hi = np.empty_like(image)
    _extrema_kernel(np.ascontiguousarray(image, dtype=np.float32), int(radius), lo, hi)
    return lo, hi


@numba.njit(parallel=True, cache=True)
def _extrema_kernel(image, radius, lo, hi):  # pragma: no cover - jitted
    """Separable: min/max along rows into lo/hi, then along columns in place (per row band)."""
    height, width, channels = image.shape
    row_lo = np.empty_like(image)
    row_hi = np.empty_like(image)
    for y in numba.prange(height):
        for x in range(width):
            x0, x1 = max(0, x - radius), min(width, x + radius + 1)
            for c in range(channels):
                a = image[y, x0, c]
                b = a
                for xx in range(x0 + 1, x1):
                    v = image[y, xx, c]
                    a = min(a, v)
                    b = max(b, v)
                row_lo[y, x, c] = a
                row_hi[y, x, c] = b
    for y in numba.prange(height):
        y0, y1 = max(0, y - radius), min(height, y + radius + 1)
        for x in range(width):
            for c in range(channels):
                a = row_lo[y0, x, c]
                b = row_hi[y0, x, c]
                for yy in range(y0 + 1, y1):
                    a = min(a, row_lo[yy, x, c])
                    b = max(b, row_hi[yy, x, c])
                lo[y, x, c] = a
                hi[y, x, c] = b


def screen_history(
    current: np.ndarray, history: np.ndarray, valid: np.ndarray, radius: int = SCREEN_RADIUS, groups: int = 1
) -> np.ndarray:
    """Where reprojected `history` is still plausible: `valid` and, in every channel of a group, within the
    min-max range of `current` over the (2 radius + 1)^2 window around the pixel.

    From the authors' code (temporal_screening), not the paper's text: it rejects history that motion
    vectors carry correctly but whose shading changed (a moving shadow on a static floor). We compare
    with <= where the authors compare strictly, so flat regions (all-black background) keep their history.
    current, history: (H, W, C) float32 in the same (log1p) space, C = groups x channels per group (several
    quantities screened in one pass); valid: (H, W) bool. Returns (H, W) bool for groups = 1, else
    (H, W, groups) bool, one mask per group of consecutive channels.
    """
    height, width, channels = current.shape
    if channels % groups:
        raise ValueError(f"{channels} channels do not split into {groups} groups")
    lo, hi = _window_extrema(current, radius)
    inside = ((history >= lo) & (history <= hi)).reshape(height, width, groups, channels // groups)
    masks = valid[..., None] & np.all(inside, axis=-1)
    return masks[..., 0] if groups == 1 else masks
