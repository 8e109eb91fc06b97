"""Albedo demodulation: divide radiance by albedo before filtering so texture detail survives, then
multiply back. The small offset keeps black albedo (and environment pixels, albedo 0) well defined:
there demodulation and remodulation are a division and multiplication by ALBEDO_EPS, i.e. exact."""

from __future__ import annotations

import numba
import numpy as np

ALBEDO_EPS = np.float32(1e-2)  # albedo units; as in SVGF-style demodulation, keeps 1/albedo <= 100


@numba.njit(inline="always")
def albedo_factor(albedo):  # pragma: no cover - jitted
    """The divisor of `demodulate` and factor of `remodulate` for one float32 albedo value, in kernels."""
    return np.maximum(albedo, np.float32(0.0)) + ALBEDO_EPS


def demodulate(color: np.ndarray, albedo: np.ndarray) -> np.ndarray:
    """color: (H, W, 3) float32 linear radiance; albedo: (H, W, 3) float32 in [0, 1].
    Returns (H, W, 3) float32 irradiance-like values color / (albedo + eps)."""
    return color / (np.maximum(albedo, 0) + ALBEDO_EPS)


def remodulate(irradiance: np.ndarray, albedo: np.ndarray) -> np.ndarray:
    """Inverse of `demodulate`: (H, W, 3) float32 -> radiance (H, W, 3) float32."""
    return irradiance * (np.maximum(albedo, 0) + ALBEDO_EPS)
