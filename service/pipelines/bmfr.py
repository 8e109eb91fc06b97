"""`bmfr`: block regression of radiance on G-buffers only (BMFR-style; the "existing regression" of
Choi et al. 2024, Figs. 2 and 4).

Stages: albedo demodulation -> G-buffer features (albedo, normal, log depth, position) -> block-wise
linear regression with flat weights (service/stages/bmfr.py) -> remodulation. Keeps geometric edges,
blurs what no G-buffer shows (shadows, caustics).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from service.frame import Frame
from service.pipelines import register
from service.pipelines.base import Pipeline, SequenceState
from service.pipelines.options import MAX_SPARSITY, MAX_WINDOW, check_sparsity, option
from service.stages.bmfr import BmfrParams, bmfr
from service.stages.outliers import FIREFLY_K
from service.stages.range_clamp import clamp_to_local_range


@dataclass(frozen=True)
class BmfrOptions:
    window: int = option(13, low=3, high=MAX_WINDOW, odd=True)  # regression window side, pixels (see BmfrParams)
    # centre pixels on every 6th row and column (see BmfrParams); at most window // 2 + 1
    sparsity: int = option(6, low=1, high=MAX_SPARSITY)
    demodulate: bool = option(True)  # regress radiance / albedo, multiply back after (Koskela 2019)
    # clamp outliers to k neighbour ranges beyond their neighbours; None: off
    firefly_k: float | None = option(FIREFLY_K, above=0, high=1e6)

    def __post_init__(self) -> None:
        check_sparsity(self.window, self.sparsity)


@register
class BmfrPipeline(Pipeline):
    name = "bmfr"
    summary = "block regression on albedo/normal/depth/position (BMFR-style); fast, keeps geometric edges only"
    requires = ("color", "albedo", "normal")
    optional = ("depth", "emission")
    Options = BmfrOptions

    def denoise(self, frame: Frame, state: SequenceState) -> tuple[dict[str, np.ndarray], SequenceState]:
        opt = self.options
        params = BmfrParams(opt.window, opt.sparsity, opt.demodulate, opt.firefly_k)
        color = bmfr(frame["color"], frame["albedo"], frame["normal"], frame.get("depth"), params)
        color = clamp_to_local_range(color, frame["color"], opt.window // 2)  # no extrapolated energy
        return {"color": color}, state
