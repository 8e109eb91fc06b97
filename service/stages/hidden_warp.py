"""Warping a recurrent network's hidden state by the frame's motion (an option of the `rae` pipeline).

A hidden state at `scale` (its height and width are the padded frame's / scale) is moved the way the image
moved: the frame's backward motion (FRAME_FORMAT.md) is averaged over scale x scale blocks and divided by
`scale`, then the state is sampled bilinearly there by service.stages.reprojection.reproject (taps outside
the frame dropped and the weights renormalised; zero where the sample point is off screen). The torch twin
that training runs through is models/nets/warp.py; a parity test holds the two together.
"""

from __future__ import annotations

import numpy as np

from service.stages.reprojection import reproject


def downsample_motion(motion: np.ndarray, scale: int) -> np.ndarray:
    """motion: (H, W, 2) float32 backward motion in pixels, H and W multiples of `scale`. Returns
    (H / scale, W / scale, 2) float32: the block means in pixels of the downsampled grid."""
    h, w = motion.shape[0] // scale, motion.shape[1] // scale
    blocks = motion.reshape(h, scale, w, scale, 2)
    return (blocks.mean(axis=(1, 3), dtype=np.float32) / np.float32(scale)).astype(np.float32)


def warp_state(state: np.ndarray, motion: np.ndarray, scale: int) -> np.ndarray:
    """state: (1, C, h, w) float32 hidden state of the previous frame; motion: (h * scale, w * scale, 2)
    float32 backward motion of the current (padded) frame. Returns (1, C, h, w) float32, contiguous."""
    level = downsample_motion(motion, scale)
    warped, _valid = reproject(state[0].transpose(1, 2, 0), level)  # planes in, planes out
    return np.ascontiguousarray(warped.transpose(2, 0, 1)[None])
