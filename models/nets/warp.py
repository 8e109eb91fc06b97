"""Torch twin of service/stages/hidden_warp.py (the hidden-state warp), differentiable in the state.

Bilinear sampling at (row + Y, column + X) with the taps outside the frame dropped and the weights
renormalised over the inside ones, zero where the point is off screen or the inside taps carry less than
MIN_WEIGHT: service.stages.reprojection.reproject without depth and normal tests.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from service.stages.reprojection import ReprojectionParams

MIN_WEIGHT = ReprojectionParams().min_weight  # the numpy side's default


def downsample_motion(motion: torch.Tensor, scale: int) -> torch.Tensor:
    """(N, 2, H, W) backward motion in pixels, H and W multiples of `scale` -> (N, 2, H/scale, W/scale)."""
    return F.avg_pool2d(motion, scale) / scale if scale > 1 else motion


def warp_valid(state: torch.Tensor, motion: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """state: (N, C, h, w) of the previous frame; motion: (N, 2, h, w) backward motion on its grid, pixels.
    Returns (warped (N, C, h, w), the state sampled where each pixel was, zero where invalid; valid
    (N, 1, h, w) bool): `reproject`'s (warped, valid) (module docstring)."""
    n, _, h, w = state.shape
    rows = torch.arange(h, dtype=state.dtype, device=state.device).view(1, h, 1)
    cols = torch.arange(w, dtype=state.dtype, device=state.device).view(1, 1, w)
    ys, xs = rows + motion[:, 1], cols + motion[:, 0]
    on_screen = (ys >= -0.5) & (ys < h - 0.5) & (xs >= -0.5) & (xs < w - 0.5)
    grid = torch.stack([2 * xs / max(w - 1, 1) - 1, 2 * ys / max(h - 1, 1) - 1], dim=-1)
    sample = F.grid_sample(state, grid, mode="bilinear", padding_mode="zeros", align_corners=True)
    ones = torch.ones(n, 1, h, w, dtype=state.dtype, device=state.device)
    total = F.grid_sample(ones, grid, mode="bilinear", padding_mode="zeros", align_corners=True)
    valid = on_screen[:, None] & (total >= MIN_WEIGHT)
    return sample / total.clamp_min(MIN_WEIGHT) * valid.to(state.dtype), valid


def warp(state: torch.Tensor, motion: torch.Tensor) -> torch.Tensor:
    """state: (N, C, h, w) of the previous frame; motion: (N, 2, h, w) backward motion on its grid, pixels.
    Returns (N, C, h, w), the state sampled where each pixel was (module docstring)."""
    return warp_valid(state, motion)[0]


def warp_level(state: torch.Tensor, motion: torch.Tensor, scale: int) -> torch.Tensor:
    """warp(state, downsample_motion(motion, scale)): motion (N, 2, H, W) at the padded frame's resolution."""
    return warp(state, downsample_motion(motion, scale))
