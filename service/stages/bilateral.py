"""Joint bilateral filter guided by G-buffers: the base filter rho_ij of Sakai et al. 2024, eq. 16.

rho_ij = exp(-1/2 (p_j - p_i)^T Sigma^-1 (p_j - p_i)) with p = (x, y, albedo RGB, normal XYZ) and a
diagonal Sigma (default diag(10, 10, 0.02, 0.02, 0.02, 0.1, 0.1, 0.1), Sakai sec. 5), restricted to a
square window of the given radius. As an extension the paper does not have, p may also hold log depth
(variance `sigma2_log_depth`, i.e. a relative depth difference), which separates silhouettes whose
albedo and normal agree. The weights are symmetric, rho_ij = rho_ji, so each pair is evaluated once.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
from numba import njit

from service.kernels.window import Slice2, overlap, window_offsets

DEPTH_FLOOR = 1e-6  # scene units; depths below this are clamped before the log


def log_depth(depth: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """log(max(depth, DEPTH_FLOOR)): depth any shape float32 camera distance, scene units; into `out`
    (same shape, float32) when given. The depth guide of every filter that takes one."""
    out = np.maximum(depth, np.float32(DEPTH_FLOOR), out=out)
    return np.log(out, out=out)


@dataclass(frozen=True)
class BilateralParams:
    radius: int = 6  # window half-size in pixels (Sakai uses 20 at 720p; 6 is their fast setting)
    sigma2_position: float = 10.0  # pixels^2, Sakai eq. 16 default
    sigma2_albedo: float = 0.02  # albedo units^2, Sakai eq. 16 default
    sigma2_normal: float = 0.1  # (unit normal components)^2, Sakai eq. 16 default
    sigma2_log_depth: float | None = 0.01  # (log depth)^2, ~10% relative depth; None: depth unused

    def __post_init__(self) -> None:
        if self.radius < 0:
            raise ValueError(f"radius must be >= 0, got {self.radius}")
        for name in ("sigma2_position", "sigma2_albedo", "sigma2_normal", "sigma2_log_depth"):
            value = getattr(self, name)
            if value is not None and not value > 0:
                raise ValueError(f"{name} must be > 0, got {value}")


def guide_features(
    params: BilateralParams,
    height: int,
    width: int,
    albedo: np.ndarray | None = None,
    normal: np.ndarray | None = None,
    depth: np.ndarray | None = None,
) -> np.ndarray:
    """Guide features scaled so that their squared distance is the Mahalanobis term of eq. 16.

    albedo: (H, W, 3) float32 in [0, 1]; normal: (H, W, 3) float32 unit (or zero) world-space normal;
    depth: (H, W, 1) float32 camera distance, scene units. Absent guides are left out.
    Returns (H, W, F) float32, F = 3 per colour guide + 1 for depth (F may be 0: a Gaussian filter).
    """
    parts: list[np.ndarray] = [np.zeros((height, width, 0), np.float32)]
    if albedo is not None:
        parts.append(albedo / np.float32(np.sqrt(params.sigma2_albedo)))
    if normal is not None:
        parts.append(normal / np.float32(np.sqrt(params.sigma2_normal)))
    if depth is not None and params.sigma2_log_depth is not None:
        parts.append(log_depth(depth) / np.float32(np.sqrt(params.sigma2_log_depth)))
    return np.ascontiguousarray(np.concatenate(parts, axis=-1), dtype=np.float32)


def base_weights(
    features: np.ndarray, radius: int, sigma2_position: float
) -> Iterator[tuple[Slice2, Slice2, np.ndarray]]:
    """rho_ij (eq. 16) for every pixel pair in the window, half of the symmetric pairs at a time.

    features: (H, W, F) float32 from `guide_features`. Yields (centre slices, neighbour slices, rho)
    for each offset of `window_offsets(radius, half=True)`; rho: (h, w) float32 in (0, 1] over the
    overlap. The pair (0, 0) is not yielded: its weight is 1. Because rho is symmetric, a caller
    applies each yielded rho from centre to neighbour and from neighbour to centre.
    """
    height, width = features.shape[:2]
    for dy, dx in window_offsets(radius, half=True):
        pair = overlap(height, width, dy, dx)
        if pair is None:
            continue
        centre, neighbour = pair
        diff = features[neighbour] - features[centre]
        distance2 = np.einsum("hwc,hwc->hw", diff, diff) + np.float32((dy * dy + dx * dx) / sigma2_position)
        yield centre, neighbour, np.exp(np.float32(-0.5) * distance2)


def joint_bilateral(color: np.ndarray, features: np.ndarray, params: BilateralParams) -> np.ndarray:
    """Normalised joint bilateral filter of `color` with the eq. 16 weights.

    color: (H, W, C) float32, any linear quantity (radiance may be negative or huge).
    features: (H, W, F) float32 from `guide_features`, same H and W.
    Returns (H, W, C) float32. The centre weight is 1, so the normalisation never divides by zero and
    a constant image is returned unchanged.
    """
    num = color.astype(np.float32, copy=True)
    den = np.ones(color.shape[:2], np.float32)
    for centre, neighbour, rho in base_weights(features, params.radius, params.sigma2_position):
        weight = rho[..., None]
        num[centre] += weight * color[neighbour]
        num[neighbour] += weight * color[centre]
        den[centre] += rho
        den[neighbour] += rho
    return num / den[..., None]


@njit(cache=True, inline="always")
def pair_weight(
    features: np.ndarray, y: int, x: int, yn: int, xn: int, position_term: np.float32, first: int = 0
) -> np.float32:
    """rho_ij of eq. 16 for one pixel pair, for compiled filters that visit pairs one at a time.

    features: (H, W, K) float32 whose channels `first` .. K-1 are the output of `guide_features` (a
    compiled filter may keep other per-pixel values in front of them); (y, x) and (yn, xn): the two
    pixels; position_term: float32 (dy^2 + dx^2) / sigma2_position. Returns float32 in (0, 1], the
    value `base_weights` yields for the pair (same float32 arithmetic up to summation order).
    """
    distance2 = position_term
    for k in range(first, features.shape[2]):
        diff = features[yn, xn, k] - features[y, x, k]
        distance2 += diff * diff
    return np.exp(np.float32(-0.5) * distance2)


# exp(-x) for compiled kernels, in a form LLVM vectorises (numba's exp is a scalar libm call without SVML):
# x = k / EXP_TABLE_STEPS + r with |r| <= 1 / (2 EXP_TABLE_STEPS), exp(-x) = table[k] * poly(r). Relative error
# < 2e-7 (float32 rounding; the degree-5 Taylor remainder is 5e-9). Above NEG_EXP_MAX (exp(-87) = 1.6e-38, the
# smallest normal float32) and for NaN it returns 0, so no subnormal ever enters the sums.
EXP_TABLE_STEPS = 4  # table entries per unit of x
NEG_EXP_MAX = np.float32(87.0)
_NEG_EXP_TABLE = np.exp(-np.arange(EXP_TABLE_STEPS * 87 + 2, dtype=np.float64) / EXP_TABLE_STEPS).astype(np.float32)


@njit(cache=True, inline="always")
def neg_exp(x: np.float32) -> np.float32:
    """exp(-x) for float32 x >= 0, vectorisable: 0 beyond NEG_EXP_MAX and for NaN; negative x count as 0."""
    ok = x <= NEG_EXP_MAX
    xc = max(x, np.float32(0.0)) if ok else np.float32(0.0)
    k = np.int32(xc * np.float32(EXP_TABLE_STEPS) + np.float32(0.5))
    r = xc - np.float32(k) * np.float32(1.0 / EXP_TABLE_STEPS)
    poly = np.float32(1.0) - r * (
        np.float32(1.0) - r * (np.float32(0.5) - r * (
            np.float32(1.0 / 6.0) - r * (np.float32(1.0 / 24.0) - r * np.float32(1.0 / 120.0))
        ))
    )
    value = _NEG_EXP_TABLE[k] * poly
    return value if ok else np.float32(0.0)
