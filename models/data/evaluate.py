"""Measure a rendered sequence folder: noise of the input and how well its motion vectors warp.

Warp error of frame t: relL2 (service.metrics) of frame t-1's reference warped by frame t's motion
(bilinear, service.stages.reprojection.reproject) against frame t's reference, over the pixels whose lookup falls
inside the image, and separately over the disoccluded pixels (where motionDual differs from motion).
The unwarped previous reference gives the baseline. Warp errors drop the highest 0.1% of per-pixel
errors (TRIM_FRACTION, as the trimmed relL2): bilinear warping smears sub-pixel emitters (a 1e3-bright
bulb) onto their neighbours, and those few pixels would otherwise decide the mean. Reads only EXR
files (no mitsuba).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from service.exr import list_sequence, read_frame, read_metadata
from service.metrics import TRIM_FRACTION, rel_l2, rel_l2_map, trimmed_mean
from service.stages.reprojection import reproject

DUAL_DIFFERS_PX = 1e-3  # motionDual and motion differ at a pixel when they are this far apart, pixels


def _masked(image: np.ndarray, reference: np.ndarray, mask: np.ndarray, trim: float) -> float:
    """Mean relL2 over `mask` (H, W) bool, the highest `trim` fraction of pixel errors dropped; NaN if empty."""
    return trimmed_mean(rel_l2_map(image, reference)[mask], trim)


def warp_errors(prev_reference: np.ndarray, reference: np.ndarray, motion: np.ndarray,
                dual: np.ndarray, *, trim: float = TRIM_FRACTION) -> dict[str, float]:
    """Warp errors of one frame pair.

    prev_reference, reference: (H, W, 3) float32 linear radiance of frames t-1 and t; motion, dual:
    (H, W, 2) float32 backward motion of frame t, pixels. Returns relL2 over in-image pixels for no
    warp / motion / motionDual (`static`, `motion`, `dual`), the same over disoccluded pixels
    (`*_disoccluded`), each without the highest `trim` fraction of pixel errors, and the disoccluded
    fraction of the frame.
    """
    warped_m, inside_m = reproject(prev_reference, motion)
    warped_d, inside_d = reproject(prev_reference, dual)
    inside = inside_m & inside_d
    disoccluded = inside & (np.linalg.norm(dual - motion, axis=-1) > DUAL_DIFFERS_PX)
    out = {"disoccluded_fraction": float(disoccluded.mean())}
    for name, image in (("static", prev_reference), ("motion", warped_m), ("dual", warped_d)):
        out[name] = _masked(image, reference, inside, trim)
        out[f"{name}_disoccluded"] = _masked(image, reference, disoccluded, trim)
    return out


def sequence_report(folder: str | Path) -> dict[str, float]:
    """Mean over frames of: noisy-input relL2 (full and 0.1% trimmed) against the reference, and the
    warp errors of `warp_errors` (frames 1..N-1); plus render seconds per frame from sequence.json."""
    noisy, noisy_trim, pairs = [], [], []
    previous = None
    for path in list_sequence(folder):
        frame = read_frame(path)
        ref = frame["reference"]
        noisy.append(rel_l2(frame["color"], ref))
        noisy_trim.append(rel_l2(frame["color"], ref, trim=TRIM_FRACTION))
        if previous is not None:
            pairs.append(warp_errors(previous, ref, frame["motion"], frame["motionDual"]))
        previous = ref
    report = {"noisy_rel_l2": float(np.mean(noisy)), "noisy_rel_l2_trimmed": float(np.mean(noisy_trim))}
    for key in pairs[0] if pairs else ():
        values = [p[key] for p in pairs if np.isfinite(p[key])]
        report[key] = float(np.mean(values)) if values else float("nan")
    meta = read_metadata(folder) or {}
    if "seconds_per_frame" in meta:
        report["seconds_per_frame"] = float(np.mean(meta["seconds_per_frame"]))
    return report
