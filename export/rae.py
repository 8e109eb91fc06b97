"""Export the recurrent autoencoder (models/nets/rae.py) to ONNX with its contract and recurrent state.

Inputs: `features` (N, 8, H, W) in service.layout.RAE_INPUTS order and `hidden0..hidden{L-1}`; outputs:
`radiance` (N, 3, H, W) in RAE_OUTPUTS order and `hidden0_next..`, the next frame's state. H and W are
dynamic, multiples of the alignment (the serving side pads). The metadata lists the state tensors
(name in, name out, channels, scale: ModelInfo.state) so the pipeline allocates zeros for a sequence's
first frame without knowing the network.

    python -m export rae CHECKPOINT.pt OUT.onnx      (a models.train checkpoint: best.pt or checkpoint.pt)

writes OUT.onnx and its manifest OUT.json (`manifest`).
"""

from __future__ import annotations

import csv
import json
from dataclasses import asdict
from pathlib import Path
from typing import Any

import torch

from export import onnx as onnx_export
from models.nets import count_parameters
from models.nets.rae import RecurrentAutoencoder, load_network
from models.train.train import LOG, inference_state
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


def train_command(opts: dict[str, Any], step: int) -> str:
    """The `python -m models.train` command line that remakes a run's checkpoint of step `step` from its
    stored options: `--steps step`, no `--minutes` (a run stopped early is the same run with fewer steps)."""
    opts = {**opts, "steps": step}
    opts.setdefault("ema", 0.0)  # runs from before the `ema` option used raw weights
    flags = " ".join(f"--{k.replace('_', '-')} {v}" for k, v in opts.items()
                     if k not in ("net", "warp", "init", "minutes") and v not in ("", None))
    flags += " --warp" * bool(opts.get("warp")) + (f" --init {opts['init']}" if opts.get("init") else "")
    return f"python -m models.train {opts.get('net', NETWORK)} {flags}"


def manifest(ckpt: dict[str, Any], net: RecurrentAutoencoder, checkpoint: Path, onnx_path: Path) -> dict[str, Any]:
    """What the shipped weights are and how they were made: the network, the training run (options as
    a command line, preceded by the runs it fine-tuned, oldest first; data, seed, steps, losses, time,
    machine) from the checkpoint and the log.csv beside it."""
    opts = ckpt.get("options") or {}
    runs, base, init = [train_command(opts, ckpt["step"])], [], opts.get("init")
    while init and Path(init).is_file():  # the runs this one fine-tuned, oldest first
        start = torch.load(init, map_location="cpu", weights_only=False)
        runs.insert(0, train_command(start["options"], start["step"]))
        base.insert(0, {"checkpoint": init, "step": start.get("step"), "seconds": start.get("seconds"),
                        "best_val_rel_l2": start.get("best_val_rel_l2")})
        init = start["options"].get("init")
    log = checkpoint.parent / LOG
    rows = list(csv.DictReader(log.open())) if log.is_file() else []
    train_rows = [r for r in rows if r["kind"] == "train" and int(r["step"]) <= ckpt["step"]]
    val_rows = [r for r in rows if r["kind"] == "val"]
    return {
        "network": NETWORK,
        "file": onnx_path.name,
        "bytes": onnx_path.stat().st_size,
        "parameters": count_parameters(net),
        "config": ckpt["config"],
        "commands": ["make data", *runs, f"python -m export {NETWORK} {checkpoint} {onnx_path}"],
        "seed": opts.get("seed"),
        "step": ckpt.get("step"),
        "data": ckpt.get("data"),
        "validation": ckpt.get("val"),
        "best_val_rel_l2": ckpt.get("best_val_rel_l2"),
        "final_train_loss": {k: float(train_rows[-1][k]) for k in ("loss", "spatial", "gradient", "temporal")}
        if train_rows else None,  # the last log row at or before the exported step
        "validation_curve": [{"step": int(r["step"]), "rel_l2": float(r["val_rel_l2"]),
                              "temporal": float(r["val_temporal"])} for r in val_rows
                             if int(r["step"]) <= ckpt["step"]],
        "training_seconds": ckpt.get("seconds"),  # wall time of this run up to the exported checkpoint
        "fine_tuned_from": base,
        "machine": ckpt.get("machine"),
    }


def export_checkpoint(checkpoint: str | Path, out: str | Path) -> Path:
    """Export a models.train checkpoint to `out` (.onnx) and its manifest to `out` with .json. The training
    options, step and validation score also go into the ONNX metadata under `training`."""
    checkpoint, out = Path(checkpoint), Path(out)
    ckpt = torch.load(checkpoint, map_location="cpu", weights_only=False)
    training = {"options": ckpt.get("options"), "step": ckpt.get("step"),
                "best_val_rel_l2": ckpt.get("best_val_rel_l2"), "machine": ckpt.get("machine")}
    net = load_network(inference_state(ckpt))
    path = onnx_export.write(export_bytes(net, extra={"training": training}), out)
    path.with_suffix(".json").write_text(json.dumps(manifest(ckpt, net, checkpoint, path), indent=1) + "\n")
    return path
