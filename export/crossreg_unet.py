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
from dataclasses import asdict
from pathlib import Path
from typing import Any

import torch

from export import onnx as onnx_export
from models.nets.crossreg_unet import CrossRegUNet, load_checkpoint
from service.layout import CROSSREG_INPUTS, CROSSREG_OUTPUTS, groups_to_json

INPUT_NAME = "features"
OUTPUT_NAME = "params"


def export_bytes(net: CrossRegUNet, *, extra: dict[str, Any] | None = None) -> bytes:
    """The ONNX model of `net` (eval mode, float32) as bytes, with the `mcdenoise` metadata."""
    dummy = torch.zeros(1, net.config.in_channels, 2 * net.alignment, 3 * net.alignment)
    metadata = {
        "network": "crossreg_unet",
        "config": asdict(net.config),
        "alignment": net.alignment,
        "inputs": {INPUT_NAME: groups_to_json(CROSSREG_INPUTS)},
        "outputs": {OUTPUT_NAME: groups_to_json(CROSSREG_OUTPUTS)},
        **(extra or {}),
    }
    return onnx_export.export_bytes(net, {INPUT_NAME: dummy}, [OUTPUT_NAME], metadata)


def export_onnx(net: CrossRegUNet, path: str | Path, *, extra: dict[str, Any] | None = None) -> Path:
    """Write `net` to `path` (see `export_bytes`)."""
    return onnx_export.write(export_bytes(net, extra=extra), path)


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
