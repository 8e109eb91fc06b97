"""Export FLNR's guide network (models/nets/flnr.py) to ONNX with its contract.

Input `features` (N, 8, H, W) in service.layout.RAE_INPUTS order; output `guides` (N, G, H, W) in
FLNR_OUTPUTS order. H and W are dynamic, multiples of the alignment (the serving side pads). The regression
options the network was trained through go into the metadata (`flr`: scale, sigma), so the pipeline
regresses as training did.
"""

from __future__ import annotations

from dataclasses import asdict
from typing import Any

import torch

from export import onnx as onnx_export
from models.nets.flnr import GuideNet
from models.train.flnr import FLR
from service.layout import FLNR_OUTPUTS, RAE_INPUTS, groups_to_json

NETWORK = "flnr"
INPUT_NAME = "features"
OUTPUT_NAME = "guides"


def export_bytes(net: GuideNet, *, extra: dict[str, Any] | None = None) -> bytes:
    """The ONNX model of `net` (eval mode, float32) as bytes, with the `mcdenoise` metadata."""
    a = net.alignment
    metadata = {
        "network": NETWORK,
        "config": asdict(net.config),
        "alignment": a,
        "inputs": {INPUT_NAME: groups_to_json(RAE_INPUTS)},
        "outputs": {OUTPUT_NAME: groups_to_json(FLNR_OUTPUTS)},
        "flr": {"scale": FLR.scale, "sigma": FLR.sigma},
        **(extra or {}),
    }
    inputs = {INPUT_NAME: torch.zeros(1, net.config.in_channels, 2 * a, 3 * a)}
    return onnx_export.export_bytes(net, inputs, [OUTPUT_NAME], metadata, named_weights=False)
