"""What a block regression is given (`service.regression.block`): its geometry and regularisation
(`BlockParams`), the pair terms of its buffers (`PairTerms`: features, weight guides, per-pixel sigma), and
the constants of Choi et al. 2024 eqs. 6-7 (the values of their code).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from service.regression.solve import RIDGE_ABSOLUTE, RIDGE_RELATIVE

WEIGHT_FLOOR = 1e-7  # added to every pair weight, as the Choi 2024 code does (ops/regression.cu)
EPS_VARIANCE = 1e-4  # Choi 2024 eq. 7 epsilon (value of their code), colour^2 units
EPS_SIGMA = 1e-2  # Choi 2024 eq. 6 epsilon (value of their code), colour units


@dataclass(frozen=True)
class BlockParams:
    """Geometry and regularisation of a block regression."""

    radius: int = 8  # window half-size in pixels: 8 gives the 17x17 window of Choi 2024 sec. 3
    sparsity: int = 4  # centres on every `sparsity`-th row and column (Choi 2024 sec. 3: 1/16 of the pixels)
    ridge_relative: float = RIDGE_RELATIVE  # see module constant
    ridge_absolute: float = RIDGE_ABSOLUTE  # see module constant
    sigma_position: float | None = None  # pixels; Gaussian falloff of the pair weight with distance, None: flat

    def __post_init__(self) -> None:
        if self.sparsity < 1:
            raise ValueError(f"sparsity must be >= 1, got {self.sparsity}")
        if self.radius < self.sparsity - 1:
            raise ValueError(
                f"radius {self.radius} leaves pixels without a centre; it must be >= sparsity - 1 = {self.sparsity - 1}"
            )
        if not (self.ridge_relative >= 0 and self.ridge_absolute > 0):
            raise ValueError("ridge_relative must be >= 0 and ridge_absolute > 0")
        if self.sigma_position is not None and not self.sigma_position > 0:
            raise ValueError(f"sigma_position must be > 0 or None, got {self.sigma_position}")


@dataclass(frozen=True)
class PairTerms:
    """Per-pixel inputs of a block regression, all channel-first float32 planes of one H x W frame.

    Pair features of centre c and pixel i, per group g: [1, shared_i - shared_c, grouped_i - grouped_c],
    where grouped feature k is divided by (sigma_i + sigma_c + EPS_SIGMA) when scaled[k] (Choi eq. 6).
    Pair weight: exp(-|h_i - h_c|^2 / (v_i + v_c + EPS_VARIANCE)) (Choi eq. 7), times the spatial falloff
    of `BlockParams.sigma_position`, plus WEIGHT_FLOOR.
    """

    shared: np.ndarray  # (Ks, H, W): features common to all groups (normals, depth, ...)
    grouped: np.ndarray  # (G, Kg, H, W): features of one group of target channels (Kg may be 0)
    scaled: np.ndarray  # (Kg,) bool: which grouped features are divided by sigma_i + sigma_c + eps
    sigma: np.ndarray  # (H, W): standard deviation used by `scaled`, units of the scaled features
    weight_guide: np.ndarray  # (D, H, W): h of the weight (D may be 0: flat weights)
    weight_variance: np.ndarray  # (H, W): v of the weight, units of h^2

    @property
    def groups(self) -> int:
        return self.grouped.shape[0]

    @property
    def features(self) -> int:
        """K1: coefficients per group, constant included."""
        return 1 + self.shared.shape[0] + self.grouped.shape[1]


def plain_terms(shared: np.ndarray, groups: int = 1) -> PairTerms:
    """PairTerms with only shared features, flat weights and no scaling (BMFR-style regression).

    shared: (Ks, H, W) float32 planes. Returns PairTerms with `groups` groups and no grouped features.
    """
    _, height, width = shared.shape
    zeros = np.zeros((height, width), np.float32)
    return PairTerms(
        np.ascontiguousarray(shared, dtype=np.float32),
        np.zeros((groups, 0, height, width), np.float32),
        np.zeros(0, bool),
        zeros,
        np.zeros((0, height, width), np.float32),
        zeros,
    )


def centre_count(size: int, sparsity: int) -> int:
    """Number of centres along an axis of `size` pixels: positions 0, s, 2s, ... < size."""
    return (size + sparsity - 1) // sparsity


def spatial_weights(params: BlockParams) -> np.ndarray:
    """(2r+1, 2r+1) float32 spatial factor of the pair weight: ones, or a Gaussian of the offset in pixels."""
    r = params.radius
    if params.sigma_position is None:
        return np.ones((2 * r + 1, 2 * r + 1), np.float32)
    d = np.arange(-r, r + 1, dtype=np.float32)
    g = np.exp(-0.5 * (d / np.float32(params.sigma_position)) ** 2)
    return np.ascontiguousarray(np.outer(g, g), dtype=np.float32)
