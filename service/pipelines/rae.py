"""`rae`: the recurrent denoising autoencoder (Chaitanya et al. 2017), trained offline, run in ONNX Runtime.

Stages, per frame (emission already split off by Pipeline.step, added back after):
  1. input planes: demodulated log1p radiance, normal, relative depth, roughness (service/stages/rae_inputs.py),
     padded by edge replication to the network's alignment; the radiance's outliers clamped first as kpn's
     (service.stages.outliers.clamp_outliers on the demodulated radiance, down to no less than what both
     halves show; not in training): a firefly would enter the hidden state. make bench's four sequences,
     2026-11-27: relL2 lower by 0.3-1.5%, temporal error unchanged to 0.1%
  2. optional (`warp`): each level's hidden state moved by the frame's motion (service/stages/hidden_warp.py);
     a frame without `motion` starts the recurrence again (zero states), as the paper's first frame: an
     absent motion is not a still camera, and a state left where it was would ghost
  3. the network in ONNX Runtime: (features, hidden states) -> (log1p demodulated radiance, next hidden states)
  4. expm1 (demodulated radiance), cropped back to the frame
  5. optional (`history`, on by default; frames with `motion`): blended with the previous frame's output of
     this step, reprojected by `motion` and clipped to the range of this frame's output over a small window
     (service/stages/history_blend.py).
     Beyond the paper, whose recurrence alone carries history: the network's output still flickers where it
     is unsure, and the clipped average steadies it. Demodulated, so that texture is not blurred by the
     bilinear reprojection; without `motion` nothing is blended (an absent motion is not a still camera).
     History 0.3 against none, the benchmark's sequences (docs/training.md): temporal error 2-5% lower, and
     relL2 as low or lower. Since the noise blend takes back an accumulated input (Pipeline.step), 0.4
     against 0.3: temporal error 0.5-1.3% lower on shadows, fireflies and textures, relL2 up to 1.5% higher
     (shadows, fireflies) or 0.3% lower (textures), relL2 on the Blender fixture 0.6% higher; 0.5 raised
     relL2 on shadows and fireflies by 3-4%.
     Blended in radiance rather than demodulated, textures' relL2 rose.
  6. remodulation by the albedo
The network sees zero radiance where nothing was hit (zero normal), and the pipeline step returns those pixels
as they came (service.stages.background). Our training renders carry the directly seen environment in their
`emission` layer, so the network learned radiance without it; a frame whose renderer writes no `emission`
layer, or one without the environment (Blender's Emit pass), would otherwise hand it a sky of radiance /
ALBEDO_EPS that it never saw (the `glints` hard case: a sky tile 16x worse than the noisy input). The
environment seen directly is nearly noise-free in a path tracer (one lookup per sample), so passing it through
costs little.
State: the network's hidden states (explicit ONNX inputs and outputs, ModelInfo.state), zeros at the first
frame of every sequence. A sequence has one size (Pipeline.check refuses a frame of another size, as the
streaming sessions do), so a renderer that changes resolution starts a new sequence, and with it a new state.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field

import numpy as np

from service.frame import Frame
from service.layout import pad_planes
from service.pipelines import register
from service.pipelines.base import SequenceState
from service.pipelines.networks import NetworkPipeline, frame_planes
from service.pipelines.options import MAX_THREADS, option
from service.runtime import OnnxModel, weight_names
from service.stages.albedo import remodulate
from service.stages.hidden_warp import warp_states
from service.stages.history_blend import OutputHistory
from service.stages.outliers import clamp_outliers
from service.stages.rae_inputs import lighting_from_output

NETWORK = "rae"  # the network a `weights` file must hold (its ONNX metadata)
DEFAULT_WEIGHTS = "rae"  # models/weights/rae.onnx (manifest: rae.json)
HISTORY = 0.4  # default weight of the previous output in step 5 (module docstring)


@dataclass(frozen=True)
class RaeOptions:
    # network weights: a name from the registry (service.runtime.weight_files), never a path
    weights: str = option(DEFAULT_WEIGHTS, choices=functools.partial(weight_names, NETWORK))
    # move the hidden state by `motion` between frames (an extension of the paper); None: as the weights
    # were trained (their metadata)
    warp: bool | None = option(None)
    # ONNX Runtime intra-op threads (0: $MCDENOISE_ORT_THREADS or ORT's default)
    threads: int = option(0, low=0, high=MAX_THREADS)
    # weight of the previous output, reprojected by `motion` and clipped to the range of this output over a
    # (2 history_radius + 1)^2 window, in each output where reprojection holds (module docstring; 0: off)
    history: float = option(HISTORY, low=0, high=0.95)
    history_radius: int = option(1, low=1, high=8)


@dataclass
class RaeState(SequenceState):
    """hidden: the network's state tensors (1, C_l, H_pad / s_l, W_pad / s_l) float32, in ModelInfo.state
    order; empty before the first frame."""

    hidden: list[np.ndarray] = field(default_factory=list)
    history: OutputHistory = field(default_factory=OutputHistory)  # the last step-5 output (module docstring)

    def forget(self) -> None:
        """The recurrent state and the output history go (a new start)."""
        super().forget()
        self.hidden, self.history = [], OutputHistory()


def trained_with_warp(model: OnnxModel) -> bool:
    """Whether the weights were trained with the hidden-state warp (their `training.options.warp`)."""
    training = model.info.metadata.get("training") or {}
    return bool((training.get("options") or {}).get("warp", False))


@register
class RaePipeline(NetworkPipeline):
    name = "rae"
    summary = "recurrent denoising autoencoder (Chaitanya 2017), trained offline; ONNX Runtime, temporal"
    requires = ("color", "albedo", "normal", "depth")
    optional = ("roughness", "motion", "emission", "colorA", "colorB")
    temporal = True
    Options = RaeOptions
    network = NETWORK
    State = RaeState

    @property
    def warps(self) -> bool:
        """Whether the hidden state is moved by `motion`: the `warp` option, else as the weights were trained."""
        warp = self.options.warp
        return trained_with_warp(self.model()) if warp is None else warp

    def denoise(self, frame: Frame, state: SequenceState) -> tuple[dict[str, np.ndarray], SequenceState]:
        model = self.model()
        info = model.info
        halves = (frame["colorA"], frame["colorB"]) if "colorA" in frame and "colorB" in frame else None
        clamped = clamp_outliers(frame["color"], halves=halves, albedo=frame["albedo"])
        planes = frame_planes(frame.replace(color=clamped))
        padded = np.ascontiguousarray(pad_planes(planes, info.alignment))
        height, width = padded.shape[1:]
        hidden = state.hidden
        if not hidden or (self.warps and "motion" not in frame):  # a start (stage 2)
            hidden = [np.zeros(spec.shape(height, width), np.float32) for spec in info.state]
        elif self.warps:
            motion = pad_planes(frame["motion"].transpose(2, 0, 1), info.alignment).transpose(1, 2, 0)
            hidden = warp_states(hidden, motion, [spec.scale for spec in info.state])
        feeds = {info.input_name: padded[None], **{spec.input: h for spec, h in zip(info.state, hidden, strict=True)}}
        outputs = model.run(feeds)
        # The radiance alone is checked: each hidden state is an encoder level's output, which also reaches
        # the radiance through that level's skip connection, and NaN and Inf survive convolutions and leaky
        # ReLU, so a non-finite state shows in this frame's radiance; one that got past (fed back in) shows
        # in the next frame's at the latest, and that frame resets the state.
        if not np.isfinite(outputs[info.output_name]).all():  # a non-finite state would fail every later frame:
            # Pipeline.step's RaeState.forget resets it, and the next frame starts afresh
            raise FloatingPointError(f"pipeline '{self.name}': the network produced non-finite values; "
                                     "its recurrent state was reset")
        state.hidden = [outputs[spec.output] for spec in info.state]
        lighting = lighting_from_output(outputs[info.output_name][0, :, : frame.height, : frame.width])
        if self.options.history:
            lighting = state.history.blend(lighting, frame, self.options.history, self.options.history_radius)
        radiance = remodulate(lighting, frame["albedo"])
        return {"color": radiance}, state
