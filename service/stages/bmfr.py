"""Block regression on G-buffers only, in the manner of BMFR (Koskela et al. 2019): the "existing
regression" that Choi et al. 2024 compare cross-regression with (their Figs. 2 and 4).

Radiance (demodulated by albedo, as BMFR does) is fitted per centre pixel as a linear function of
G-buffer features over a window, with flat weights, by the block-wise solver of
`service.regression` (Choi eqs. 3-5 with w = 1). Features: albedo RGB, normal XYZ, log depth
and the pixel position (x, y). Differences from the paper's BMFR: overlapping windows on a sparse
centre grid blended by eq. 5 instead of disjoint 32x32 blocks, first-order features only, and no
temporal accumulation (it is a spatial filter). Geometric edges survive; detail that no G-buffer shows
(shadows, caustics) is blurred, which is the point of the comparison.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from service.regression.block import block_regression
from service.regression.box import box_regression
from service.regression.planes import (
    channel_planes,
    channel_planes_reference,
    from_planes,
    standardise,
    standardise_reference,
    to_planes,
)
from service.regression.solve import RIDGE_ABSOLUTE, RIDGE_RELATIVE
from service.regression.terms import BlockParams, plain_terms
from service.stages.albedo import remodulate
from service.stages.bilateral import log_depth
from service.stages.outliers import FIREFLY_K, check_firefly_k, clamp_outlier_planes


@dataclass(frozen=True)
class BmfrParams:
    """Options of the G-buffer block regression."""

    window: int = 13  # side of the square regression window, pixels, odd (17 spans whole objects in small frames)
    sparsity: int = 6  # centre pixels on every 6th row and column (cheaper than 4, as accurate here)
    demodulate: bool = True  # regress radiance / albedo and multiply back (Koskela 2019 sec. 3)
    firefly_k: float | None = FIREFLY_K  # clamp outliers to k neighbour ranges beyond their neighbours; None: off
    robust_clamp: bool = True  # sigma-clipped clamp of outlier clusters (outliers.clamp_outlier_clusters)
    ridge_relative: float = RIDGE_RELATIVE  # Tikhonov, relative to each feature's scale (service.regression.solve)
    ridge_absolute: float = RIDGE_ABSOLUTE  # Tikhonov floor x sum of weights (service.regression.solve)
    sigma_position: float | None = None  # pixels; Gaussian falloff of the weights with distance, None: flat

    def __post_init__(self) -> None:
        if self.window < 1 or self.window % 2 == 0:
            raise ValueError(f"window must be a positive odd number of pixels, got {self.window}")
        check_firefly_k(self.firefly_k)
        self.block()

    def block(self) -> BlockParams:
        return BlockParams(
            self.window // 2, self.sparsity, self.ridge_relative, self.ridge_absolute, self.sigma_position
        )


def gbuffer_features(albedo: np.ndarray, normal: np.ndarray, depth: np.ndarray | None = None) -> np.ndarray:
    """BMFR explanatory variables as standardised planes.

    albedo: (H, W, 3) float32 in [0, 1]; normal: (H, W, 3) float32 unit (or zero) normal; depth: (H, W, 1)
    float32 camera distance, scene units, or None. Returns (K, H, W) float32, K = 8 or 9: albedo RGB,
    normal XYZ, log depth (when given), pixel x and y; each plane standardised over the frame. Built in
    place (`channel_planes`, in-place `standardise`); `gbuffer_features_reference` is the numpy twin.
    """
    height, width = albedo.shape[:2]
    planes = np.empty((8 if depth is None else 9, height, width), np.float32)
    channel_planes(albedo, out=planes[0:3])
    channel_planes(normal, out=planes[3:6])
    if depth is not None:
        log_depth(depth[..., 0], out=planes[6])
    planes[-2] = np.arange(width, dtype=np.float32)
    planes[-1] = np.arange(height, dtype=np.float32)[:, None]
    return standardise(planes, out=planes)


def gbuffer_features_reference(albedo: np.ndarray, normal: np.ndarray, depth: np.ndarray | None = None) -> np.ndarray:
    """Plain-numpy twin of `gbuffer_features`."""
    height, width = albedo.shape[:2]
    x = np.broadcast_to(np.arange(width, dtype=np.float32), (1, height, width))
    y = np.broadcast_to(np.arange(height, dtype=np.float32)[:, None], (1, height, width))
    parts = [to_planes(albedo), to_planes(normal)]
    if depth is not None:
        parts.append(log_depth(to_planes(depth)))
    parts += [x, y]
    return standardise_reference(np.concatenate(parts, axis=0))


def bmfr(
    color: np.ndarray,
    albedo: np.ndarray,
    normal: np.ndarray,
    depth: np.ndarray | None = None,
    params: BmfrParams | None = None,
    *,
    reference: bool = False,
) -> np.ndarray:
    """Denoise `color` by block regression on G-buffer features.

    color: (H, W, 3) float32 linear HDR radiance (any sign); albedo, normal, depth: see
    `gbuffer_features`. Returns (H, W, 3) float32 linear radiance. reference: plain-numpy kernels (tests).
    """
    params = params or BmfrParams()
    factor = albedo if params.demodulate else None  # demodulated here, remodulated in the last pass
    planes = (channel_planes_reference if reference else channel_planes)(color, factor)
    planes = clamp_outlier_planes(planes, params.firefly_k, params.robust_clamp)
    features = (gbuffer_features_reference if reference else gbuffer_features)(albedo, normal, depth)
    block = params.block()
    if block.sigma_position is None:  # flat weights: exact box sums, same result; remodulation fused
        return from_planes(box_regression(features, planes, block, albedo=factor, reference=reference))
    out = from_planes(block_regression(plain_terms(features), planes, block, reference=reference))
    return out if factor is None else remodulate(out, factor)
