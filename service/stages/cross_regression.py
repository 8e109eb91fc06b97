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
outliers are clamped to their 3x3 neighbourhood before the log (see `local_regression.clamp_fireflies`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from service.stages.local_regression import (
    FIREFLY_K,
    RIDGE_ABSOLUTE,
    RIDGE_RELATIVE,
    BlockParams,
    PairTerms,
    block_regression,
    check_firefly_k,
    clamp_fireflies,
    from_planes,
    neighbour_mean,
    to_planes,
)


@dataclass(frozen=True)
class CrossRegressionParams:
    """Options of the cross-regression."""

    window: int = 17  # side of the square regression window, pixels (Choi 2024 sec. 3: 17 x 17), odd
    sparsity: int = 4  # centre pixels on every 4th row and column, 1/16 of the pixels (Choi 2024 sec. 3)
    firefly_k: float | None = FIREFLY_K  # clamp outliers to k neighbour ranges beyond their neighbours; None: off
    ridge_relative: float = RIDGE_RELATIVE  # Tikhonov, relative to each feature's scale (local_regression)
    ridge_absolute: float = RIDGE_ABSOLUTE  # Tikhonov floor x sum of weights (local_regression)

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
    y = np.clip(np.asarray(log_color, np.float32), -88.0, 88.0)
    return (np.sign(y) * np.expm1(np.abs(y))).astype(np.float32, copy=False)


def pixel_variance(log_planes: np.ndarray) -> np.ndarray:
    """Choi sec. 4.1 variance estimate: |y - mean of the 8 neighbours|^2, summed over channels, numba kernel.

    log_planes: (C, H, W) float32 log colour. Neighbours outside the frame are left out of the mean.
    Returns (H, W) float32, >= 0 (0 for a 1x1 frame). `pixel_variance_reference` is the numpy twin.
    """
    planes = np.ascontiguousarray(log_planes, dtype=np.float32)
    out = np.empty(planes.shape[1:], np.float32)
    _variance_kernel(planes, out)
    return out


def pixel_variance_reference(log_planes: np.ndarray) -> np.ndarray:
    """Plain-numpy twin of `pixel_variance` (same argument and result)."""
    diff = log_planes - neighbour_mean(log_planes)
    return np.einsum("chw,chw->hw", diff, diff).astype(np.float32)


@numba.njit(parallel=True, cache=True, fastmath=True)
def _variance_kernel(planes, out):  # pragma: no cover - jitted
    """planes (C, H, W) -> out (H, W): 3-pixel row sums of the valid rows, minus the pixel, per channel."""
    channels, height, width = planes.shape
    for y in numba.prange(height):
        y0, y1 = max(0, y - 1), min(height, y + 2)
        rows = y1 - y0
        total = np.zeros(width, np.float32)
        acc = np.empty(width, np.float32)
        for c in range(channels):
            acc[:] = 0.0
            for yy in range(y0, y1):
                row = planes[c, yy]
                for x in range(1, width - 1):
                    acc[x] += row[x - 1] + row[x] + row[x + 1]
                acc[0] += row[0] + (row[1] if width > 1 else np.float32(0.0))
                if width > 1:
                    acc[width - 1] += row[width - 2] + row[width - 1]
            own = planes[c, y]
            inner = np.float32(1.0) / np.float32(3 * rows - 1)
            for x in range(1, width - 1):
                d = own[x] - (acc[x] - own[x]) * inner
                total[x] += d * d
            count = (2 if width > 1 else 1) * rows - 1  # at the first and last column
            for x in range(0, width, max(width - 1, 1)):
                d = own[x] - (acc[x] - own[x]) / count if count > 0 else np.float32(0.0)
                total[x] += d * d
        out[y] = total


def buffer_terms(log_planes: np.ndarray, variance: np.ndarray, albedo: np.ndarray, normal: np.ndarray) -> PairTerms:
    """One buffer's explanatory variables (eq. 6) and weights (eq. 7) for `block_regression`.

    log_planes: (3, H, W) float32 log colour of the buffer; variance: (H, W) from `pixel_variance`;
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


def cross_regression(
    color_a: np.ndarray,
    color_b: np.ndarray,
    albedo: np.ndarray,
    normal: np.ndarray,
    params: CrossRegressionParams | None = None,
    *,
    reference: bool = False,
) -> tuple[np.ndarray, np.ndarray]:
    """`cross_regression_planes` with (H, W, 3) float32 pilots (same arguments, same values)."""
    pilot_a, pilot_b = cross_regression_planes(color_a, color_b, albedo, normal, params, reference=reference)
    return from_planes(pilot_a), from_planes(pilot_b)


def cross_regression_planes(
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
    logs = []
    for color in (color_a, color_b):
        planes = to_planes(color)
        if params.firefly_k is not None:
            planes = clamp_fireflies(planes, params.firefly_k)
        logs.append(linear_to_log(planes))
    log_a, log_b = logs
    albedo_planes, normal_planes = to_planes(albedo), to_planes(normal)
    terms_a = buffer_terms(log_a, pixel_variance(log_a), albedo_planes, normal_planes)
    terms_b = buffer_terms(log_b, pixel_variance(log_b), albedo_planes, normal_planes)
    pilot_a = block_regression(terms_a, log_b, block, reference=reference)
    pilot_b = block_regression(terms_b, log_a, block, reference=reference)
    return pilot_a, pilot_b
