"""The one torch -> ONNX export path of every network (export/crossreg_unet.py, rae.py, flnr.py, kpn.py).

`export_bytes` traces the network with the TorchScript exporter (opset 17), makes height and width (and the
batch axis) of every input and output dynamic, and writes the JSON metadata entry `mcdenoise` that
service/runtime.py reads instead of hard-coding anything: the caller's contract (network name, channel
groups, alignment, constructor args, recurrent state) plus name -> shape of every weight initializer.
With `named_weights` every torch parameter must survive as an initializer of its own name (the crossreg
hot-swap overrides weights by name; the exporter merges identical tensors, such as freshly zeroed biases,
so a network whose weights are never swapped does not ask for it).
"""

from __future__ import annotations

import io
import json
import warnings
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import onnx
import torch
from onnx import numpy_helper

from service.runtime import METADATA_KEY

OPSET = 17


def dynamic_axes(name: str) -> dict[int, str]:
    """NCHW batch, height and width of tensor `name` vary. Each tensor gets its own height and width
    symbols: ONNX Runtime's memory planner takes equal symbols for equal sizes, and a hidden state at
    half resolution is not the frame's size."""
    return {0: "n", 2: f"{name}_height", 3: f"{name}_width"}


def export_bytes(net: torch.nn.Module, inputs: Mapping[str, torch.Tensor], outputs: Sequence[str],
                 metadata: Mapping[str, Any], *, named_weights: bool = True) -> bytes:
    """The ONNX model of `net` in eval mode as bytes.

    inputs: input name -> example NCHW float32 tensor, in the order `net.forward` takes them (their height
    and width should not be 1 or equal each other's by accident: the tracer would fold them); outputs: the
    output names in the order `forward` returns them; metadata: the contract, stored under `mcdenoise` with
    `weights` (initializer name -> shape) added.
    """
    net = net.eval()
    names = [*inputs, *outputs]
    buffer = io.BytesIO()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)  # the TorchScript exporter; no onnxscript here
        torch.onnx.export(
            net, tuple(inputs.values()), buffer, input_names=list(inputs), output_names=list(outputs),
            dynamic_axes={name: dynamic_axes(name) for name in names}, opset_version=OPSET, do_constant_folding=True,
            dynamo=False,
        )  # fmt: skip
    model = onnx.load_from_string(buffer.getvalue())
    params = dict(net.named_parameters())
    weights = {i.name: list(i.dims) for i in model.graph.initializer if i.name in params}
    missing = sorted(set(params) - set(weights))
    if named_weights and missing:
        raise RuntimeError(f"ONNX export renamed or folded parameters {missing}; the hot-swap needs their names")
    entry = model.metadata_props.add()
    entry.key, entry.value = METADATA_KEY, json.dumps({**metadata, "layout": "NCHW", "weights": weights})
    onnx.checker.check_model(model)
    return model.SerializeToString()


def write(model_bytes: bytes, path: str | Path) -> Path:
    """Write an exported model to `path` (parent folders created)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(model_bytes)
    return path


def initializers(model_bytes: bytes) -> dict[str, np.ndarray]:
    """name -> array of every initializer of an ONNX model."""
    model = onnx.load_from_string(model_bytes)
    return {i.name: numpy_helper.to_array(i) for i in model.graph.initializer}


def checkpoint_state(model_bytes: bytes) -> dict[str, Any]:
    """{'config', 'state_dict'} of a network `export_bytes` exported, as a checkpoint's `inference_state` holds
    them (a fine-tune can start from shipped weights): the config from the `mcdenoise` metadata, every
    parameter its `weights` entry names from the initializer of that name (float32 CPU tensors)."""
    model = onnx.load_from_string(model_bytes)
    entries = {p.key: p.value for p in model.metadata_props}
    if METADATA_KEY not in entries:
        raise ValueError(f"no '{METADATA_KEY}' metadata: not a model this project exported")
    metadata = json.loads(entries[METADATA_KEY])
    if "config" not in metadata or "weights" not in metadata:
        raise ValueError(f"the '{METADATA_KEY}' metadata names no config or weights: exported before they were kept")
    arrays = initializers(model_bytes)
    missing = sorted(set(metadata["weights"]) - set(arrays))
    if missing:
        raise ValueError(f"the model lacks the initializers of weights {missing}")
    state = {name: torch.from_numpy(np.array(arrays[name], dtype=np.float32)) for name in metadata["weights"]}
    return {"config": metadata["config"], "state_dict": state}
