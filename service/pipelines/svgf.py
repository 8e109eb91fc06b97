"""`svgf`: spatiotemporal variance-guided filtering (Schied et al. 2017).

Stages, top to bottom: outlier clamp, judged on the colour as filtered (service/stages/outliers.py) ->
albedo demodulation -> reprojection of the history (colour, moments, history length) by motion with
depth/normal validity -> history clamp to the current frame's local colour box (extension) -> temporal
accumulation of colour and luminance moments -> variance estimate (spatial for short histories, no more
than the half buffers' own where the frame has them) -> 5 edge-aware a-trous passes -> remodulation.
The colour after the first a-trous pass becomes the next frame's colour history (Schied sec. 4.3).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from service.frame import Frame
from service.pipelines import register
from service.pipelines.base import Pipeline, SequenceState
from service.pipelines.options import option
from service.stages.albedo import demodulate, remodulate
from service.stages.atrous import AtrousParams, atrous, edge_guides
from service.stages.outliers import clamp_outliers
from service.stages.range_clamp import clamp_to_local_range
from service.stages.reprojection import ReprojectionParams, reproject
from service.stages.svgf import (
    ALPHA_COLOR,
    ALPHA_MOMENTS,
    TemporalParams,
    accumulate,
    clamp_history,
    estimate_variance,
    halves_variance,
    luminance_moments,
)


@dataclass(frozen=True)
class SvgfOptions:
    # Schied sec. 4.1: weight of the new frame in the colour history
    alpha_color: float = option(ALPHA_COLOR, above=0, high=1)
    # Schied sec. 4.2: weight of the new frame in the moments
    alpha_moments: float = option(ALPHA_MOMENTS, above=0, high=1)
    iterations: int = option(5, low=0, high=8)  # a-trous passes (Schied sec. 4.3); pass k steps 2^k px, 8: 128 px
    sigma_depth: float = option(1.0, above=0, high=1e6)  # sigma_z (Schied eq. 3)
    sigma_normal: float = option(128.0, above=0, high=1e4)  # sigma_n (Schied eq. 4), an exponent of a cosine
    sigma_luminance: float = option(4.0, above=0, high=1e6)  # sigma_l (Schied eq. 5)
    depth_tolerance: float = option(0.1, above=0, high=1e3)  # reprojection: max relative depth change of a history tap
    normal_cos_min: float = option(0.9, low=-1, high=1)  # reprojection: min cosine between current and history normal
    demodulate: bool = option(True)  # filter radiance / albedo when albedo is present (Schied sec. 4)
    # history clamp to local mean +- this * std (extension); None: off
    clamp_spread: float | None = option(1.0, low=0, high=1e3)


# Radiance above this is scaled down before filtering so that squared luminance moments stay finite in
# float32 (max 3.4e38): (1e15)^2 = 1e30 leaves room for sums over windows and histories.
SAFE_RADIANCE = 1e15
# Output is clipped to the noisy input's range within this many pixels (service/stages/range_clamp.py):
# demodulating by a near-black albedo magnifies irradiance ~1/ALBEDO_EPS, and the wide a-trous footprint
# would carry it onto brighter-albedo neighbours as energy the input cannot explain.
CLAMP_RADIUS = 8


@dataclass
class SvgfState(SequenceState):
    """History of the previous frame: (H, W, 6) float32 colour (3, after the first a-trous pass),
    moments (2) and history length (1); its depth (H, W, 1) and normal (H, W, 3); None before frame 1.
    The history is stored divided by `scale` (>= 1, see SAFE_RADIANCE)."""

    history: np.ndarray | None = None
    depth: np.ndarray | None = None
    normal: np.ndarray | None = None
    scale: float = 1.0

    def forget(self) -> None:
        """The history and its depth, normal and scale go (a new start)."""
        super().forget()
        self.history = self.depth = self.normal = None
        self.scale = 1.0


@register
class SvgfPipeline(Pipeline):
    name = "svgf"
    summary = "SVGF (Schied 2017): temporal accumulation with reprojection + variance-guided a-trous; fast, temporal"
    requires = ("color", "normal", "depth", "motion")
    optional = ("albedo", "emission", "colorA", "colorB")
    temporal = True
    Options = SvgfOptions

    def __init__(self, **options):
        super().__init__(**options)
        opt = self.options
        self.temporal_params = TemporalParams(
            opt.alpha_color, opt.alpha_moments, sigma_normal=opt.sigma_normal, sigma_depth=opt.sigma_depth,
            clamp_spread=opt.clamp_spread,
        )
        self.atrous_params = AtrousParams(opt.iterations, opt.sigma_depth, opt.sigma_normal, opt.sigma_luminance)
        self.reprojection_params = ReprojectionParams(opt.depth_tolerance, opt.normal_cos_min)

    def new_state(self, height: int, width: int) -> SvgfState:
        return SvgfState(height, width)

    def denoise(self, frame: Frame, state: SvgfState) -> tuple[dict[str, np.ndarray], SvgfState]:
        albedo = frame.get("albedo") if self.options.demodulate else None
        # a firefly would enter the history and every a-trous pass; judged on the colour as filtered
        color = clamp_outliers(frame["color"], albedo=albedo)
        color = color if albedo is None else demodulate(color, albedo)
        scale = max(1.0, float(np.abs(color).max()) / SAFE_RADIANCE)
        color = color / np.float32(scale)
        halves = None
        if "colorA" in frame and "colorB" in frame:
            def halves(box: tuple[slice, slice]) -> np.ndarray:  # over `box`, in the filtered colour's units
                a, b = (frame[k][box] if albedo is None else demodulate(frame[k][box], albedo[box])
                        for k in ("colorA", "colorB"))
                with np.errstate(over="ignore"):  # a half far above the full estimate's range: inf, never chosen
                    return halves_variance(a / np.float32(scale), b / np.float32(scale))
        depth, normal = frame["depth"], frame["normal"]
        guides = edge_guides(depth, normal)
        moments = luminance_moments(color)
        if state.history is None:
            prev = np.zeros((frame.height, frame.width, 6), np.float32)
            valid = np.zeros((frame.height, frame.width), bool)
        else:
            prev, valid = reproject(
                state.history, frame["motion"], depth=depth, prev_depth=state.depth, normal=normal,
                prev_normal=state.normal, params=self.reprojection_params,
            )
            ratio = state.scale / scale  # history units -> this frame's units, clipped to the safe range
            with np.errstate(over="ignore"):
                prev[..., :4] = np.clip(prev[..., :4] * np.float32(ratio), -SAFE_RADIANCE, SAFE_RADIANCE)
                prev[..., 4] = np.minimum(prev[..., 4] * np.float32(ratio * ratio), SAFE_RADIANCE**2)
        prev_color, prev_moments = prev[..., :3], prev[..., 3:5]
        if self.temporal_params.clamp_spread is not None:
            prev_color, prev_moments = clamp_history(
                prev_color, prev_moments, color, self.temporal_params.clamp_radius, self.temporal_params.clamp_spread
            )
        accumulated, moments_acc, history = accumulate(
            color, moments, prev_color, prev_moments, prev[..., 5], valid, self.temporal_params
        )
        variance = estimate_variance(moments_acc, moments, history, color, guides, self.temporal_params, halves)
        filtered, _, first = atrous(accumulated, variance, guides, self.atrous_params)
        state.history = np.concatenate([first, moments_acc, history[..., None]], axis=-1)
        state.depth, state.normal, state.scale = depth, normal, scale
        filtered = filtered * np.float32(scale)
        out = filtered if albedo is None else remodulate(filtered, albedo)
        return {"color": clamp_to_local_range(out, frame["color"], CLAMP_RADIUS)}, state
