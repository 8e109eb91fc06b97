"""Export the recurrent autoencoder (models/nets/rae.py) to ONNX with its contract and recurrent state.

Inputs: `features` (N, 8, H, W) in service.layout.RAE_INPUTS order and `hidden0..hidden{L-1}`; outputs:
`radiance` (N, 3, H, W) in RAE_OUTPUTS order and `hidden0_next..`, the next frame's state. H and W are
dynamic, multiples of the alignment (the serving side pads). The metadata lists the state tensors
(name in, name out, channels, scale: ModelInfo.state) so the pipeline allocates zeros for a sequence's
first frame without knowing the network.

    python -m export rae CHECKPOINT.pt OUT.onnx      (a models.train checkpoint: best.pt or checkpoint.pt)

writes OUT.onnx and its manifest OUT.json (export/checkpoint.py).
"""

from __future__ import annotations

from dataclasses import asdict
from typing import Any

import torch

from export import onnx as onnx_export
from models.nets.rae import RecurrentAutoencoder
from service.layout import RAE_INPUTS, RAE_OUTPUTS, groups_to_json

NETWORK = "rae"
INPUT_NAME = "features"
OUTPUT_NAME = "radiance"


def state_names(levels: int) -> list[tuple[str, str]]:
    """(input, output) names of each level's hidden state."""
    return [(f"hidden{i}", f"hidden{i}_next") for i in range(levels)]


def export_bytes(net: RecurrentAutoencoder, *, extra: dict[str, Any] | None = None) -> bytes:
    """The ONNX model of `net` (eval mode, float32) as bytes, with the `mcdenoise` metadata."""
    a = net.alignment
    height, width = 2 * a, 3 * a  # distinct, not 1: the tracer keeps them symbolic
    names = state_names(net.config.levels)
    inputs = {INPUT_NAME: torch.zeros(1, net.config.in_channels, height, width)}
    inputs.update(zip((i for i, _ in names), net.zero_hidden(1, height, width), strict=True))
    metadata = {
        "network": NETWORK,
        "config": asdict(net.config),
        "alignment": a,
        "inputs": {INPUT_NAME: groups_to_json(RAE_INPUTS)},
        "outputs": {OUTPUT_NAME: groups_to_json(RAE_OUTPUTS)},
        "state": [{"input": i, "output": o, "channels": c, "scale": s}
                  for (i, o), c, s in zip(names, net.config.widths, net.config.scales, strict=True)],
        **(extra or {}),
    }
    # never hot-swapped (the pipeline loads it with swappable=False), so initializers may be merged
    return onnx_export.export_bytes(net, inputs, [OUTPUT_NAME, *(o for _, o in names)], metadata, named_weights=False)
