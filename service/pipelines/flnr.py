"""`flnr`: fast local neural regression (Salmi et al.): FLR on guides that a small network learned, so that
the regression can follow what no G-buffer shows (cast shadows, indirect light).

Stages, per frame (emission already split off by Pipeline.step, added back after):
  1. the guide network in ONNX Runtime (models/nets/flnr.py): the recurrent autoencoder's input planes
     (service/stages/rae_inputs.py: demodulated log1p radiance, normal, relative depth, roughness), padded by
     edge replication to the network's alignment -> guides (normal and relative depth, transformed by what
     the network learned), cropped back to the frame;
  2. FLR (service/stages/flr.py) of the radiance (below 0 read as 0) demodulated by the albedo on those
     guides, with the regression options the network was trained through (its metadata);
  3. clamp to the local range of the noisy input, as `flr` does.
It is temporal through the shared step alone (`Pipeline.step`): the noise blend may take back the input
accumulated over the sequence (reprojected by `motion`; service.stages.input_history) where the halves say it
beats this frame's, as Salmi et al. extend FLNR to sequences by accumulating reprojected samples. The
regression itself stays on this frame's input, as it was trained: on the accumulated input it did worse on
the benchmark's disocclusion and fireflies sequences (docs/training.md, `flnr`).
The network was trained end to end through FLR's torch twin (models/train/flnr.py);
tests/service/pipelines/test_flnr.py holds the served pipeline to it.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from service.frame import Frame
from service.layout import pad_planes
from service.pipelines import register
from service.pipelines.base import SequenceState
from service.pipelines.networks import NetworkPipeline, frame_planes
from service.pipelines.options import MAX_THREADS, option
from service.runtime import OnnxModel, weight_names
from service.stages.flr import FlrParams, local_linear_regression
from service.stages.range_clamp import clamp_to_local_range

NETWORK = "flnr"  # the network a `weights` file must hold (its ONNX metadata)
DEFAULT_WEIGHTS = "flnr"  # models/weights/flnr.onnx (manifest: flnr.json)


@dataclass(frozen=True)
class FlnrOptions:
    # network weights: a name from the registry (service.runtime.weight_files), never a path
    weights: str = option(DEFAULT_WEIGHTS, choices=functools.partial(weight_names, NETWORK))
    # ONNX Runtime intra-op threads (0: $MCDENOISE_ORT_THREADS or ORT's default)
    threads: int = option(0, low=0, high=MAX_THREADS)


def regression_params(model: OnnxModel) -> FlrParams:
    """The FLR options the weights were trained through (their metadata's `flr`: scale, sigma)."""
    flr = model.info.metadata.get("flr") or {}
    return FlrParams(scale=int(flr.get("scale", FlrParams.scale)), sigma=float(flr.get("sigma", FlrParams.sigma)))


@register
class FlnrPipeline(NetworkPipeline):
    name = "flnr"
    summary = "fast local regression on guides a small network learns (Salmi et al.); ONNX Runtime + FLR"
    requires = ("color", "albedo", "normal", "depth")
    optional = ("roughness", "motion", "emission")  # motion: the accumulated input's (module docstring)
    Options = FlnrOptions
    network = NETWORK
    temporal = True  # the noise blend's accumulated input (module docstring)

    def guides(self, frame: Frame) -> np.ndarray:
        """(G, H, W) float32: the network's FLR guides for `frame`."""
        model = self.model()
        info = model.info
        planes = frame_planes(frame)  # the network sees no radiance where nothing was hit (as rae)
        learned = model.run({info.input_name: np.ascontiguousarray(pad_planes(planes, info.alignment))[None]})
        learned = learned[info.output_name][0, :, : frame.height, : frame.width]
        if not np.isfinite(learned).all():
            raise FloatingPointError(f"pipeline '{self.name}': the network produced non-finite guides")
        return learned

    def denoise(self, frame: Frame, state: SequenceState) -> tuple[dict[str, np.ndarray], SequenceState]:
        params = regression_params(self.model())
        guides = self.guides(frame).transpose(1, 2, 0)  # (H, W, G), a view of (G, H, W) memory
        # radiance below 0 (a light's edge, with its emission taken out) counts as 0, as in training
        radiance = np.maximum(frame["color"], np.float32(0))
        color = local_linear_regression(radiance, guides, params, albedo=frame["albedo"])
        # No extrapolated energy: the fit's support is about two cells of `scale` pixels each way.
        color = clamp_to_local_range(color, frame["color"], 2 * params.scale)
        return {"color": color}, state
