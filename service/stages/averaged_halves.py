"""Each half buffer averaged over a sequence's frames, as the cross-regression's features (`crossreg`).

Cross-regression (service/stages/cross_regression.py) fits one half's colour on the other half's features: the
colour's own differences, scaled by its 3x3 noise, and its weights (Choi 2024 eqs. 6-7), with albedo and normal.
At 1-2 samples per half the colour term is mostly noise, so the regression window weighs pixels across an edge
that no G-buffer shows (a shadow) nearly as those beside it, and the pilots blur it. Here half A and half B are
each averaged over the frames so far, reprojected by `motion` (depth and normal checked, the mask eroded 3x3 as
crossreg's history), the newest frame weighing a = max(1 / n, ALPHA_MIN) over the n frames in the average, as
the noise blend's accumulated input (service.stages.input_history). Pilot A then takes its features and weights
from averaged A and is still fitted to this frame's B, pilot B from averaged B fitted to this frame's A: the
targets stay this frame's samples, and the two pilots stay built from independent samples (averaged A holds
only A's). Where the reprojection fails the average starts again from the frame's own half.

The average is not clamped to the frame's range: clamped to each half's 5x5 range at 2 spp, the pilots' error
on `fireflies` went from 0.0318 to 0.1066 (prototype, docs/benchmarks.md). It starts again where the light
changed: where both halves of this frame, each on its own, stand beyond CHANGE times the history's (above, or
below its 1 / CHANGE) in their 3x3 means, or beyond PIXEL_CHANGE times in the pixel itself
(service/stages/light_change.py). A firefly is in one half, not both, so it does not
restart the average; a shadow that moved in does, where the history would have kept the lit floor (a moving
ball's shadow on `make bench-long`'s `shadows`: features of 1.2 where the reference is 0.13, and pilots fitted
to them). Without the test the features lag wherever the light moves.

What it gains (`make bench` and `make bench-long`, crossreg with and without `average_halves`):
docs/benchmarks.md, "Long sequences": crossreg's relL2 on the 64-frame `shadows` 0.0348 -> 0.0308, `textures`
0.0141 -> 0.0131, `fireflies` 0.0281 -> 0.0284. Cost: two cross-regressions a frame instead of one (each call
gives both pilots; one of each is kept) and this stage's numpy passes: crossreg 508 -> 623 ms a 1280x720 frame
(`python -m bench.classical_speed`, one run, OIDN-high 2732). The restart where the light changed, measured
alone (docs/benchmarks.md, "Long sequences"): 64-frame `shadows` 0.0304 -> 0.0280 (temporal error 0.0588 ->
0.0545), `fireflies` 0.0284 -> 0.0257, `textures` 0.0116 -> 0.0116; its test takes about 54 ms of a
1280x720 frame (`out/exp/s50/lc_time.py`, 2026-11-28).
"""

from __future__ import annotations

import numpy as np

from service.stages.cross_regression import CrossRegressionParams, cross_regression
from service.stages.input_history import ALPHA_MIN
from service.stages.light_change import light_changed
from service.stages.reprojection import ReprojectionParams, reproject

PLANES = 7  # half A (3), half B (3), the frames in the average (1)
# The light changed where both halves' 3x3 means differ from the history's by more than this factor, or both
# pixels by more than PIXEL_CHANGE (module docstring). Chosen on `make bench-long` from 1.5, 2 and 3 (and 3x3
# against 5x5 windows) and 4 and 8: docs/benchmarks.md, "Long sequences"
CHANGE = 1.5
PIXEL_CHANGE = 8.0


def average_halves(color_a: np.ndarray, color_b: np.ndarray, previous: np.ndarray | None, motion: np.ndarray,
                   *, depth: np.ndarray | None = None, prev_depth: np.ndarray | None = None,
                   normal: np.ndarray | None = None, prev_normal: np.ndarray | None = None,
                   params: ReprojectionParams | None = None) -> np.ndarray:
    """The halves averaged with the previous frames' (module docstring).

    color_a, color_b: (H, W, 3) float32 linear radiance of this frame's halves (less emission); previous: the
    last frame's result, (PLANES, H, W) float32, or None (a start); motion (H, W, 2) float32 backward motion,
    pixels; depth, prev_depth (H, W, 1) and normal, prev_normal (H, W, 3) float32 check the reprojection where
    given (`reprojection.reproject`, with `params`). Returns (PLANES, H, W) float32 planes: averaged A (3),
    averaged B (3) and the frames in each pixel's average (1, at least 1).
    """
    height, width = color_a.shape[:2]
    current = np.empty((PLANES, height, width), np.float32)
    current[0:3] = color_a.transpose(2, 0, 1)
    current[3:6] = color_b.transpose(2, 0, 1)
    current[6] = 1.0
    if previous is None or previous.shape != current.shape:
        return current
    warped, valid = reproject(previous.transpose(1, 2, 0), motion, depth=depth, prev_depth=prev_depth,
                              normal=normal, prev_normal=prev_normal, params=params)
    warped = warped.transpose(2, 0, 1)  # (PLANES, H, W), zero where not valid
    # where the reprojection failed the history is this frame's own (no change), so that its zeros do not enter
    # the 3x3 means of the valid pixels beside it
    valid &= ~light_changed(current[:6], np.where(valid, warped[:6], current[:6]), CHANGE, PIXEL_CHANGE)
    frames = np.where(valid, warped[6] + 1.0, 1.0).astype(np.float32)
    weight = np.maximum(1.0 / frames, np.float32(ALPHA_MIN))  # the newest frame's, 1 where not valid
    current[:6] = (1.0 - weight) * warped[:6] + weight * current[:6]
    current[6] = frames
    return current


def averaged_pilots(color_a: np.ndarray, color_b: np.ndarray, averaged: np.ndarray, albedo: np.ndarray,
                    normal: np.ndarray, params: CrossRegressionParams | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(pilot_a, pilot_b) as `cross_regression` gives them, (3, H, W) float32 log1p planes, with the features and
    weights of averaged A and averaged B (`average_halves`' planes) fitted to this frame's B and A.

    color_a, color_b: (H, W, 3) float32 this frame's halves; averaged: (PLANES, H, W) float32; albedo, normal:
    (H, W, 3) float32. Where every pixel's average holds this frame alone (a start), one cross-regression."""
    if (averaged[6] == 1.0).all():
        return cross_regression(color_a, color_b, albedo, normal, params)
    mean_a = np.ascontiguousarray(averaged[0:3].transpose(1, 2, 0))
    mean_b = np.ascontiguousarray(averaged[3:6].transpose(1, 2, 0))
    pilot_a = cross_regression(mean_a, color_b, albedo, normal, params)[0]
    pilot_b = cross_regression(color_a, mean_b, albedo, normal, params)[1]
    return pilot_a, pilot_b
