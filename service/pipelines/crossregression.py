"""`crossregression`: cross-regression alone (Choi et al. 2024, the ablation of their Fig. 8).

Stages: cross-regression of the two half buffers in log space (service/stages/cross_regression.py)
-> the two pilot estimates back to linear radiance -> their mean -> clipped to the noisy frame's range
over the regression window (the last three in one pass, `cross_regression_radiance`). No network, no
temporal filter: the input that the online denoiser (`crossreg`) refines, useful on its own as a fast,
detail-preserving spatial filter for frames that carry colorA/colorB.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from service.frame import Frame
from service.pipelines import register
from service.pipelines.base import Pipeline, SequenceState
from service.pipelines.options import MAX_SPARSITY, MAX_WINDOW, check_sparsity, option
from service.stages.cross_regression import CrossRegressionParams, cross_regression_radiance
from service.stages.outliers import FIREFLY_K


@dataclass(frozen=True)
class CrossRegressionOptions:
    # window: a speed/smoothing trade-off (docs/benchmarks.md, "crossregression's window"). 15, not the paper's
    # 17 (which the crossreg network's pilots keep): relL2 2-5% lower on make bench's four sequences and 2.9%
    # lower (geometric mean) on the 11 held-out data/val sequences, every hard case passing.
    window: int = option(15, low=3, high=MAX_WINDOW, odd=True)  # regression window side, pixels (Choi 2024 sec. 3)
    # centre pixels on every 4th row and column (Choi 2024 sec. 3); at most window // 2 + 1
    sparsity: int = option(4, low=1, high=MAX_SPARSITY)
    # clamp each buffer's outliers (outliers.clamp_fireflies); None: off
    firefly_k: float | None = option(FIREFLY_K, above=0, high=1e6)

    def __post_init__(self) -> None:
        check_sparsity(self.window, self.sparsity)


@register
class CrossRegressionPipeline(Pipeline):
    name = "crossregression"
    summary = "cross-regression of the half buffers alone (Choi 2024 Fig. 8 ablation); keeps non-geometric edges"
    requires = ("colorA", "colorB", "albedo", "normal")
    optional = ("emission",)
    Options = CrossRegressionOptions

    def denoise(self, frame: Frame, state: SequenceState) -> tuple[dict[str, np.ndarray], SequenceState]:
        opt = self.options
        params = CrossRegressionParams(opt.window, opt.sparsity, opt.firefly_k)
        # the pilots' mean in linear radiance, clipped to the noisy range over the window (no extrapolated energy)
        color = cross_regression_radiance(
            frame["colorA"], frame["colorB"], frame["albedo"], frame["normal"], frame["color"], params
        )
        return {"color": color}, state
