"""Outlier suppression before a filter: the two clamps the regressions use, for any (H, W, C) image.

A firefly (one sample of 1e3 among samples of 1) is a value no filter should average in: a bilateral or
t-test filter spreads it into a bright disc of its window, a temporal filter into its history. The
regressions (bmfr, flr, cross-regression) clamp their inputs with `local_regression.clamp_fireflies`
(isolated values, against the 3x3 neighbour range) and `local_regression.clamp_outlier_clusters` (small
clusters, against a sigma-clipped 7x7 statistic of the log-compressed signal), in that order, through
`clamp_outlier_planes`; the filters without a regression (bilateral, statistical, svgf) call
`clamp_outliers` on their colour. A directly visible light is not clipped when
the frame carries its emission: the renderer's `emission` layer, or, for a frame with both halves and no
emission layer, its exact pixels (`service.stages.exact`, taken out by `Pipeline.step`).
"""

from __future__ import annotations

import numpy as np

from service.stages.local_regression import FIREFLY_K, clamp_fireflies, clamp_outlier_clusters, from_planes, to_planes


def clamp_outlier_planes(planes: np.ndarray, firefly_k: float | None = FIREFLY_K, robust: bool = True) -> np.ndarray:
    """(C, H, W) float32 radiance planes (any sign) with isolated outliers clipped (`clamp_fireflies`, k =
    firefly_k; None: off) and then small clusters of them (`clamp_outlier_clusters`; robust=False: off).
    Returns (C, H, W) float32; a constant image and smooth gradients are unchanged."""
    if firefly_k is not None:
        planes = clamp_fireflies(planes, firefly_k)
    if robust:  # clusters of outliers, which the 3x3 clamp cannot see
        planes = clamp_outlier_clusters(planes)
    return planes


def clamp_outliers(image: np.ndarray, firefly_k: float = FIREFLY_K) -> np.ndarray:
    """`image` ((H, W, C) float32 linear radiance, any sign) through `clamp_outlier_planes` with both clamps.
    Returns (H, W, C) float32."""
    return from_planes(clamp_outlier_planes(to_planes(image), firefly_k))
