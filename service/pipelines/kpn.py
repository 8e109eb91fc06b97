"""`kpn`: neural temporal denoising with dual motion vectors (Zeng et al. 2023): a network predicts per-pixel
kernels at three scales and a temporal kernel, trained offline, run in ONNX Runtime; the filter runs in numba.

Stages, per frame (emission already split off by Pipeline.step, added back after):
  1. input planes: demodulated log1p radiance, normal, relative depth, roughness (service/stages/rae_inputs.py),
     the radiance's isolated fireflies and outlier clusters clamped first (service.stages.outliers.clamp_outliers,
     as svgf; not in training: make bench's fireflies sequence, relL2 0.0240 -> 0.0231, temporal error 0.947
     -> 0.673; the other three unchanged), down to no less than what both halves show where the frame has
     them (a glint, not a firefly: fireflies' temporal error 0.673 -> 0.625, relL2 and the other three
     unchanged; for svgf the same raised fireflies' relL2 0.0366 -> 0.0370 and temporal error -> 0.665),
     judged on the albedo-demodulated radiance (relL2 lower by up to 0.8% on the four sequences, 2026-11-27)
  2. the previous output (log1p demodulated, the sequence state) warped to this frame by `motionDual`
     (`motion` option: auto takes it where the frame has it and the weights were trained with it, else
     `motion`), bilinear, taps outside the frame
     dropped (service.stages.reprojection.reproject without G-buffer tests); where the warp fails (off
     screen) and at a sequence's first frame, the noisy radiance of step 1 (Zeng 2023 sec. 5)
  3. the network in ONNX Runtime on planes and warped previous output (service.layout.KPN_INPUTS), padded by
     edge replication to its alignment -> 5x5 kernels at full, 1/2 and 1/4 resolution, their blending
     weights, the temporal kernel and alpha_t, as logits (models/nets/kpn.py)
  4. the multi-scale kernel filter with temporal blend, which normalises them
     (service/stages/kernel_filter.py), cropped back
  5. expm1 (demodulated radiance)
  6. optional (`history`, on by default; frames with `motion`): blended with the previous frame's output of
     this step, reprojected by `motion` and clipped to this output's local range, as `rae` does
     (service/stages/history_blend.py; beyond the paper). Step 2 still feeds the network step 4's output,
     as it was trained. History 0.2 against none, the benchmark's sequences (docs/training.md): temporal
     error 0-9% lower, relL2 as low or lower but fireflies' (0.0230 -> 0.0231); 0.4 lowered the temporal
     error further but raised relL2 on shadows and fireflies.
  7. remodulation by the albedo
The network sees zero radiance where nothing was hit (zero normal), as in `rae`; the pipeline step returns those
pixels as they came (service.stages.background). State: the previous output of step 4 (3, H, W) float32, none
at the first frame of a sequence, and step 6's.
The network and the filter were trained together through their torch twins (models/train/kpn.py);
tests/service/pipelines/test_kpn.py holds the served pipeline to them.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field

import numpy as np

from service.frame import Frame
from service.layout import KPN_INPUTS, channel_slices, pad_planes
from service.pipelines import register
from service.pipelines.base import SequenceState
from service.pipelines.networks import NetworkPipeline, frame_planes
from service.pipelines.options import MAX_THREADS, OptionError, option
from service.runtime import OnnxModel, weight_names
from service.stages.albedo import remodulate
from service.stages.history_blend import OutputHistory
from service.stages.kernel_filter import kernel_filter
from service.stages.outliers import clamp_outliers
from service.stages.rae_inputs import RADIANCE, lighting_from_output
from service.stages.reprojection import reproject

NETWORK = "kpn"  # the network a `weights` file must hold (its ONNX metadata)
DEFAULT_WEIGHTS = "kpn"  # models/weights/kpn.onnx (manifest: kpn.json)
MOTIONS = ("auto", "dual", "plain")
HISTORY = 0.2  # default weight of the previous output in step 6 (module docstring)
PREVIOUS = channel_slices(KPN_INPUTS)["previous"]  # the warped previous output among the network's input planes


@dataclass(frozen=True)
class KpnOptions:
    # network weights: a name from the registry (service.runtime.weight_files), never a path
    weights: str = option(DEFAULT_WEIGHTS, choices=functools.partial(weight_names, NETWORK))
    # which motion warps the previous output: "dual" (`motionDual`, required), "plain" (`motion`), "auto"
    # (as the weights were trained: `motionDual` where the frame has it for dual-trained weights, else `motion`)
    motion: str = option("auto", choices=MOTIONS)
    # ONNX Runtime intra-op threads (0: $MCDENOISE_ORT_THREADS or ORT's default)
    threads: int = option(0, low=0, high=MAX_THREADS)
    # weight of the previous output in step 6 (module docstring; 0: off), and the half-width of its clip window
    history: float = option(HISTORY, low=0, high=0.95)
    history_radius: int = option(1, low=1, high=8)


@dataclass
class KpnState(SequenceState):
    """previous: (3, H, W) float32 the last output of step 4, log1p demodulated radiance; None before the first
    frame. history: step 6's last output."""

    previous: np.ndarray | None = None
    history: OutputHistory = field(default_factory=OutputHistory)

    def forget(self) -> None:
        """The previous output and the output history go (a new start)."""
        super().forget()
        self.previous, self.history = None, OutputHistory()


def warp_motion(frame: Frame, mode: str, trained: str = "dual") -> np.ndarray:
    """(H, W, 2) float32: the frame's `motionDual` or `motion`. mode "dual" or "plain" says which; "auto"
    follows `trained`, the motion the weights were trained with (their metadata): `motionDual` where the
    frame has it for weights trained with it, else `motion`."""
    if mode == "dual" or (mode == "auto" and trained == "dual" and "motionDual" in frame):
        return frame["motionDual"]
    return frame["motion"]


@register
class KpnPipeline(NetworkPipeline):
    name = "kpn"
    summary = "multi-scale kernel prediction with dual motion vectors (Zeng 2023), trained offline; temporal"
    requires = ("color", "albedo", "normal", "depth", "motion")
    optional = ("motionDual", "roughness", "emission", "colorA", "colorB")
    temporal = True
    Options = KpnOptions
    network = NETWORK
    State = KpnState

    def model(self) -> OnnxModel:
        """NetworkPipeline.model, and, when it loads, OptionError on `weights` unless its coarse outputs are at
        scales 2 and 4."""
        if self._model is not None:  # checked when it loaded
            return self._model
        model = super().model()
        scales = sorted(c.get("scale") for c in model.info.metadata.get("coarse", []))
        if scales != [2, 4]:
            self._model = None
            raise OptionError(f"weights '{self.options.weights}' have coarse outputs at scales {scales}, not 2 and 4",
                              "weights")
        return model

    def check(self, frame: Frame, state: SequenceState) -> None:
        """Pipeline.check, and `motionDual` is required with motion="dual"."""
        super().check(frame, state)
        if self.options.motion == "dual":
            frame.require(("motionDual",), who=f"pipeline '{self.name}' with motion 'dual'")

    def previous(self, frame: Frame, state: KpnState, noisy: np.ndarray) -> np.ndarray:
        """(3, H, W) float32: the last output warped to `frame`, `noisy` (3, H, W) where the warp fails or
        there is no last output (module docstring, stage 2)."""
        if state.previous is None:
            return noisy
        motion = warp_motion(frame, self.options.motion, self.model().info.metadata.get("motion", "dual"))
        warped, valid = reproject(state.previous.transpose(1, 2, 0), motion)
        return np.where(valid, warped.transpose(2, 0, 1), noisy)

    def denoise(self, frame: Frame, state: SequenceState) -> tuple[dict[str, np.ndarray], SequenceState]:
        model = self.model()
        info = model.info
        # a firefly would be spread by the kernels and carried on in the history (as in svgf); what both
        # halves show is no firefly
        halves = (frame["colorA"], frame["colorB"]) if "colorA" in frame and "colorB" in frame else None
        clamped = clamp_outliers(frame["color"], halves=halves, albedo=frame.get("albedo"))
        planes = frame_planes(frame.replace(color=clamped))
        previous = self.previous(frame, state, planes[RADIANCE])
        features = np.ascontiguousarray(pad_planes(np.concatenate([planes, previous]), info.alignment))
        outputs = model.run({info.input_name: features[None]})
        coarse = {c["scale"]: outputs[c["output"]][0] for c in info.metadata["coarse"]}
        filtered = kernel_filter(features[RADIANCE], features[PREVIOUS], outputs[info.output_name][0], coarse[2],
                                 coarse[4], space_to_depth=int(info.metadata["space_to_depth"]))
        filtered = filtered[:, : frame.height, : frame.width]
        if not np.isfinite(filtered).all():  # Pipeline.step's KpnState.forget: the next frame starts afresh
            raise FloatingPointError(f"pipeline '{self.name}': the network produced non-finite kernels; "
                                     "its recurrent state was reset")
        state.previous = np.ascontiguousarray(filtered)
        lighting = lighting_from_output(filtered)
        if self.options.history:
            lighting = state.history.blend(lighting, frame, self.options.history, self.options.history_radius)
        radiance = remodulate(lighting, frame["albedo"])
        return {"color": radiance}, state
