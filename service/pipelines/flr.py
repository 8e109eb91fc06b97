"""`flr`: fast local regression (Salmi et al.): per-pixel Gaussian-weighted least squares of radiance on
G-buffer guides, from downsampled and blurred outer-product tensors.

Stages: guides: normal and log depth, those present, and ao with the `ao` option (service/stages/flr.py) ->
local linear regression (of radiance demodulated by albedo when present, remodulated after) -> clamp to the
local range of the noisy input. A FLNR pipeline feeds learned guides to the same `local_linear_regression`.

Salmi et al. found ambient occlusion a valuable guide; here it is off by default. Our renderer's `ao` (64
cosine rays of length 0.5 a pixel) made FLR worse on all four `make bench` sequences (trimmed relL2 with it
-> without: shadows 0.0339 -> 0.0311, disocclusion 0.00423 -> 0.00412, fireflies 0.0366 -> 0.0357, textures
0.0136 -> 0.0135) and on 10 of the 11 held-out `data/val` sequences (geometric mean 0.95x; 1.02x on
veiled_light), 2026-11-28. Each guide is one more slope per channel for the window to fit.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from service.frame import Frame
from service.pipelines import register
from service.pipelines.base import Pipeline, SequenceState
from service.pipelines.options import option
from service.stages.flr import FlrParams, gbuffer_guides, local_linear_regression
from service.stages.outliers import FIREFLY_K
from service.stages.range_clamp import clamp_to_local_range


@dataclass(frozen=True)
class FlrOptions:
    scale: int = option(4, low=1, high=16)  # downsampling factor of the outer-product tensors, pixels
    # Gaussian std on the downsampled grid, cells; the blur reaches 3 sigma, so 8 spans 24 cells (384 px at scale 16)
    sigma: float = option(0.5, above=0, high=8)
    demodulate: bool = option(True)  # regress radiance / albedo when albedo is present, multiply back after
    # clamp outliers to k neighbour ranges beyond their neighbours; None: off
    firefly_k: float | None = option(FIREFLY_K, above=0, high=1e6)
    ao: bool = option(False)  # the `ao` layer as one more guide when present (module docstring: off is better here)


@register
class FlrPipeline(Pipeline):
    name = "flr"
    summary = "fast local regression on normal/depth guides (Salmi et al.); very fast, smooth lighting"
    requires = ("color", "normal")
    optional = ("depth", "ao", "albedo", "emission")
    Options = FlrOptions

    def denoise(self, frame: Frame, state: SequenceState) -> tuple[dict[str, np.ndarray], SequenceState]:
        opt = self.options
        params = FlrParams(scale=opt.scale, sigma=opt.sigma, firefly_k=opt.firefly_k)
        albedo = frame.get("albedo") if opt.demodulate else None
        guides = gbuffer_guides(frame["normal"], frame.get("depth"), frame.get("ao") if opt.ao else None)
        color = local_linear_regression(frame["color"], guides, params, albedo=albedo)
        # No extrapolated energy: the fit's support is about two cells of `scale` pixels each way.
        color = clamp_to_local_range(color, frame["color"], 2 * opt.scale)
        return {"color": color}, state
