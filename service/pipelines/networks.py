"""Loading a pipeline's ONNX network from the weight registry (service.runtime.weight_files) by name, and
what the pipelines around one offline-trained network (`rae`, `flnr`, `kpn`) share."""

from __future__ import annotations

from typing import Any

import numpy as np

from service.frame import Frame
from service.pipelines.base import Pipeline, SequenceState
from service.pipelines.options import OptionError
from service.runtime import OnnxModel, weight_files
from service.stages.rae_inputs import rae_planes
from service.stages.reprojection import surface_hit


def registered_model(name: str, network: str, *, threads: int | None, swappable: bool = True) -> OnnxModel:
    """The registry's `name` as an OnnxModel. OptionError on option `weights` when the file is gone (an
    operator's folder may change after the option was checked), is not a loadable model, or holds another
    network than `network`."""
    path = weight_files().get(name)
    if path is None:
        raise OptionError(f"weights '{name}' are no longer in the registry", "weights")
    try:
        model = OnnxModel.from_file(path, threads=threads, swappable=swappable)
    except Exception as err:  # ONNX Runtime raises its own types for a file that is not a model
        raise OptionError(f"weights '{name}' are not a loadable ONNX model ({type(err).__name__})", "weights") from err
    if model.info.network != network:
        raise OptionError(f"weights '{name}' hold network '{model.info.network}', not {network}", "weights")
    return model


class NetworkPipeline(Pipeline):
    """A pipeline around one ONNX network of the registry: its Options have `weights` (a registry name) and
    `threads`; the model loads on first use, at the latest when a sequence starts, and its sessions share it
    (no state inside the model)."""

    network: str  # the network a `weights` file must hold (its ONNX metadata)
    State: type[SequenceState] = SequenceState  # what `new_state` makes

    def __init__(self, **options: Any):
        super().__init__(**options)
        self._model: OnnxModel | None = None

    def model(self) -> OnnxModel:
        if self._model is None:
            self._model = registered_model(self.options.weights, self.network, threads=self.options.threads or None,
                                           swappable=False)
        return self._model

    def new_state(self, height: int, width: int) -> SequenceState:
        self.model()  # a bad `weights` file fails at the start of the sequence, not at its first frame
        return self.State(height, width)


def frame_planes(frame: Frame) -> np.ndarray:
    """The recurrent autoencoder's input planes of `frame` (its `color` without emission): (8, H, W) float32
    (service.stages.rae_inputs.rae_planes), with zero radiance where nothing was hit (zero normal): the pipeline
    step returns those pixels as they came (service.stages.background), and the networks never saw radiance
    there."""
    return rae_planes(frame["color"], frame["albedo"], frame["normal"], frame["depth"], frame.get("roughness"),
                      background=~surface_hit(frame["normal"]))
