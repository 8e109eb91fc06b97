"""Export the cross-regression U-Net (models/nets/crossreg_unet.py) to ONNX with its input contract.

The graph has one input `features` (N, 15, H, W) and one output `params` (N, 6, H, W), H and W dynamic
(multiples of the alignment; the serving side pads). The file's metadata entry `mcdenoise` (JSON) carries
what service/runtime.py reads instead of hard-coding it: the channel groups of input and output with their
transforms, the alignment, the constructor arguments, and name -> shape of every weight initializer (the
names the hot-swap overrides; they equal the torch parameter names).

    python -m export.crossreg_unet CHECKPOINT.pt OUT.onnx
"""

from __future__ import annotations

import argparse
import io
import json
import warnings
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np
import onnx
import torch
from onnx import numpy_helper

from models.nets.crossreg_unet import CrossRegUNet, load_checkpoint
from service.layout import CROSSREG_INPUTS, CROSSREG_OUTPUTS, groups_to_json
from service.runtime import METADATA_KEY

OPSET = 17
INPUT_NAME = "features"
OUTPUT_NAME = "params"


def export_bytes(net: CrossRegUNet, *, extra: dict[str, Any] | None = None) -> bytes:
    """The ONNX model of `net` (eval mode, float32) as bytes, with the `mcdenoise` metadata."""
    net = net.eval()
    dummy = torch.zeros(1, net.config.in_channels, 2 * net.alignment, 3 * net.alignment)
    buffer = io.BytesIO()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)  # the TorchScript exporter; no onnxscript here
        torch.onnx.export(
            net, (dummy,), buffer, input_names=[INPUT_NAME], output_names=[OUTPUT_NAME],
            dynamic_axes={name: {0: "n", 2: "height", 3: "width"} for name in (INPUT_NAME, OUTPUT_NAME)},
            opset_version=OPSET, do_constant_folding=True, dynamo=False,
        )  # fmt: skip
    model = onnx.load_from_string(buffer.getvalue())
    params = dict(net.named_parameters())
    weights = {i.name: list(i.dims) for i in model.graph.initializer if i.name in params}
    missing = sorted(set(params) - set(weights))
    if missing:
        raise RuntimeError(f"ONNX export renamed or folded parameters {missing}; the hot-swap needs their names")
    metadata = {
        "network": "crossreg_unet",
        "config": asdict(net.config),
        "alignment": net.alignment,
        "inputs": {INPUT_NAME: groups_to_json(CROSSREG_INPUTS)},
        "outputs": {OUTPUT_NAME: groups_to_json(CROSSREG_OUTPUTS)},
        "layout": "NCHW",
        "weights": weights,
        **(extra or {}),
    }
    entry = model.metadata_props.add()
    entry.key, entry.value = METADATA_KEY, json.dumps(metadata)
    onnx.checker.check_model(model)
    return model.SerializeToString()


def export_onnx(net: CrossRegUNet, path: str | Path, *, extra: dict[str, Any] | None = None) -> Path:
    """Write `net` to `path` (see `export_bytes`)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(export_bytes(net, extra=extra))
    return path


def initializers(model_bytes: bytes) -> dict[str, np.ndarray]:
    """name -> array of every initializer of an ONNX model."""
    model = onnx.load_from_string(model_bytes)
    return {i.name: numpy_helper.to_array(i) for i in model.graph.initializer}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m export.crossreg_unet", description=__doc__.splitlines()[0])
    parser.add_argument("checkpoint", type=Path)
    parser.add_argument("out", type=Path)
    args = parser.parse_args(argv)
    net, ckpt = load_checkpoint(str(args.checkpoint))
    export_onnx(net, args.out, extra={"training": ckpt.get("manifest", {})})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
