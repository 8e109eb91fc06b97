"""Statistical denoising filter of Sakai et al. 2024 (Algorithm 2): the joint bilateral base filter
rho_ij (eq. 16, `service.stages.bilateral`) gated by a pair-wise Welch t-test membership m_ij.

Per pixel the renderer hands the statistics of its Box-Cox transformed samples (frame layers
`sampleCount`, `bcMean`, `bcM2`, `bcM3`; `service.stages.sample_statistics` computes them from
samples, Algorithm 1). From them, per channel:

    Var(theta_i) = sigma_i^2 / n_i = M2_i / (n_i - 1)              (Algorithm 2, Bessel-corrected)
    theta_i      = mu_i + M3_i / (6 sigma_i^2 n_i)                 (Curto 2023 eq. 20 mean correction)

and for a pair (i, j) with d = theta_i - theta_j the membership passes when

    symmetric (eq. 12):   t = |d| / sqrt(Var_i + Var_j) <= t_{1-alpha/2, nu}
    asymmetric (eq. 14):  ((2 (1 - w*_asym))^-1 - 1)^(1/2) <= t_{1-alpha/2, nu},
                          i.e. d^2 + Var_j <= (1 + 2 t_crit^2) Var_i   (i: the pixel being denoised)

with nu = n_i + n_j - 2 (sec. 4.2), in all three channels (sec. 5). Both tests are written without
division, so zero variance is well defined: a pixel whose statistics are exact (M2 = 0) admits only
neighbours with the same estimate, which makes the filter consistent (eq. 9): as the variance goes
to zero the output converges to its input. We use `<=` where the paper writes `<`; they differ only
where t equals the critical value exactly, and `<=` admits identical estimates of zero variance.
A pixel with fewer than two samples has no variance estimate: its variance is +inf, so the symmetric
test cannot reject it (the filter is the base filter there).

The weights w_ij = rho_ij m_ij / sum_j rho_ij m_ij (eq. 10) filter `color`: the membership decides in
the Box-Cox domain, the average is of the radiance itself, so energy is preserved with symmetric
weights. `statistical_filter` runs a compiled kernel; `statistical_filter_numpy` is the reference,
built on `base_weights`, and a parity test holds the two together.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numba import njit, prange

from service.stages.bilateral import BilateralParams, base_weights, neg_exp
from service.stages.student_t import critical_value_table

ALPHA = 0.005  # Sakai 2024 sec. 4.2: significance level of the Welch test
# Sakai 2024 sec. 5 base filter: Sigma = diag(10, 10, 0.02 x3, 0.1 x3) over position, albedo, normal;
# radius 20 pixels at 720p (sec. 6; 6 is their fast setting, Fig. 6d). No depth term: not in the paper.
PAPER_BASE = BilateralParams(
    radius=20, sigma2_position=10.0, sigma2_albedo=0.02, sigma2_normal=0.1, sigma2_log_depth=None
)
UNTESTABLE_CRIT2 = np.float32(1e30)  # stands for t_crit^2 = inf (nu <= 0) without producing inf * 0
MAX_COUNT = 1 << 24  # sample counts are clamped here (float32 holds integers exactly up to 2^24)


@dataclass(frozen=True)
class StatisticalParams:
    base: BilateralParams = field(default_factory=lambda: PAPER_BASE)  # rho_ij: eq. 16 weights and window radius
    alpha: float = ALPHA  # significance level; the critical value is t_{1 - alpha/2, n_i + n_j - 2}
    symmetric: bool = True  # eq. 12 (energy preserving) if True, else eq. 14 (asymmetric)
    skew_correction: bool = True  # Curto 2023 eq. 20 correction of the means by the third moment

    def __post_init__(self) -> None:
        if not 0.0 < self.alpha < 1.0:
            raise ValueError(f"alpha must be in (0, 1), got {self.alpha}")


@dataclass(frozen=True)
class PixelEstimates:
    """Per-pixel inputs of the membership test, in the Box-Cox domain of the samples.

    theta: (H, W, C) float32 estimate of the pixel's mean (skew-corrected when asked).
    var: (H, W, C) float32 variance of that estimate, sigma^2 / n >= 0; +inf where n < 2.
    count: (H, W) int32 sample count n >= 0.
    """

    theta: np.ndarray
    var: np.ndarray
    count: np.ndarray


def pixel_estimates(
    count: np.ndarray, mean: np.ndarray, m2: np.ndarray, m3: np.ndarray, *, skew_correction: bool = True
) -> PixelEstimates:
    """Estimate and estimator variance per pixel from the frame-format statistics (Algorithm 2, lines 3-4).

    count: (H, W, 1) or (H, W) float32 `sampleCount` n (rounded; negative counts count as 0).
    mean, m2, m3: (H, W, C) float32 `bcMean`, `bcM2` (= sum d^2 / n) and `bcM3` (= sum d^3 / n) of the
    Box-Cox transformed samples. Inconsistent statistics (a negative M2, or M3 beyond what n samples
    with that M2 can produce, as float16 rounding makes) are clamped to the nearest consistent value:
    |M3| <= (n - 2) / sqrt(n - 1) * M2^(3/2), the bound on the sample skewness.
    """
    shape = mean.shape
    n = np.rint(np.clip(np.asarray(count, np.float32).reshape(*shape[:2], 1), 0, MAX_COUNT))
    m2 = np.maximum(np.asarray(m2, np.float32), np.float32(0.0))
    known = n >= 2
    nm1 = np.maximum(n - np.float32(1.0), np.float32(1.0))
    with np.errstate(over="ignore", invalid="ignore", divide="ignore", under="ignore"):
        var = np.where(known, m2 / nm1, np.float32(np.inf))  # sigma^2 / n with the Bessel-corrected sigma^2
        theta = np.array(mean, np.float32)
        if skew_correction:
            skew_max = np.where(known, (n - np.float32(2.0)) / np.sqrt(nm1), np.float32(0.0))
            bound = skew_max * m2 * np.sqrt(m2)
            m3 = np.clip(np.asarray(m3, np.float32), -bound, bound)
            # Curto 2023 eq. 20: mu + M3 / (6 sigma^2 n) with sigma^2 = M2 n / (n - 1)
            correction = m3 * nm1 / (np.float32(6.0) * m2 * n * n)
            theta += np.where(np.isfinite(correction), correction, np.float32(0.0))
    return PixelEstimates(theta, var.astype(np.float32), n[..., 0].astype(np.int32))


def critical_values_squared(alpha: float, max_count: int) -> np.ndarray:
    """t_{1-alpha/2, nu}^2 for nu = 0 .. 2 max_count - 2, float32, with the untestable nu = 0 as 1e30.

    The table length is rounded up to a power of two so that frames with similar counts share a table.
    """
    nu_max = 1 << max(6, int(2 * max_count - 2).bit_length())
    table = np.asarray(critical_value_table(float(alpha), nu_max), np.float64) ** 2
    return np.minimum(table, UNTESTABLE_CRIT2).astype(np.float32)


def membership(
    theta_i: np.ndarray,
    var_i: np.ndarray,
    theta_j: np.ndarray,
    var_j: np.ndarray,
    crit2: np.ndarray,
    symmetric: bool,
) -> np.ndarray:
    """m_ij of Algorithm 2: True where estimator j may be averaged into pixel i, all channels passing.

    theta_*, var_*: (..., C) float32 from `PixelEstimates`; crit2: (...) float32 squared critical
    values t_{1-alpha/2, n_i + n_j - 2}^2. Returns (...) bool. Symmetric: eq. 12; else eq. 14 with i
    the pixel being denoised.
    """
    diff = theta_i - theta_j
    d2 = diff * diff
    crit2 = crit2[..., None]
    with np.errstate(over="ignore", invalid="ignore"):
        if symmetric:
            passed = d2 <= crit2 * (var_i + var_j)
        else:
            passed = d2 + var_j <= (np.float32(1.0) + np.float32(2.0) * crit2) * var_i
    return passed.all(axis=-1)


def _pair_crit2_numpy(table: np.ndarray, n_i: np.ndarray, n_j: np.ndarray) -> np.ndarray:
    return table[np.minimum(np.maximum(n_i + n_j - 2, 0), table.size - 1)]


def statistical_filter_numpy(
    color: np.ndarray, features: np.ndarray, estimates: PixelEstimates, params: StatisticalParams
) -> np.ndarray:
    """Reference implementation of `statistical_filter` in numpy, on `base_weights` (same arguments)."""
    table = critical_values_squared(params.alpha, int(estimates.count.max(initial=0)))
    theta, var, count = estimates.theta, estimates.var, estimates.count
    num = color.astype(np.float32, copy=True)
    den = np.ones(color.shape[:2], np.float32)
    for centre, neighbour, rho in base_weights(features, params.base.radius, params.base.sigma2_position):
        crit2 = _pair_crit2_numpy(table, count[centre], count[neighbour])
        args = theta[centre], var[centre], theta[neighbour], var[neighbour], crit2
        into_centre = rho * membership(*args, params.symmetric)
        if params.symmetric:
            into_neighbour = into_centre
        else:
            into_neighbour = rho * membership(args[2], args[3], args[0], args[1], crit2, False)
        num[centre] += into_centre[..., None] * color[neighbour]
        den[centre] += into_centre
        num[neighbour] += into_neighbour[..., None] * color[centre]
        den[neighbour] += into_neighbour
    return num / den[..., None]


STRIP_ROWS = 16  # rows per work item of the compiled kernel (at least the radius; see `_filter_kernel`)


@njit(cache=True, error_model="numpy")
def _pair_crit2(crit2, count, y, yn, p, q, uniform, out):
    """Squared critical values of the pairs (y, p) - (yn, q) into out: t^2_{1-alpha/2, n_i + n_j - 2} (table lookup)."""
    if uniform:
        out[:] = crit2[min(max(2 * count[0, 0] - 2, 0), crit2.size - 1)]
        return
    last = crit2.size - 1
    n_p, n_q = count[y, p], count[yn, q]
    for t in range(out.size):
        out[t] = crit2[min(max(n_p[t] + n_q[t] - 2, 0), last)]


@njit(cache=True, error_model="numpy")
def _pair_weights(theta, var, features, crit2, count, uniform, symmetric, y, yn, p, q, position_term, scratch,
                  into_centre, into_neighbour):
    """rho_ij m_ij of the pairs i = (y, p), j = (yn, q) along a row segment (p, q: slices of equal length n):
    into_centre[:n] weights j -> i, into_neighbour[:n] i -> j (the same array when symmetric). Branch-free
    loops over contiguous rows (SIMD); exp by `neg_exp`. scratch: (2, W) float32 work rows."""
    n = into_centre.size
    distance2, c2 = scratch[0, :n], scratch[1, :n]
    distance2[:] = position_term
    for k in range(features.shape[0]):
        f_p, f_q = features[k, y, p], features[k, yn, q]
        for t in range(n):
            diff = f_q[t] - f_p[t]
            distance2[t] += diff * diff
    _pair_crit2(crit2, count, y, yn, p, q, uniform, c2)
    half = np.float32(0.5)
    for t in range(n):
        into_centre[t] = neg_exp(half * distance2[t])
    if not symmetric:
        into_neighbour[:] = into_centre
    for c in range(3):  # the test in every colour channel; one loop per channel keeps each loop at few streams
        theta_p, theta_q, var_p, var_q = theta[c, y, p], theta[c, yn, q], var[c, y, p], var[c, yn, q]
        if symmetric:
            _gate_symmetric(theta_p, theta_q, var_p, var_q, c2, into_centre)
        else:
            _gate_asymmetric(theta_p, theta_q, var_p, var_q, c2, into_centre)
            _gate_asymmetric(theta_q, theta_p, var_q, var_p, c2, into_neighbour)


@njit(cache=True, error_model="numpy")
def _gate_symmetric(theta_i, theta_j, var_i, var_j, c2, weight):
    """weight = 0 where eq. 12 rejects the pair in this channel: (theta_i - theta_j)^2 > c2 (var_i + var_j).
    (LLVM vectorises a loop only while its runtime alias checks stay few: hence a loop per channel.)"""
    for t in range(weight.size):
        diff = theta_i[t] - theta_j[t]
        weight[t] = weight[t] if diff * diff <= c2[t] * (var_i[t] + var_j[t]) else np.float32(0.0)


@njit(cache=True, error_model="numpy")
def _gate_asymmetric(theta_i, theta_j, var_i, var_j, c2, weight):
    """weight = 0 where eq. 14 rejects j for the pixel i in this channel: d^2 + var_j > (1 + 2 c2) var_i."""
    one, two = np.float32(1.0), np.float32(2.0)
    for t in range(weight.size):
        diff = theta_i[t] - theta_j[t]
        passed = diff * diff + var_j[t] <= (one + two * c2[t]) * var_i[t]
        weight[t] = weight[t] if passed else np.float32(0.0)


@njit(cache=True, error_model="numpy")
def _scatter(acc, color, weight, y, p, yn, q):
    """acc[:C, y, p] += weight * color[:, yn, q] and acc[C, y, p] += weight (p, q: row segments of equal length).
    One loop per plane: a loop writing several planes of acc would need more runtime alias checks than LLVM
    makes before it vectorises."""
    channels = color.shape[0]
    n = weight.size
    for c in range(channels):
        acc_p, color_q = acc[c, y, p], color[c, yn, q]
        for t in range(n):
            acc_p[t] += weight[t] * color_q[t]
    total = acc[channels, y, p]
    for t in range(n):
        total[t] += weight[t]


@njit(cache=True, error_model="numpy")
def _filter_strip(y0, y1, color, theta, var, features, count, crit2, position_terms, radius, symmetric, acc):
    """Accumulate every pair whose first pixel lies in rows [y0, y1) and whose second pixel follows it in raster
    order within the window (half of the symmetric pairs), into both pixels' sums. Planar arrays: color (C, H, W),
    theta and var (3, H, W), features (F, H, W) float32; count (H, W) int64 or (1, 1) when uniform.

    acc: (C + 1, H, W) float32 running sums of rho * color (planes 0..C-1) and of rho (plane C)."""
    height, width = color.shape[1:]
    uniform = count.size == 1  # one sample count for the whole frame: one critical value
    scratch = np.empty((2, width), np.float32)
    weights = np.empty((2, width), np.float32)
    for y in range(y0, y1):
        for dy in range(0, min(radius, height - 1 - y) + 1):
            yn = y + dy
            for dx in range(1 if dy == 0 else -radius, radius + 1):
                x0, x1 = max(0, -dx), min(width, width - dx)
                if x0 >= x1:
                    continue
                n = x1 - x0
                p, q = slice(x0, x1), slice(x0 + dx, x1 + dx)
                into_centre = weights[0, :n]
                into_neighbour = into_centre if symmetric else weights[1, :n]
                _pair_weights(theta, var, features, crit2, count, uniform, symmetric, y, yn, p, q,
                              position_terms[dy + radius, dx + radius], scratch, into_centre, into_neighbour)
                _scatter(acc, color, into_centre, y, p, yn, q)
                _scatter(acc, color, into_neighbour, yn, q, y, p)


@njit(parallel=True, cache=True, error_model="numpy")
def _filter_kernel(color, theta, var, features, count, crit2, position_terms, radius, symmetric, strip_rows):
    """Symmetric-pair scatter in strips of `strip_rows` >= radius rows: a strip writes only to itself and
    the next strip, so the even strips run in parallel, then the odd ones, without write conflicts.
    Planar inputs as `_filter_strip`; returns (H, W, C) float32."""
    channels, height, width = color.shape
    acc = np.empty((channels + 1, height, width), np.float32)
    acc[:channels] = color
    acc[channels] = 1.0
    strips = (height + strip_rows - 1) // strip_rows
    for parity in range(2):
        for half in prange((strips - parity + 1) // 2):
            y0 = (2 * np.int64(half) + parity) * strip_rows
            _filter_strip(
                y0, min(y0 + strip_rows, height), color, theta, var, features, count, crit2, position_terms,
                radius, symmetric, acc,
            )
    out = np.empty((height, width, channels), np.float32)
    for y in prange(height):
        for x in range(width):
            for c in range(channels):
                out[y, x, c] = acc[c, y, x] / acc[channels, y, x]
    return out


def position_terms(radius: int, sigma2_position: float) -> np.ndarray:
    """(dy^2 + dx^2) / sigma2_position over the window, (2r+1, 2r+1) float32, as `base_weights` rounds it."""
    offsets = np.arange(-radius, radius + 1)
    d2 = np.add.outer(offsets * offsets, offsets * offsets)
    return np.array([[np.float32(v / sigma2_position) for v in row] for row in d2], np.float32).reshape(d2.shape)


def statistical_filter(
    color: np.ndarray, features: np.ndarray, estimates: PixelEstimates, params: StatisticalParams
) -> np.ndarray:
    """Sakai 2024 Algorithm 2: out_i = sum_j rho_ij m_ij color_j / sum_j rho_ij m_ij over the window.

    color: (H, W, C) float32 linear radiance to filter (any sign, any magnitude).
    features: (H, W, F) float32 from `guide_features(params.base, ...)`.
    estimates: `pixel_estimates` of the frame's statistics, (H, W, 3) each.
    Returns (H, W, C) float32. The centre weight is 1 (m_ii = 1, rho_ii = 1), so the result is a convex
    combination of inputs within the window: a constant image is unchanged and nothing spreads further
    than `params.base.radius` pixels. Compiled (numba, parallel over strips of rows, each pair's weight
    evaluated once, planar (K, H, W) copies of the inputs so that every window offset is a SIMD loop along a
    row, exp by `bilateral.neg_exp`); parity with `statistical_filter_numpy` is tested.
    """
    count = estimates.count
    table = critical_values_squared(params.alpha, int(count.max(initial=0)))
    if count.size and count.min() == count.max():
        count = count[:1, :1]  # the kernel's uniform-count path
    radius = params.base.radius
    return _filter_kernel(
        _planes(color),
        _planes(estimates.theta),
        _planes(estimates.var),
        _planes(features),
        np.ascontiguousarray(count, np.int64),
        table,
        position_terms(radius, params.base.sigma2_position),
        radius,
        params.symmetric,
        max(radius, STRIP_ROWS),
    )


def _planes(array: np.ndarray) -> np.ndarray:
    """(H, W, K) -> contiguous (K, H, W) float32, the layout of the compiled kernels."""
    return np.ascontiguousarray(np.moveaxis(np.asarray(array, np.float32), -1, 0))
