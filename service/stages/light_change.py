"""Where the light changed since the frames a history averages, as both halves of this frame say.

A history of radiance averaged over frames (reprojected by `motion`, its depth and normal checked) keeps what
the light was: where a shadow moved in, the average still holds the lit floor, and no G-buffer test sees it.
This frame's two halves are independent estimates of its light. Where both stand beyond a factor of the
history's, on the same side, the light changed; a firefly is in one half, not both, so it does not count.
Compared are the sums over the channels, as 3x3 means and per pixel, with EPS_SHARE of the frame's mean
radiance added to both sides, so that the test does not depend on the radiance's scale and dark pixels do not
restart on nothing. The mean is that of a sample at an odd stride (so that it holds both halves) of 2/3 to 2
times SCALE_SAMPLES values, every value capped at the sample's SCALE_QUANTILE quantile: one firefly of 1e10 in
a 1280x720 frame would otherwise have made eps about 10, every ratio about 1 where the radiance is about 1, and
the test blind for that frame. Used by crossreg's averaged halves (service/stages/averaged_halves.py).

Known limits: a pixel whose halves are both 0 is "darker" than any history above a few eps, so the pixel test
restarts it (a 0/1 signal hitting light half the time restarts often); more than 1 - SCALE_QUANTILE of the
frame's values huge still makes eps large, and a NaN (frames repair them on input) makes it 1e30.

Where samples are rare (a dim region hit by one sample in 20), a 3x3 window of one half holds one or two hits
or none, and both halves can stand beyond any factor by chance: the test then restarts an average that was
right. The noise blend's accumulated input (service/stages/input_history.py) does not use it for that reason:
there, at a factor of 2, it lowered `make bench` relL2 by up to 3% but left an average of a 0/1 signal at a
chance of 0.05 a sample no better than half the frame's own error (docs/benchmarks.md, "Accumulated input").
"""

from __future__ import annotations

import numpy as np

from service.stages.svgf import box_mean

EPS_SHARE = 1e-3  # of the frame's mean radiance (a half, summed over channels), added before the ratios
SCALE_QUANTILE = 0.999  # ... the mean taken with every value capped at this quantile
SCALE_SAMPLES = 65536  # ... of a strided sample of 2/3 to 2 times this many values


def light_changed(halves: np.ndarray, history: np.ndarray, change: float, pixel_change: float) -> np.ndarray:
    """(H, W) bool: where both halves of this frame disagree with the history in the same direction: both halves'
    3x3 means beyond `change` times the history's, above or below, or both pixels beyond `pixel_change` times
    (inf: no pixel test). halves, history: (6, H, W) float32 linear radiance planes, half A (3) then half B (3):
    this frame's and the reprojected average, whose pixels all count (where the reprojection failed, pass this
    frame's halves: a 3x3 mean reads its neighbours); an average of both halves may stand twice. Radiance may be
    negative (a light's edge less its emission): a sum below 0 counts as 0. change, pixel_change: factors > 1.
    """
    changed = np.zeros(halves.shape[1:], bool)
    # radiance near float32's largest sums to inf, and inf / inf is nan, which compares false: no change is seen
    # there (the reprojection's own tests still apply)
    with np.errstate(over="ignore", invalid="ignore"):
        current = np.maximum(np.stack([halves[0:3].sum(0), halves[3:6].sum(0)], axis=-1), 0)  # (H, W, 2): A, B
        previous = np.maximum(np.stack([history[0:3].sum(0), history[3:6].sum(0)], axis=-1), 0)
        mean = robust_mean(current)
        eps = np.float32(min(max(EPS_SHARE * mean, 1e-30), 1e30)) if np.isfinite(mean) else np.float32(1e30)
        for radius, factor in ((1, change), (0, pixel_change)):  # both sides of each ratio at least eps > 0
            now, before = (box_mean(v, radius) if radius else v for v in (current, previous))
            ratio = (now + eps) / (before + eps)
            brighter, darker = ratio > factor, ratio < 1.0 / factor
            changed |= (brighter[..., 0] & brighter[..., 1]) | (darker[..., 0] & darker[..., 1])
    return changed


def robust_mean(values: np.ndarray) -> float:
    """The mean of a sample at an odd stride of 2/3 to 2 times SCALE_SAMPLES of `values` (all of them below 2
    SCALE_SAMPLES; any shape, at least one value, float32 >= 0, possibly inf), every value capped at the
    sample's SCALE_QUANTILE quantile (module docstring): a scale, read once, not a full pass over the frame. inf
    where more than the quantile's share are inf; float64."""
    flat = values.reshape(-1)
    sample = flat[:: max(1, flat.size // SCALE_SAMPLES) | 1]  # odd: interleaved halves both in the sample
    k = int(SCALE_QUANTILE * (sample.size - 1))
    cap = np.partition(sample, k)[k]
    return float(np.minimum(sample, cap).mean(dtype=np.float64))
