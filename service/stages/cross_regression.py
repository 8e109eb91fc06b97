"""Cross-regression (Choi et al. 2024, sec. 4.1, eqs. 3-7): two pilot estimates from two half buffers.

Colours first go to log space, y = log1p(radiance) (Choi sec. 4.4 "log transform [Bako 2017]"; the authors'
code applies log1p to both buffers). Negative radiance, which log1p cannot take below -1, goes through the
odd extension sign(x) log1p(|x|): identical to log1p for x >= 0, finite and invertible everywhere.

Buffer A's explanatory variables (eq. 6) for centre c and pixel i, per colour channel as in the authors'
code: [(y_i^A - y_c^A) / (sigma_i^A + sigma_c^A + eps), albedo_i - albedo_c, n_i - n_c], with
(sigma^A)^2 = |y^A - mean of the 8 neighbours|^2 (summed over RGB, 3x3 window without the pixel), and
weights w^A_ci = exp(-|y_i^A - y_c^A|^2 / ((sigma_c^A)^2 + (sigma_i^A)^2 + eps)) (eq. 7).

Which pilot is which (Choi sec. 4.1, "one regression using x^A and w^A for y^B and another regression
using x^B and w^B for y^A"):
    pilot_a = f~(x^A): buffer A's variables and weights, fitted to buffer B's colours y^B.
    pilot_b = f~(x^B): buffer B's variables and weights, fitted to buffer A's colours y^A.
pilot_a is a linear function of y^A, so its noise correlates with y^A (not y^B), and vice versa; the
online loss (eq. 12) compares the network's output from pilot_a with pilot_b.

As our addition (not in the paper, on by default, `firefly_k=None` turns it off) each buffer's isolated
outliers are clamped to their 3x3 neighbourhood before the log (see `outliers.clamp_fireflies`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from service.kernels.fill import filled
from service.kernels.parallel import rows_per_thread
from service.kernels.simd import bits_to_float32, float32_to_bits
from service.regression.block import block_regression, normalise_row, pad_lanes
from service.regression.planes import from_planes, interleave_row, neighbour_mean, to_planes
from service.regression.solve import RIDGE_ABSOLUTE, RIDGE_RELATIVE
from service.regression.terms import BlockParams, PairTerms
from service.stages.cross_block import empty_planes, pack_row, regress_packed, regress_sums
from service.stages.emission import nonfinite
from service.stages.outliers import FIREFLY_K, check_firefly_k, clamp_fireflies_reference
from service.stages.range_clamp import emit_range_row, range_scratch, window_range

LOG_MAX = 88.0  # |log value| limit of `log_to_linear`: expm1(88) = 1.65e38, two of them still below float32 max


@dataclass(frozen=True)
class CrossRegressionParams:
    """Options of the cross-regression."""

    window: int = 17  # side of the square regression window, pixels (Choi 2024 sec. 3: 17 x 17), odd
    sparsity: int = 4  # centre pixels on every 4th row and column, 1/16 of the pixels (Choi 2024 sec. 3)
    firefly_k: float | None = FIREFLY_K  # clamp outliers to k neighbour ranges beyond their neighbours; None: off
    ridge_relative: float = RIDGE_RELATIVE  # Tikhonov, relative to each feature's scale (service.regression.solve)
    ridge_absolute: float = RIDGE_ABSOLUTE  # Tikhonov floor x sum of weights (service.regression.solve)

    def __post_init__(self) -> None:
        if self.window < 1 or self.window % 2 == 0:
            raise ValueError(f"window must be a positive odd number of pixels, got {self.window}")
        check_firefly_k(self.firefly_k)
        self.block()  # validates sparsity against the window

    def block(self) -> BlockParams:
        return BlockParams(self.window // 2, self.sparsity, self.ridge_relative, self.ridge_absolute)


def linear_to_log(color: np.ndarray) -> np.ndarray:
    """Radiance to the regression's log space: log1p(x) for x >= 0, -log1p(-x) below.

    color: any shape, linear radiance (any sign). Returns float32 of the same shape.
    """
    color = np.asarray(color, np.float32)
    return (np.sign(color) * np.log1p(np.abs(color))).astype(np.float32, copy=False)


def log_to_linear(log_color: np.ndarray) -> np.ndarray:
    """Inverse of `linear_to_log`: expm1(y) for y >= 0, -expm1(-y) below. Any shape, float32.

    Log values above 88 (radiance beyond float32) are clipped so the result stays finite.
    """
    y = np.clip(np.asarray(log_color, np.float32), -LOG_MAX, LOG_MAX)
    return (np.sign(y) * np.expm1(np.abs(y))).astype(np.float32, copy=False)


def log_planes_reference(color: np.ndarray, firefly_k: float | None = FIREFLY_K) -> np.ndarray:
    """One buffer into the regression's log space, as channel planes, in plain numpy (the numba pass,
    `_log_row`, runs inside `pack_buffers`): `outliers.clamp_fireflies_reference` with k = firefly_k
    (None: no clamp), then `linear_to_log`.

    color: (H, W, 3) float32 linear HDR radiance (any sign, finite). Returns (3, H, W) float32 log colour."""
    planes = to_planes(color)
    if firefly_k is not None:
        planes = clamp_fireflies_reference(planes, firefly_k)
    return linear_to_log(planes)


def pilots_to_radiance(pilot_a: np.ndarray, pilot_b: np.ndarray) -> np.ndarray:
    """The mean of the two pilots back in linear radiance, as pixels: from_planes(0.5 (log_to_linear(pilot_a)
    + log_to_linear(pilot_b))), in one numba pass.

    pilot_a, pilot_b: (3, H, W) float32 log colour (`cross_regression`). Returns (H, W, 3) float32
    linear HDR radiance (any sign, finite: log values are clipped to +-LOG_MAX as in `log_to_linear`).
    The exponential is a Cody-Waite reduction and a degree-7 polynomial (within 2 ulp of expm1).
    `pilots_to_radiance_reference` is the plain-numpy twin.
    """
    pilot_a = np.ascontiguousarray(pilot_a, dtype=np.float32)
    pilot_b = np.ascontiguousarray(pilot_b, dtype=np.float32)
    out = np.empty((*pilot_a.shape[1:], pilot_a.shape[0]), np.float32)
    _pilots_kernel(pilot_a, pilot_b, out)
    return out


def pilots_to_radiance_reference(pilot_a: np.ndarray, pilot_b: np.ndarray) -> np.ndarray:
    """Plain-numpy twin of `pilots_to_radiance`."""
    return from_planes(np.float32(0.5) * (log_to_linear(pilot_a) + log_to_linear(pilot_b)))


@numba.njit(inline="always")
def _log_row(flat, y, k, clamp, d0, d1, d2):  # pragma: no cover - jitted
    """Row y of one buffer in log space (`log_planes_reference`) into d0, d1, d2 (W,) float32, its three
    colour planes' rows, from flat (H, 3 W) float32, the frame's interleaved radiance. The clamp of
    `outliers._clamp_kernel` (the same float32 operations; min and max are exact, so the order in
    which the neighbours are taken does not matter) runs on the interleaved rows, where the neighbour in x
    of a value lies a constant 3 values away, so every loop is contiguous and vectorises; one pass per
    neighbour row over the pixels that have both x neighbours, then the first and last pixel. Without
    `clamp` no neighbour is read, and lo > hi leaves every value as it is (as for a 1x1 frame). Then the
    signed log1p, and the row is split into the planes. No fast-math (its caller has none either: inlined,
    it would take the caller's). (Allocating lo and hi under an `if clamp` halved the clamp's speed; taking
    them, or the line, as scratch from the caller: their loops no longer vectorised.)"""
    n = flat.shape[1]
    width = n // 3
    height = flat.shape[0]
    src = flat[y]
    lo = filled(n, np.inf, np.float32)
    hi = filled(n, -np.inf, np.float32)
    for yy in range(max(0, y - 1), min(height, y + 2) if clamp else 0):
        row = flat[yy]
        if yy != y:  # the row above or below: the neighbours left, right and in line
            for i in range(3, n - 3):
                a, b, c = row[i - 3], row[i], row[i + 3]
                lo[i] = min(min(lo[i], c), min(a, b))
                hi[i] = max(max(hi[i], c), max(a, b))
        else:  # the own row: left and right
            for i in range(3, n - 3):
                a, c = row[i - 3], row[i + 3]
                lo[i] = min(lo[i], min(a, c))
                hi[i] = max(hi[i], max(a, c))
        for e in range(6):  # the first and the last pixel (some values twice if W < 3: min and max do not mind)
            i = e if e < 3 else n - 6 + e
            if i >= 3:
                lo[i] = min(lo[i], row[i - 3])
                hi[i] = max(hi[i], row[i - 3])
            if i + 3 < n:
                lo[i] = min(lo[i], row[i + 3])
                hi[i] = max(hi[i], row[i + 3])
            if yy != y:
                lo[i] = min(lo[i], row[i])
                hi[i] = max(hi[i], row[i])
    line = np.empty(n, np.float32)
    for i in range(n):
        spread = k * (hi[i] - lo[i])
        clamped = min(max(src[i], lo[i] - spread), hi[i] + spread)
        line[i] = clamped if lo[i] <= hi[i] else src[i]
    _signed_log1p_row(line)
    for x in range(width):  # a constant stride: the strided loads vectorise together
        d0[x] = line[3 * x]
        d1[x] = line[3 * x + 1]
        d2[x] = line[3 * x + 2]


@numba.njit(fastmath={"contract"}, error_model="numpy")
def _signed_log1p_row(line):  # pragma: no cover - jitted
    """line[i] = sign(v) log1p(|v|), v = line[i], in place; line (N,) float32, finite. Fast-math for the
    fused multiply-adds alone (the accuracy of `_log1p_nonneg` unchanged); a call, not inlined, so that the
    flag stays its own."""
    for i in range(line.shape[0]):
        v = line[i]
        log_abs = _log1p_nonneg(abs(v))
        line[i] = -log_abs if v < 0 else log_abs


@numba.njit(parallel=True, cache=True, error_model="numpy")
def _pilots_kernel(pilot_a, pilot_b, out):  # pragma: no cover - jitted
    """pilot_a, pilot_b (C, H, W) -> out (H, W, C): `_linear_mean` of each row, a task per row, the row
    interleaved by `interleave_row` (its albedo is unused)."""
    channels, height, width = pilot_a.shape
    for y in numba.prange(height):
        line = np.empty((channels, width), np.float32)
        for m in range(channels):
            _linear_mean(pilot_a[m, y], pilot_b[m, y], line[m])
        interleave_row(line, out[y], False, out[y])


@numba.njit(fastmath={"contract"}, error_model="numpy")
def _linear_mean(a, b, dst):  # pragma: no cover - jitted
    """dst = 0.5 (e(a) + e(b)) for rows a, b, dst (W,) float32: e the signed expm1 (`_expm1_nonneg`) of log
    values clipped to +-LOG_MAX. Fast-math for the fused multiply-adds alone, as in `_signed_log1p_row`.
    (dst may be a or b, but then the loop runs scalar: its run-time check for overlap fails.)"""
    limit, half = np.float32(LOG_MAX), np.float32(0.5)
    for x in range(dst.shape[0]):
        ea = _expm1_nonneg(min(abs(a[x]), limit))
        eb = _expm1_nonneg(min(abs(b[x]), limit))
        dst[x] = half * ((-ea if a[x] < 0 else ea) + (-eb if b[x] < 0 else eb))


# musl src/math/log1pf.c (from FreeBSD s_log1pf.c): ln 2 split in two, and the minimax polynomial
# |(log(1+s) - log(1-s))/s - Lg(s)| < 2^-34.24 on the reduced range.
_LN2_HI, _LN2_LO = float.fromhex("0x1.62e3p-1"), float.fromhex("0x1.2fefa2p-17")
_LG1, _LG2 = float.fromhex("0xaaaaaa.0p-24"), float.fromhex("0xccce13.0p-25")
_LG3, _LG4 = float.fromhex("0x91e9ee.0p-25"), float.fromhex("0xf89e26.0p-26")
_SQRT2_M1 = float.fromhex("0x1.a827a0p-2")  # sqrt(2) - 1 rounded up (musl's 0x3ed413d0)


@numba.njit(inline="always")
def _log1p_nonneg(x):
    """log1p(x) for finite float32 x >= 0, within 1 ulp: musl's log1pf with its branches as selects
    (vectorisable, unlike a call to log1pf). 1 + x = 2^k u, u in [sqrt(2)/2, sqrt(2)); below sqrt(2) - 1,
    k = 0 and f = x exactly; c corrects for the rounding of 1 + x."""
    one = np.float32(1.0)
    u = one + x
    bits = float32_to_bits(u) + (0x3F800000 - 0x3F3504F3)
    k = (bits >> 23) - 0x7F
    c = (one - (u - x) if k >= 2 else x - (u - one)) / u
    reduced = bits_to_float32((bits & 0x007FFFFF) + 0x3F3504F3) - one
    small = x < np.float32(_SQRT2_M1)
    f = x if small else reduced
    c = np.float32(0.0) if small else c
    dk = np.float32(0.0) if small else np.float32(k)
    s = f / (np.float32(2.0) + f)
    z = s * s
    w = z * z
    r = z * (np.float32(_LG1) + w * np.float32(_LG3)) + w * (np.float32(_LG2) + w * np.float32(_LG4))
    hfsq = np.float32(0.5) * f * f
    return s * (hfsq + r) + (dk * np.float32(_LN2_LO) + c) - hfsq + f + dk * np.float32(_LN2_HI)


# Cody-Waite split of ln 2 for the exponential (musl src/math/expf.c, ln2hi/ln2lo): n ln2_hi is exact
# for n < 2^9.
_EXP_LN2_HI, _EXP_LN2_LO = float.fromhex("0x1.62e4p-1"), float.fromhex("0x1.7f7d1cp-20")


@numba.njit(inline="always")
def _expm1_nonneg(t):
    """expm1(t) for float32 t in [0, LOG_MAX], within 2 ulp, vectorisable: t = n ln2 + r, |r| <= ln2 / 2,
    expm1(r) by its Taylor series to r^7 (truncation < 2e-8 relative), then 2^n expm1(r) + (2^n - 1), which
    keeps full relative precision near 0 (n = 0)."""
    n = np.floor(t * np.float32(1.4426950408889634) + np.float32(0.5))  # log2(e)
    r = (t - n * np.float32(_EXP_LN2_HI)) - n * np.float32(_EXP_LN2_LO)
    p = np.float32(1.0 / 5040.0)
    p = p * r + np.float32(1.0 / 720.0)
    p = p * r + np.float32(1.0 / 120.0)
    p = p * r + np.float32(1.0 / 24.0)
    p = p * r + np.float32(1.0 / 6.0)
    p = p * r + np.float32(0.5)
    p = p * r * r + r
    scale = bits_to_float32((np.int32(n) + np.int32(127)) << np.int32(23))
    return scale * p + (scale - np.float32(1.0))


def pixel_variance_reference(log_planes: np.ndarray) -> np.ndarray:
    """Choi sec. 4.1 variance estimate: |y - mean of the 8 neighbours|^2, summed over channels, in plain
    numpy (the numba pass, `_variance_row`, runs inside `pack_buffers`).

    log_planes: (C, H, W) float32 log colour. Neighbours outside the frame are left out of the mean.
    Returns (H, W) float32, >= 0 (0 for a 1x1 frame)."""
    diff = log_planes - neighbour_mean(log_planes)
    return np.einsum("chw,chw->hw", diff, diff).astype(np.float32)


@numba.njit(fastmath=True, error_model="numpy")
def _row_sums(planes, r, sums):  # pragma: no cover - jitted
    """The 3-pixel sums along frame row r of every channel (2 values at the first and last pixel, 1 in a
    1-pixel row): sums[c, r % P] (W,) from planes[c, r % P], planes (C, P, W) float32 a ring of log rows,
    sums (C, P + 1, W) float32 (its last row, zeros, stands for rows outside the frame). Each row's sums are
    taken once and serve the variance of the row and of both neighbours (`_variance_row`). Fast-math, so a
    call (as `_variance_row`)."""
    channels, period, width = planes.shape
    for c in range(channels):
        row, dst = planes[c, r % period], sums[c, r % period]
        for x in range(1, width - 1):
            dst[x] = row[x - 1] + row[x] + row[x + 1]
        dst[0] = row[0] + (row[1] if width > 1 else np.float32(0.0))
        if width > 1:
            dst[width - 1] = row[width - 2] + row[width - 1]


@numba.njit(fastmath=True, error_model="numpy")
def _variance_row(planes, sums, y, height, total):  # pragma: no cover - jitted
    """Row y of `pixel_variance_reference` of an H-row frame into total (W,) float32: the 3-pixel row sums
    (`_row_sums`, sums (C, P + 1, W)) of the valid rows y - 1 ... y + 1, minus the pixel, per channel. Frame
    row yy lies at planes[:, yy % P], planes (C, P, W) float32 a ring of the log rows around y. Fast-math,
    so a call: inlined, numba would compile it with its caller's flags."""
    channels, period, width = planes.shape
    rows = min(height, y + 2) - max(0, y - 1)
    above = (y - 1) % period if y > 0 else period  # the zeros: no row there
    below = (y + 1) % period if y + 1 < height else period
    inner = np.float32(1.0) / np.float32(3 * rows - 1)
    count = (2 if width > 1 else 1) * rows - 1  # at the first and last column
    total[:] = 0.0
    for c in range(channels):
        own, up, mid, down = planes[c, y % period], sums[c, above], sums[c, y % period], sums[c, below]
        for x in range(1, width - 1):
            d = own[x] - (up[x] + mid[x] + down[x] - own[x]) * inner
            total[x] += d * d
        for x in range(0, width, max(width - 1, 1)):
            d = own[x] - (up[x] + mid[x] + down[x] - own[x]) / count if count > 0 else np.float32(0.0)
            total[x] += d * d


def buffer_terms(log_planes: np.ndarray, variance: np.ndarray, albedo: np.ndarray, normal: np.ndarray) -> PairTerms:
    """One buffer's explanatory variables (eq. 6) and weights (eq. 7) for `block_regression`.

    log_planes: (3, H, W) float32 log colour of the buffer; variance: (H, W) from `pixel_variance_reference`;
    albedo, normal: (3, H, W) float32 planes. Per colour channel (group) the features are
    [1, n_x, n_y, n_z, scaled colour difference, albedo difference].
    """
    grouped = np.ascontiguousarray(np.stack([log_planes, albedo], axis=1))  # (3, 2, H, W)
    return PairTerms(
        shared=normal,
        grouped=grouped,
        scaled=np.array([True, False]),
        sigma=np.sqrt(variance).astype(np.float32),
        weight_guide=log_planes,
        weight_variance=variance,
    )


def pack_buffers(
    color_a: np.ndarray,
    color_b: np.ndarray,
    albedo: np.ndarray,
    normal: np.ndarray,
    firefly_k: float | None,
    params: BlockParams,
) -> np.ndarray:
    """Both buffers' phase planes for `cross_block.regress_packed`, straight from the radiance, in one numba
    pass: each buffer in log space (3x3 firefly clamp with k = firefly_k,
    None: off; signed log1p, musl's log1pf, within 1 ulp of log1p), its 3x3 variance, and the G-buffers,
    packed.

    color_a, color_b: (H, W, 3) float32 linear HDR radiance (any sign, finite); albedo, normal: (H, W, 3)
    float32 frame layers; params: the block regression's geometry. Returns (S, PLANES, H, L) float32 (the
    layout of `cross_block.pack_cross_reference`). The numpy twin is the chain `log_planes_reference`,
    `pixel_variance_reference`, `pack_cross_reference`.
    """
    named = {"color_a": color_a, "color_b": color_b, "albedo": albedo, "normal": normal}
    shapes = {name: x.shape for name, x in named.items()}
    if len(set(shapes.values())) != 1 or len(shapes["color_a"]) != 3 or shapes["color_a"][2] != 3:
        raise ValueError(f"pack_buffers: expected (H, W, 3) layers of one shape, got {shapes}")
    height, width = shapes["color_a"][:2]
    out = empty_planes(height, width, params)
    f32 = [np.ascontiguousarray(x, dtype=np.float32) for x in (color_a, color_b, albedo, normal)]
    rows = rows_per_thread(height)  # the fewest logs taken twice
    k = np.float32(1.0 if firefly_k is None else firefly_k)  # unused when the clamp is off
    _pack_buffers_kernel(*f32, k, firefly_k is not None, rows, pad_lanes(params), out)
    return out


@numba.njit(parallel=True, cache=True, error_model="numpy")
def _pack_buffers_kernel(
    color_a, color_b, albedo, normal, k, clamp, rows, pad, out
):  # pragma: no cover - jitted
    """color_a, color_b, albedo, normal (H, W, 3) -> out, a task per `rows` consecutive frame rows
    (`_pack_rows`)."""
    height, width = albedo.shape[:2]
    n = 3 * width
    flat_a, flat_b = color_a.reshape(height, n), color_b.reshape(height, n)
    albedo, normal = albedo.reshape(height, n), normal.reshape(height, n)
    for task in numba.prange(-(-height // rows)):
        _pack_rows(flat_a, flat_b, albedo, normal, k, clamp, task * rows,
                   min(height, task * rows + rows), pad, out)  # fmt: skip


@numba.njit(error_model="numpy")
def _pack_rows(flat_a, flat_b, albedo, normal, k, clamp, first, last, pad, out):  # pragma: no cover
    """Frame rows first ... last - 1 of `_pack_buffers_kernel` (the layers as (H, 3 W) rows). Each buffer's
    log rows y - 1, y, y + 1 (`_log_row`) are kept in a ring of three, frame row yy in slot yy % 3, the
    variance of row y formed from it (`_variance_row`) and the row packed (`cross_block.pack_row`); the logs
    of the row before `first` and after `last` are taken by the neighbouring task as well. A function of its own,
    not the parallel loop's body: numba's parallel passes cost time superlinear in the size of that body."""
    height, n = flat_a.shape
    width = n // 3
    ring_a, ring_b = np.empty((3, 3, width), np.float32), np.empty((3, 3, width), np.float32)
    var_a, var_b = np.empty(width, np.float32), np.empty(width, np.float32)
    sums_a, sums_b = np.zeros((3, 4, width), np.float32), np.zeros((3, 4, width), np.float32)  # `_row_sums`
    for after in range(max(first - 1, 0), last + 1):  # row after = y + 1 is taken, then row y is packed
        r = min(after, height - 1)  # the last row twice, not under an `if` (which stopped the vectorising)
        _log_row(flat_a, r, k, clamp, ring_a[0, r % 3], ring_a[1, r % 3], ring_a[2, r % 3])
        _log_row(flat_b, r, k, clamp, ring_b[0, r % 3], ring_b[1, r % 3], ring_b[2, r % 3])
        _row_sums(ring_a, r, sums_a)
        _row_sums(ring_b, r, sums_b)
        y = after - 1
        if y >= first:
            _variance_row(ring_a, sums_a, y, height, var_a)
            _variance_row(ring_b, sums_b, y, height, var_b)
            pack_row(ring_a, ring_b, y % 3, var_a, var_b, albedo[y], normal[y], pad, out, y)


def cross_regression_radiance(
    color_a: np.ndarray,
    color_b: np.ndarray,
    albedo: np.ndarray,
    normal: np.ndarray,
    noisy: np.ndarray,
    params: CrossRegressionParams | None = None,
) -> np.ndarray:
    """The pipeline `crossregression`'s image: the two pilots of `cross_regression` (same arguments), their
    mean in linear radiance (`pilots_to_radiance`), clipped per pixel and channel to the range of `noisy`
    over the regression window (`range_clamp.clamp_to_local_range`, radius window // 2: no energy that
    the input cannot explain). The last three steps run as one numba pass over the regression's sums.

    noisy: (H, W, 3) float32 the frame's radiance (the two halves' mean). Returns (H, W, 3) float32 linear
    HDR radiance, the same values as that chain of the separate functions, finite: FloatingPointError
    otherwise."""
    params = params or CrossRegressionParams()
    noisy = np.ascontiguousarray(noisy, dtype=np.float32)
    if noisy.shape != np.shape(color_a):
        raise ValueError(f"cross_regression_radiance: noisy {noisy.shape} != the halves {np.shape(color_a)}")
    block = params.block()
    planes = pack_buffers(color_a, color_b, albedo, normal, params.firefly_k, block)
    num, den = regress_sums(planes, noisy.shape[1], block)
    out = np.empty(noisy.shape, np.float32)
    bad = _finish_kernel(num, den, pad_lanes(block), noisy, params.window // 2, rows_per_thread(noisy.shape[0]), out)
    if bad:
        raise FloatingPointError(f"cross_regression_radiance: {bad} non-finite values in the result")
    return out


@numba.njit(parallel=True, cache=True, error_model="numpy")
def _finish_kernel(num, den, pad, noisy, radius, rows_per_task, out):  # pragma: no cover - jitted
    """The sums num (2, S, 3, H, L'), den (2, S, H, L') of `cross_block.regress_sums` -> out (H, W, 3), a band
    of rows_per_task rows per task (`_finish_rows`). Returns the count of non-finite values written."""
    height = noisy.shape[0]
    bad = 0
    for task in numba.prange(-(-height // rows_per_task)):
        bad += _finish_rows(num, den, pad, noisy, radius, task * rows_per_task,
                            min(height, task * rows_per_task + rows_per_task), out)  # fmt: skip
    return bad


@numba.njit(error_model="numpy")
def _finish_rows(num, den, pad, noisy, radius, y0, y1, out):  # pragma: no cover - jitted
    """Rows y0 ... y1 - 1 of `_finish_kernel`: per row, both pilots (`normalise_row`), their `_linear_mean`,
    interleaved, clipped to the window range of noisy (H, W, 3) (`window_range`). Returns the count of
    non-finite values written (`emission.nonfinite`). A function of its own, not the parallel loop's body
    (see `_pack_rows`)."""
    height, width, channels = noisy.shape
    n = width * channels
    flat = noisy.reshape(height, n)
    bad = 0
    scans, rows = range_scratch(radius, width, channels)
    inv = np.empty((num.shape[1], num.shape[4]), np.float32)
    pilots = np.empty((2, channels, 1, width), np.float32)
    line = np.empty((channels, width), np.float32)
    mean = np.empty(n, np.float32)
    for y in range(y0, y1):
        normalise_row(num[0], den[0], pad, y, inv, pilots[0], 0)
        normalise_row(num[1], den[1], pad, y, inv, pilots[1], 0)
        for m in range(channels):
            _linear_mean(pilots[0, m, 0], pilots[1, m, 0], line[m])
        interleave_row(line, mean, False, mean)
        if window_range(flat, channels, y, y0, radius, scans, rows):
            emit_range_row(rows[2], rows[3], mean, True, out[y], out[y])
        else:
            emit_range_row(rows[0], rows[1], mean, True, out[y], out[y])
        dst = out[y].reshape(n)
        for j in range(n):
            bad += nonfinite(dst[j])
    return bad


def cross_regression(
    color_a: np.ndarray,
    color_b: np.ndarray,
    albedo: np.ndarray,
    normal: np.ndarray,
    params: CrossRegressionParams | None = None,
    *,
    reference: bool = False,
) -> tuple[np.ndarray, np.ndarray]:
    """The two pilot estimates of Choi 2024 sec. 4.1, as channel planes.

    color_a, color_b: (H, W, 3) float32 linear HDR radiance of the two half-sample buffers (any sign).
    albedo: (H, W, 3) float32 in [0, 1]; normal: (H, W, 3) float32 unit (or zero) world-space normal.
    Returns (pilot_a, pilot_b), each (3, H, W) float32 in log space (see `linear_to_log`; back to
    radiance with `log_to_linear`): pilot_a = f~(x^A), buffer A's variables and weights fitted to y^B;
    pilot_b = f~(x^B), buffer B's variables and weights fitted to y^A.
    reference: run the plain-numpy kernels instead of numba (slow; for tests).
    """
    params = params or CrossRegressionParams()
    block = params.block()
    if not reference:
        planes = pack_buffers(color_a, color_b, albedo, normal, params.firefly_k, block)
        return regress_packed(planes, color_a.shape[1], block)
    log_a, log_b = (log_planes_reference(color, params.firefly_k) for color in (color_a, color_b))
    variance_a, variance_b = pixel_variance_reference(log_a), pixel_variance_reference(log_b)
    albedo_planes, normal_planes = to_planes(albedo), to_planes(normal)
    terms_a = buffer_terms(log_a, variance_a, albedo_planes, normal_planes)
    terms_b = buffer_terms(log_b, variance_b, albedo_planes, normal_planes)
    pilot_a = block_regression(terms_a, log_b, block, reference=True)
    return pilot_a, block_regression(terms_b, log_a, block, reference=True)
