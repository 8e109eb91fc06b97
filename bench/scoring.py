"""Per-frame and per-sequence scores of one method's outputs against the reference.

The metrics themselves live in service/metrics.py (one definition for the demo, training and the
benchmark); this module only decides which frames and pixels each one sees and how frames add up:

- relL2: `rel_l2` with the 0.1% trim, mean over frames.
- 1-SSIM (`dssim`) and FLIP (`flip_error`): mean over frames.
- temporal: `temporal_rel_l2` of consecutive outputs against consecutive references, mean over frames
  1..N-1 (it needs a previous frame).
- worst tile: the hard cases' criterion 2 (`bench.hard_cases.tile_ratios`), per frame the largest ratio over
  16x16 tiles of the output's mean untrimmed relL2 to the noisy input's (each plus a floor of 1e-3), the
  largest over frames; above 1 + TILE_SLACK (1.1) a tile came out worse than the input. Also the number of
  (frame, tile) pairs above it.
- disoccluded relL2: untrimmed relL2 over the disoccluded pixels (surfaces not visible in the previous
  frame), pooled over frames 1..N-1: where the reprojection stage marks a pixel invalid (`~valid` of
  service.stages.reprojection.reproject), or, in a frame with `motionDual`, where it differs from `motion`
  by more than 0.5 px (`dual_occluded`: the pixel was hidden behind a moving occluder, which the
  reprojection's depth and normal tests can miss when the background matches). That is where a temporal
  pipeline has no history to lean on, and where history warped by `motion` ghosts (Zeng et al. 2023).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from bench.hard_cases import TILE_SLACK, tile_ratios, worst_tile
from service.frame import Frame
from service.metrics import TRIM_FRACTION, dssim, flip_error, rel_l2_map, temporal_rel_l2, trimmed_mean
from service.stages.reprojection import dual_occluded, reproject


def disoccluded_mask(frame: Frame, prev: Frame) -> np.ndarray | None:
    """(H, W) bool: pixels of `frame` whose surface was not visible in `prev`: reprojection by `motion`
    fails (the reprojection stage with every G-buffer both frames have) or, where the frame has
    `motionDual`, it differs from `motion` by more than DUAL_OCCLUSION_PX. None when the frame has no
    `motion` layer.
    """
    if "motion" not in frame:
        return None
    _, valid = reproject(
        prev["color"],
        frame["motion"],
        depth=frame.get("depth"),
        prev_depth=prev.get("depth"),
        normal=frame.get("normal"),
        prev_normal=prev.get("normal"),
    )
    mask = ~np.asarray(valid, bool)
    if "motionDual" in frame:
        mask |= dual_occluded(frame["motion"], frame["motionDual"])
    return mask


@dataclass
class FrameScore:
    """Scores of one output frame; None where a metric was not computed or does not apply."""

    rel_l2: float
    dssim: float | None  # None only in hand-built scores; score_frame always computes it
    flip: float | None
    temporal: float | None  # None on the first frame
    disoccluded_sum: float | None  # sum of per-pixel relL2 over disoccluded pixels
    disoccluded_pixels: int  # how many pixels were disoccluded
    worst_tile_ratio: float | None = None  # largest tile ratio to the noisy input's (None: no noisy input given)
    worst_tile: tuple[int, int] | None = None  # (row, column) of that tile's top-left pixel
    failing_tiles: int = 0  # tiles above 1 + TILE_SLACK times the noisy input's error

    def as_dict(self) -> dict[str, Any]:
        return {
            "rel_l2": self.rel_l2,
            "dssim": self.dssim,
            "flip": self.flip,
            "temporal": self.temporal,
            "disoccluded_rel_l2": (
                None if not self.disoccluded_pixels or self.disoccluded_sum is None
                else self.disoccluded_sum / self.disoccluded_pixels
            ),
            "disoccluded_pixels": self.disoccluded_pixels,
            "worst_tile_ratio": self.worst_tile_ratio,
            "worst_tile": None if self.worst_tile is None else list(self.worst_tile),
            "failing_tiles": self.failing_tiles,
        }


def score_frame(
    image: np.ndarray,
    reference: np.ndarray,
    prev: tuple[np.ndarray, np.ndarray] | None,
    mask: np.ndarray | None,
    *,
    flip: bool = True,
    noisy: np.ndarray | None = None,
) -> FrameScore:
    """Scores of `image` against `reference`.

    image, reference: (H, W, 3) float32 linear radiance. prev: (previous output, previous reference)
    or None on the first frame. mask: (H, W) bool disoccluded pixels or None. flip: whether to compute
    FLIP (the slowest metric). noisy: the frame's (H, W, 3) float32 noisy input, for the worst tile, or None.
    """
    temporal = None if prev is None else float(temporal_rel_l2(prev[0], image, prev[1], reference))
    errors = rel_l2_map(image, reference)
    dis_sum, dis_count = None, 0
    if mask is not None:
        dis_count = int(mask.sum())
        dis_sum = float(errors[mask].sum()) if dis_count else 0.0
    ratio, at, failing = None, None, 0
    if noisy is not None:
        ratios = tile_ratios(errors, rel_l2_map(noisy, reference))
        ratio, at = worst_tile(ratios)
        failing = int(np.count_nonzero(ratios > 1.0 + TILE_SLACK))
    return FrameScore(
        rel_l2=trimmed_mean(errors, TRIM_FRACTION),
        dssim=float(dssim(image, reference)),
        flip=float(flip_error(image, reference)) if flip else None,
        temporal=temporal,
        disoccluded_sum=dis_sum,
        disoccluded_pixels=dis_count,
        worst_tile_ratio=ratio,
        worst_tile=at,
        failing_tiles=failing,
    )


def _mean(values: list[float | None]) -> float | None:
    kept = [v for v in values if v is not None]
    return float(np.mean(kept)) if kept else None


@dataclass
class SequenceScore:
    """Per-frame scores and timings of one method on one sequence, and their summaries."""

    frames: list[FrameScore] = field(default_factory=list)
    ms: list[float] = field(default_factory=list)  # pipeline.step wall time per frame, milliseconds

    def summary(self, megapixels: float) -> dict[str, Any]:
        dis_frames = [f for f in self.frames if f.disoccluded_sum is not None]
        dis_pixels = sum(f.disoccluded_pixels for f in dis_frames)
        ms = float(np.median(self.ms)) if self.ms else None
        return {
            "ms_per_frame": ms,
            "ms_per_megapixel": None if ms is None else ms / megapixels,
            "ms_mean": float(np.mean(self.ms)) if self.ms else None,
            "rel_l2": _mean([f.rel_l2 for f in self.frames]),
            "dssim": _mean([f.dssim for f in self.frames]),
            "flip": _mean([f.flip for f in self.frames]),
            "temporal": _mean([f.temporal for f in self.frames]),
            "disoccluded_rel_l2": (
                sum(f.disoccluded_sum for f in dis_frames) / dis_pixels if dis_pixels else None
            ),
            "disoccluded_fraction": (
                dis_pixels / (len(dis_frames) * megapixels * 1e6) if dis_frames else None
            ),
            **self.tiles(),
        }

    def tiles(self) -> dict[str, Any]:
        """worst_tile: the largest frame's worst tile ratio (None without them), worst_tile_at: "frame i (row,
        column)" of it, failing_tiles: (frame, tile) pairs above 1 + TILE_SLACK, summed over frames."""
        scored = [(f.worst_tile_ratio, i, f.worst_tile) for i, f in enumerate(self.frames)
                  if f.worst_tile_ratio is not None]
        if not scored:
            return {"worst_tile": None, "worst_tile_at": None, "failing_tiles": None}
        ratio, index, (row, column) = max(scored, key=lambda s: s[0])
        return {"worst_tile": ratio, "worst_tile_at": f"frame {index} ({row}, {column})",
                "failing_tiles": sum(f.failing_tiles for f in self.frames)}
