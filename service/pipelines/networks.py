"""Loading a pipeline's ONNX network from the weight registry (service.runtime.weight_files) by name."""

from __future__ import annotations

from service.pipelines.options import OptionError
from service.runtime import OnnxModel, weight_files


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
