"""Export the kernel-predicting network (models/nets/kpn.py) to ONNX with its contract.

Input `features` (N, 11, H, W) in service.layout.KPN_INPUTS order: the recurrent autoencoder's planes and the
previous output warped to this frame (the recurrent state, an explicit input that the pipeline holds in its
sequence state and warps). Outputs, all logits: `fine`, the full-resolution KPN_FINE_OUTPUTS in space-to-depth
layout (N, 51 * 4, H/2, W/2) (its factor is the metadata's `space_to_depth`), `half` (N, 26, H/2, W/2) and
`quarter` (N, 26, H/4, W/4) in KPN_COARSE_OUTPUTS order, listed under the metadata's `coarse` with their
scales. H and W are dynamic, multiples of the alignment (the serving side pads). The metadata's `motion`
says which motion the previous output was warped by in training (`dual`: motionDual; `plain`: motion).
"""

from __future__ import annotations

from dataclasses import asdict
from typing import Any

import torch

from export import onnx as onnx_export
from models.nets.kpn import KernelPredictor
from models.nets.rae import SPACE_TO_DEPTH
from service.layout import KPN_COARSE_OUTPUTS, KPN_FINE_OUTPUTS, KPN_INPUTS, groups_to_json

NETWORK = "kpn"
INPUT_NAME = "features"
OUTPUT_NAME = "fine"
COARSE_OUTPUTS = (("half", 2), ("quarter", 4))  # (output name, downsampling of the frame), as forward returns them


def trained_motion(extra: dict[str, Any] | None) -> str:
    """The motion the network was trained with (`training.options.motion` of the export's extra metadata),
    "dual" when not recorded."""
    options = ((extra or {}).get("training") or {}).get("options") or {}
    return str(options.get("motion", "dual"))


def export_bytes(net: KernelPredictor, *, extra: dict[str, Any] | None = None) -> bytes:
    """The ONNX model of `net` (eval mode, float32) as bytes, with the `mcdenoise` metadata."""
    a = net.alignment
    metadata = {
        "network": NETWORK,
        "config": asdict(net.config),
        "alignment": a,
        "inputs": {INPUT_NAME: groups_to_json(KPN_INPUTS)},
        "outputs": {OUTPUT_NAME: groups_to_json(KPN_FINE_OUTPUTS)},
        "space_to_depth": SPACE_TO_DEPTH,  # of `fine`: (N, 51 * 4, H/2, W/2), pixel-shuffle order
        "coarse": [{"output": name, "scale": scale, "groups": groups_to_json(KPN_COARSE_OUTPUTS)}
                   for name, scale in COARSE_OUTPUTS],
        "motion": trained_motion(extra),
        **(extra or {}),
    }
    inputs = {INPUT_NAME: torch.zeros(1, net.config.in_channels, 2 * a, 3 * a)}
    names = [OUTPUT_NAME, *(name for name, _ in COARSE_OUTPUTS)]
    return onnx_export.export_bytes(net, inputs, names, metadata, named_weights=False)
