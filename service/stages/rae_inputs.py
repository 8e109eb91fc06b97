"""The recurrent autoencoder's input planes and the inverse of its output transform (service.layout.RAE_INPUTS,
RAE_OUTPUTS). Training (models/train/dataset.py) and serving (service/pipelines/rae.py) both call these, so
the channel order and transforms exist once.

Radiance is albedo-demodulated (Chaitanya 2017 sec. 3.2) with service.stages.albedo's offset and compressed
with log1p (the paper raises its input to the power 0.2; log1p compresses HDR as the other networks here do;
negative radiance, legal input, counts as 0). Depth is divided by the median depth of the frame's surface
hits (a nonzero normal; misses carry any large value a renderer writes and stay out of the median),
clipped at DEPTH_CLIP and log1p-compressed, so the network sees the same numbers for a scene modelled in
millimetres or in metres, whatever share of the frame is sky. Roughness, optional in the frame format, is
ROUGHNESS_ABSENT when a frame has none (training drops it to that value at random, so the network knows it).
"""

from __future__ import annotations

import numpy as np

from service.layout import RAE_INPUTS, channel_slices, total_channels
from service.stages.albedo import demodulate
from service.stages.reprojection import surface_hit

DEPTH_CLIP = 16.0  # relative depth above this (misses, far background) reads as this
DEPTH_STRIDE = 4  # the median depth is taken over every 4th row and column (a 1/16 subsample)
LOG_RADIANCE_MAX = 30.0  # log1p output clipped here before expm1: demodulated radiance up to ~1e13
ROUGHNESS_ABSENT = -1.0  # the roughness plane of a frame without `roughness` (outside the range [0, 1])

# Plane positions, all from the layout. The radiance leads and the guides follow it: training stores the
# guides apart and stacks [radiance, guides] (models/train/rae.py, RaeRecipe.inputs).
if RAE_INPUTS[0].name != "radiance":
    raise ImportError("service.layout.RAE_INPUTS must lead with 'radiance' (training stacks it first)")
PLANES = total_channels(RAE_INPUTS)  # 8: the network input
RADIANCE = channel_slices(RAE_INPUTS)["radiance"]  # the radiance planes of the network input
GUIDE_GROUPS = RAE_INPUTS[1:]  # normal, depth, roughness: what `guide_planes` returns, in this order
GUIDE_PLANES = channel_slices(GUIDE_GROUPS)  # group name -> its planes in `guide_planes`' output
GUIDES = total_channels(GUIDE_GROUPS)  # 5


def median_depth(depth: np.ndarray, normal: np.ndarray) -> float:
    """depth: (H, W, 1) float32 camera distance (any unit); normal: (H, W, 3) float32 (zero where nothing was
    hit). The median depth of the surface hits of a DEPTH_STRIDE subsample, in depth's unit; 1 when none."""
    n = normal[::DEPTH_STRIDE, ::DEPTH_STRIDE]
    sample = depth[::DEPTH_STRIDE, ::DEPTH_STRIDE, 0]
    hit = surface_hit(n) & np.isfinite(sample) & (sample > 0)
    return float(np.median(sample[hit])) if hit.any() else 1.0


def demodulated(color: np.ndarray, albedo: np.ndarray) -> np.ndarray:
    """color: (..., 3) float32 linear radiance without emission; albedo: (..., 3) float32 in [0, 1].
    Returns service.stages.albedo.demodulate of max(color, 0): same shape, float32 >= 0 (before log1p)."""
    return demodulate(np.maximum(color, 0), albedo)


def guide_planes(normal: np.ndarray, depth: np.ndarray, roughness: np.ndarray | None,
                 out: np.ndarray | None = None) -> np.ndarray:
    """The non-radiance inputs. normal: (H, W, 3) float32 unit or zero; depth: (H, W, 1) float32 camera
    distance, finite (the frame contract repairs NaN and Inf); roughness: (H, W, 1) float32, clipped to its
    range [0, 1] (the frame contract does not bound it, and a network fed 3e38 overflows), or None
    (ROUGHNESS_ABSENT). Returns (5, H, W) float32 planes in RAE_INPUTS order after the radiance: normal, log1p
    relative depth, roughness; written into `out` when given."""
    h, w = normal.shape[:2]
    out = np.empty((GUIDES, h, w), np.float32) if out is None else out
    out[GUIDE_PLANES["normal"]] = normal.transpose(2, 0, 1)
    scale = np.float32(median_depth(depth, normal))
    relative = np.minimum(np.maximum(depth[..., 0], 0) / scale, np.float32(DEPTH_CLIP))
    out[GUIDE_PLANES["depth"]] = np.log1p(relative)
    if roughness is None:
        out[GUIDE_PLANES["roughness"]] = ROUGHNESS_ABSENT
    else:
        np.clip(roughness[..., 0], np.float32(0), np.float32(1), out=out[GUIDE_PLANES["roughness"]])
    return out


def rae_planes(color: np.ndarray, albedo: np.ndarray, normal: np.ndarray, depth: np.ndarray,
               roughness: np.ndarray | None, *, background: np.ndarray | None = None) -> np.ndarray:
    """The network input of one frame: (8, H, W) float32 planes in RAE_INPUTS order, from color (H, W, 3)
    float32 linear radiance without emission and the layers of `demodulated` and `guide_planes`.
    background: (H, W) bool or None; where True the radiance planes are 0, as for a black `color` there."""
    out = np.empty((PLANES, *color.shape[:2]), np.float32)
    out[RADIANCE] = np.log1p(demodulated(color, albedo)).transpose(2, 0, 1)
    if background is not None:
        np.copyto(out[RADIANCE], np.float32(0), where=background)
    guide_planes(normal, depth, roughness, out[RADIANCE.stop:])
    return out


def lighting_from_output(planes: np.ndarray) -> np.ndarray:
    """planes: (3, H, W) float32 finite network output (log1p demodulated radiance; the pipeline refuses a
    non-finite one). Returns (H, W, 3) float32 linear demodulated radiance, >= 0 and finite."""
    return np.expm1(np.clip(planes.transpose(1, 2, 0), 0.0, LOG_RADIANCE_MAX))

