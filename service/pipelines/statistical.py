"""`statistical`: the statistical denoiser of Sakai et al. 2024 (Algorithm 2).

Stages, top to bottom: sample statistics -> per-pixel estimates (Curto-corrected Box-Cox means and
their variances) -> guide features (eq. 16) -> joint bilateral filter gated by the Welch t-test, of
the colour with its outliers clamped (service/stages/outliers.py: a firefly has a huge variance, so the
test cannot reject it, and the average would spread it over the window).
Keeps edges that no G-buffer shows (shadows, caustics) when the statistics resolve them, and converges
to its input as the variance goes to zero. No training, no history. Renderers that hand samples
instead of the statistics layers compute them with `service.stages.sample_statistics`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from service.frame import Frame
from service.pipelines import register
from service.pipelines.base import Pipeline, SequenceState
from service.pipelines.options import MAX_RADIUS, MAX_SIGMA2, MIN_SIGMA2, option
from service.stages.bilateral import BilateralParams, guide_features
from service.stages.outliers import clamp_outliers
from service.stages.statistical import ALPHA, PAPER_BASE, StatisticalParams, pixel_estimates, statistical_filter


@dataclass(frozen=True)
class StatisticalOptions:
    # window half-size, pixels: 20 as in Sakai sec. 6; 6 is the fast setting
    radius: int = option(PAPER_BASE.radius, low=0, high=MAX_RADIUS)
    # pixels^2 (Sakai eq. 16)
    sigma2_position: float = option(PAPER_BASE.sigma2_position, low=MIN_SIGMA2, high=MAX_SIGMA2)
    sigma2_albedo: float = option(PAPER_BASE.sigma2_albedo, low=MIN_SIGMA2, high=MAX_SIGMA2)  # albedo^2 (Sakai eq. 16)
    # normal components^2 (eq. 16)
    sigma2_normal: float = option(PAPER_BASE.sigma2_normal, low=MIN_SIGMA2, high=MAX_SIGMA2)
    # (log depth)^2; None: depth unused, as in the paper
    sigma2_log_depth: float | None = option(None, low=MIN_SIGMA2, high=MAX_SIGMA2)
    # significance level of the Welch test (Sakai sec. 4.2); below 1e-12 its quantile's 1 - alpha / 2 rounds to 1
    alpha: float = option(ALPHA, low=1e-12, below=1)
    symmetric: bool = option(True)  # eq. 12 weights (energy preserving); False: eq. 14 (asymmetric)
    skew_correction: bool = option(True)  # Curto 2023 correction of the means by the third moment


@register
class StatisticalPipeline(Pipeline):
    name = "statistical"
    summary = (
        "Sakai 2024 statistical filter: joint bilateral gated by Welch t-tests on per-pixel sample statistics; "
        "keeps shadows no G-buffer shows; option radius=6 is the fast setting"
    )
    requires = ("color", "sampleCount", "bcMean", "bcM2", "bcM3")
    optional = ("albedo", "normal", "depth", "emission")
    Options = StatisticalOptions

    def __init__(self, **options):
        super().__init__(**options)
        opt = self.options
        self.params = StatisticalParams(
            base=BilateralParams(
                opt.radius, opt.sigma2_position, opt.sigma2_albedo, opt.sigma2_normal, opt.sigma2_log_depth
            ),
            alpha=opt.alpha,
            symmetric=opt.symmetric,
            skew_correction=opt.skew_correction,
        )

    def denoise(self, frame: Frame, state: SequenceState) -> tuple[dict[str, np.ndarray], SequenceState]:
        params = self.params
        estimates = pixel_estimates(
            frame["sampleCount"], frame["bcMean"], frame["bcM2"], frame["bcM3"],
            skew_correction=params.skew_correction,
        )
        features = guide_features(
            params.base, frame.height, frame.width, frame.get("albedo"), frame.get("normal"), frame.get("depth")
        )
        # the t-test admits a firefly (its variance is huge): clip it first, judged on the demodulated colour
        color = clamp_outliers(frame["color"], albedo=frame.get("albedo"))
        return {"color": statistical_filter(color, features, estimates, params)}, state
