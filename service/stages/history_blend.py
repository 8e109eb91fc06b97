"""A denoised frame blended with the previous one, reprojected and clipped, as temporal anti-aliasing does.

    out = (1 - w) * current + w * clip(reproject(previous), local range of current)

where reprojection by the frame's backward `motion` holds (service/stages/reprojection.py: depth and normal
checked), and `current` elsewhere. Clipping the history to the range of the current output over a
(2 radius + 1)^2 window keeps what reprojection brought but the current frame does not show (a moved
shadow, a disoccluded edge) out of the result, so the blend only steadies values the current output already
allows: it lowers flicker, not detail. Every output lies within that local range of `current`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from service.frame import Frame
from service.stages.range_clamp import clamp_to_local_range
from service.stages.reprojection import reproject


def blend_history(current: np.ndarray, previous: np.ndarray, motion: np.ndarray, depth: np.ndarray,
                  prev_depth: np.ndarray, normal: np.ndarray, prev_normal: np.ndarray, weight: float,
                  radius: int) -> np.ndarray:
    """current, previous: (H, W, C) float32 this frame's and the previous frame's outputs (any linear
    quantity; the previous one as this function returned it); motion: (H, W, 2) float32 backward motion in
    pixels; depth, prev_depth: (H, W, 1) float32 camera distance; normal, prev_normal: (H, W, 3) float32 unit
    normals (zero: nothing hit); weight in [0, 1): the history's share; radius >= 1: the clip window's
    half-width, pixels. Returns (H, W, C) float32."""
    prev, valid = reproject(previous, motion, depth=depth, prev_depth=prev_depth, normal=normal,
                            prev_normal=prev_normal)
    prev = clamp_to_local_range(prev, current, radius)
    w = np.float32(weight)
    return np.where(valid[..., None], (1 - w) * current + w * prev, current)


@dataclass
class OutputHistory:
    """What `blend_history` needs of the previous frame, kept in a pipeline's sequence state: its output
    (H, W, 3) float32, depth (H, W, 1) and normal (H, W, 3); None before the first frame and after a frame
    without `motion`."""

    previous: np.ndarray | None = None
    depth: np.ndarray | None = None
    normal: np.ndarray | None = None

    def blend(self, current: np.ndarray, frame: Frame, weight: float, radius: int) -> np.ndarray:
        """`current` (H, W, 3) float32 blended with the kept output (`blend_history`), which it replaces. A
        frame without `motion` is not blended and starts the history afresh (an absent motion is not a still
        camera); `frame` needs depth and normal."""
        if "motion" not in frame:
            self.previous = self.depth = self.normal = None
            return current
        depth, normal = frame["depth"], frame["normal"]
        if self.previous is not None:
            current = blend_history(current, self.previous, frame["motion"], depth, self.depth, normal,
                                    self.normal, weight, radius)
        self.previous, self.depth, self.normal = current, depth, normal
        return current
