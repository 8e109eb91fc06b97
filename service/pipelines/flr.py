"""`flr`: fast local regression (Salmi et al.): per-pixel Gaussian-weighted least squares of radiance on
G-buffer guides, from downsampled and blurred outer-product tensors.

Stages: guides: normal, log depth, ao, those present (service/stages/flr.py) -> local linear regression
(of radiance demodulated by albedo when present, remodulated after) -> clamp to the local range of the
noisy input. A FLNR pipeline feeds learned guides to the same `local_linear_regression`.
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


@register
class FlrPipeline(Pipeline):
    name = "flr"
    summary = "fast local regression on normal/depth/ao guides (Salmi et al.); very fast, smooth lighting"
    requires = ("color", "normal")
    optional = ("depth", "ao", "albedo", "emission")
    Options = FlrOptions

    def denoise(self, frame: Frame, state: SequenceState) -> tuple[dict[str, np.ndarray], SequenceState]:
        opt = self.options
        params = FlrParams(scale=opt.scale, sigma=opt.sigma, firefly_k=opt.firefly_k)
        albedo = frame.get("albedo") if opt.demodulate else None
        guides = gbuffer_guides(frame["normal"], frame.get("depth"), frame.get("ao"))
        color = local_linear_regression(frame["color"], guides, params, albedo=albedo)
        # No extrapolated energy: the fit's support is about two cells of `scale` pixels each way.
        color = clamp_to_local_range(color, frame["color"], 2 * opt.scale)
        return {"color": color}, state
