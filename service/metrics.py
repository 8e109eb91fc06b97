"""Image error metrics shared by the demo, training and the benchmark.

relL2 is the relative MSE of Rousselle et al. 2011 as the Choi et al. 2024 code computes it: the
mean over pixels and channels of (x - r)^2 / (m^2 + 0.01), where m is the mean of the reference's
three channels at the pixel. `rel_l2(..., trim=0.001)` drops the highest 0.1% of per-pixel errors
first, the usual convention that keeps a few aliased emitter-edge pixels from dominating.
"""

from __future__ import annotations

import numpy as np

REL_L2_EPS = 0.01  # Rousselle 2011 / Choi 2024 code: denominator offset, radiance^2 units
TRIM_FRACTION = 0.001  # fraction of worst pixels dropped by the trimmed relL2


def rel_l2_map(image: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """Per-pixel relative squared error, averaged over channels.

    image, reference: (H, W, 3) float32 linear radiance. Returns (H, W) float64.
    """
    x = image.astype(np.float64)
    r = reference.astype(np.float64)
    m = r.mean(axis=-1, keepdims=True)
    return ((x - r) ** 2 / (m * m + REL_L2_EPS)).mean(axis=-1)


def rel_l2(image: np.ndarray, reference: np.ndarray, *, trim: float = 0.0) -> float:
    """Mean relL2 of `image` against `reference` ((H, W, 3) float32 linear radiance).

    trim: fraction in [0, 1) of the highest per-pixel errors dropped before averaging.
    """
    if not 0.0 <= trim < 1.0:
        raise ValueError(f"trim must be in [0, 1), got {trim}")
    errors = rel_l2_map(image, reference).ravel()
    if trim > 0.0:
        keep = errors.size - int(np.floor(errors.size * trim))
        errors = np.partition(errors, keep - 1)[:keep]
    return float(errors.mean())
