"""The recurrent autoencoder's input planes and the inverse of its output transform (service.layout.RAE_INPUTS,
RAE_OUTPUTS). Training (models/train/dataset.py) and serving (service/pipelines/rae.py) both call these, so
the channel order and transforms exist once.

Radiance is albedo-demodulated (Chaitanya 2017 sec. 3.2) with service.stages.albedo's offset and compressed
with log1p (negative radiance, legal input, counts as 0). Depth is divided by the frame's median hit depth,
clipped at DEPTH_CLIP (misses: renderers write any large value) and log1p-compressed, so the network sees
the same numbers for a scene modelled in millimetres or in metres.
"""

from __future__ import annotations

import numpy as np

from service.layout import RAE_INPUTS, total_channels
from service.stages.albedo import ALBEDO_EPS

DEPTH_CLIP = 16.0  # relative depth above this (misses, far background) reads as this
DEPTH_STRIDE = 4  # the median depth is taken over every 4th row and column (a 1/16 subsample)
LOG_RADIANCE_MAX = 30.0  # log1p output clipped here before expm1: demodulated radiance up to ~1e13
PLANES = total_channels(RAE_INPUTS)  # 8
GUIDES = PLANES - 3  # normal, depth, roughness


def median_depth(depth: np.ndarray) -> float:
    """depth: (H, W, 1) float32 camera distance (any unit). The median of the positive finite values of a
    DEPTH_STRIDE subsample, in the same unit; 1 when there is none."""
    sample = depth[::DEPTH_STRIDE, ::DEPTH_STRIDE, 0]
    sample = sample[np.isfinite(sample) & (sample > 0)]
    return float(np.median(sample)) if sample.size else 1.0


def demodulated(color: np.ndarray, albedo: np.ndarray) -> np.ndarray:
    """color: (..., 3) float32 linear radiance without emission; albedo: (..., 3) float32 in [0, 1].
    Returns max(color, 0) / (albedo + ALBEDO_EPS), same shape, float32 >= 0 (before log1p)."""
    return np.maximum(color, 0) / (np.maximum(albedo, 0) + ALBEDO_EPS)


def guide_planes(normal: np.ndarray, depth: np.ndarray, roughness: np.ndarray | None) -> np.ndarray:
    """The non-radiance inputs. normal: (H, W, 3) float32 unit or zero; depth: (H, W, 1) float32 camera
    distance; roughness: (H, W, 1) float32 in [0, 1] or None (zeros). Returns (5, H, W) float32 planes in
    RAE_INPUTS order after the radiance: normal, log1p relative depth, roughness."""
    h, w = normal.shape[:2]
    out = np.empty((GUIDES, h, w), np.float32)
    out[0:3] = normal.transpose(2, 0, 1)
    relative = np.minimum(np.maximum(depth[..., 0], 0) / np.float32(median_depth(depth)), np.float32(DEPTH_CLIP))
    out[3] = np.log1p(np.nan_to_num(relative, nan=0.0))
    out[4] = 0.0 if roughness is None else roughness[..., 0]
    return out


def rae_planes(color: np.ndarray, albedo: np.ndarray, normal: np.ndarray, depth: np.ndarray,
               roughness: np.ndarray | None) -> np.ndarray:
    """The network input of one frame: (8, H, W) float32 planes in RAE_INPUTS order, from color (H, W, 3)
    float32 linear radiance without emission and the layers of `demodulated` and `guide_planes`."""
    radiance = np.log1p(demodulated(color, albedo)).transpose(2, 0, 1)
    return np.concatenate([radiance, guide_planes(normal, depth, roughness)], axis=0)


def radiance_from_output(planes: np.ndarray, albedo: np.ndarray) -> np.ndarray:
    """planes: (3, H, W) float32 network output (log1p demodulated radiance); albedo: (H, W, 3) float32.
    Returns (H, W, 3) float32 linear radiance (without emission), >= 0 and finite."""
    log = np.clip(planes.transpose(1, 2, 0), 0.0, LOG_RADIANCE_MAX)
    return np.expm1(log) * (np.maximum(albedo, 0) + ALBEDO_EPS)
