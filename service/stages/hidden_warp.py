"""Warping a recurrent network's hidden state by the frame's motion (an option of the `rae` pipeline).

A hidden state at `scale` (its height and width are the padded frame's / scale) is moved the way the image
moved: the frame's backward motion (FRAME_FORMAT.md) is averaged over scale x scale blocks and divided by
`scale`, then the state is sampled bilinearly there by service.stages.reprojection.reproject (taps outside
the frame dropped and the weights renormalised; zero where the sample point is off screen). Each level's
motion is built from the level above it (`level_motions`): the mean of 2x2 block means is the 4x4 block
mean when the sizes divide (the padded frame's do), equal up to float32 rounding of the sums. The torch
twin that training runs through is models/nets/warp.py (block means of the full-resolution motion); a
parity test holds the two together.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from service.stages.reprojection import reproject


def downsample_motion(motion: np.ndarray, factor: int) -> np.ndarray:
    """motion: (H, W, 2) float32 backward motion in pixels of its grid, H and W multiples of `factor`.
    Returns (H / factor, W / factor, 2) float32: the block means (summed row by row through each block) in
    pixels of the downsampled grid."""
    total = motion[::factor, ::factor].copy(order="K")  # in the layout of `motion` (planes stay planes)
    for dy in range(factor):
        for dx in range(factor):
            if dy or dx:
                total += motion[dy::factor, dx::factor]
    total /= np.float32(factor * factor)
    total /= np.float32(factor)
    return total


def level_motions(motion: np.ndarray, scales: Sequence[int]) -> list[np.ndarray]:
    """motion: (H, W, 2) float32 backward motion of the padded frame, pixels; scales: increasing, each a
    multiple of the one before (the state's ModelInfo.state scales), H and W multiples of the last.
    Returns [(H / s, W / s, 2) float32 for s in scales]: `downsample_motion(motion, s)`, each level
    downsampled from the one before it."""
    levels, grid, at = [], motion, 1
    for scale in scales:
        if scale % at:
            raise ValueError(f"hidden-state scales must each divide the next, got {list(scales)}")
        grid, at = downsample_motion(grid, scale // at), scale
        levels.append(grid)
    return levels


def warp_states(states: Sequence[np.ndarray], motion: np.ndarray, scales: Sequence[int]) -> list[np.ndarray]:
    """states: [(1, C_l, H / s_l, W / s_l) float32] hidden states of the previous frame; motion: (H, W, 2)
    float32 backward motion of the current (padded) frame, pixels; scales: s_l as in `level_motions`.
    Returns the states sampled where each of their pixels was, same shapes, float32, contiguous."""
    out = []
    for state, level in zip(states, level_motions(motion, scales), strict=True):
        warped, _valid = reproject(state[0].transpose(1, 2, 0), level)  # planes in, planes out
        out.append(np.ascontiguousarray(warped.transpose(2, 0, 1)[None]))
    return out
