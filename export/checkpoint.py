"""Exporting a models.train checkpoint (`python -m export NET CHECKPOINT OUT.onnx`): the network's ONNX file
and its manifest, for every offline-trained network (export/rae.py, export/flnr.py, export/kpn.py make the ONNX bytes).

The manifest (OUT.json) says what the shipped weights are and how they were made: the network, the training
run (its options as a command line, preceded by the runs it fine-tuned, oldest first, and by `make data` or
the command that rendered its data and ran it: `--made-by` for the exported run, `--made-by-for CKPT` for the
run that made CKPT; a chain that starts from exported weights, `--init models/weights/NET.onnx`, starts with
the commands of the manifest that was beside them when that run began, which its checkpoints keep, so that
exporting over those weights changes nothing), data, seed, steps, losses, validation curve,
time and machine, from the checkpoint and the log.csv beside it.
"""

from __future__ import annotations

import csv
import json
import os
import shlex
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import torch

from export import flnr, kpn, rae
from export import onnx as onnx_export
from models.nets import count_parameters
from models.nets.flnr import load_network as load_flnr
from models.nets.kpn import load_network as load_kpn
from models.nets.rae import load_network as load_rae
from models.train.train import KPN_ONLY, LOG, LOG_TERMS, RAE_ONLY, inference_state

NETWORKS = {"rae": (load_rae, rae.export_bytes), "flnr": (load_flnr, flnr.export_bytes),
            "kpn": (load_kpn, kpn.export_bytes)}  # name -> (load, export)


PATH_OPTIONS = ("data", "val", "out", "init")  # written relative to the working directory where they lie in it


def _relative(path: str) -> str:
    """`path` relative to the working directory (the repository root, where the commands run) where it lies in
    it; else as it is."""
    relative = os.path.relpath(path)
    return relative if os.path.isabs(path) and not relative.startswith("..") else path


def train_command(opts: dict[str, Any], step: int) -> str:
    """The `python -m models.train` command line that remakes a run's checkpoint of step `step` from its
    stored options: `--steps step`, no `--minutes` (a run stopped early is the same run with fewer steps),
    `--occlusion-from` rescaled so that the occlusion term joins at the same step as in the run, and paths in
    the working directory relative to it."""
    if "occlusion_from" in opts and step:
        opts = {**opts, "occlusion_from": float(f"{min(1.0, opts['occlusion_from'] * opts['steps'] / step):.6g}")}
    opts = {**opts, "steps": step, **{k: _relative(opts[k]) for k in PATH_OPTIONS if opts.get(k)}}
    if opts.get("net", "rae") != "kpn":  # options only kpn reads stay out of other networks' commands
        opts = {k: v for k, v in opts.items() if k not in KPN_ONLY}
    if opts.get("net", "rae") != "rae":  # and those only rae reads
        opts = {k: v for k, v in opts.items() if k not in RAE_ONLY}
    opts.setdefault("ema", 0.0)  # runs from before the `ema` option used raw weights
    flags = " ".join(f"--{k.replace('_', '-')} {v}" for k, v in opts.items()
                     if k not in ("net", "warp", "init", "minutes") and v not in ("", None))
    flags += " --warp" * bool(opts.get("warp")) + (f" --init {opts['init']}" if opts.get("init") else "")
    return f"python -m models.train {opts.get('net', 'rae')} {flags}"


def manifest(ckpt: dict[str, Any], net: torch.nn.Module, checkpoint: Path, onnx_path: Path,
             network: str, made_by: str = "", earlier: dict[str, str] | None = None) -> dict[str, Any]:
    """The manifest of the module docstring. `made_by`: the command that rendered the last run's data and ran
    it (listed before that run's command), where it was not `make data`; `earlier`: the same for runs it
    fine-tuned, by the checkpoint path they made as the chain names it (`--init`). `make data` comes first
    while any run lacks one."""
    opts = ckpt.get("options") or {}
    runs, base, init = [(str(checkpoint), train_command(opts, ckpt["step"]))], [], opts.get("init")
    shipped: list[str] = []  # the commands that made the exported weights the chain starts from, if it does
    link = ckpt  # the run whose --init is `init`
    while init and init not in {path for path, _ in runs}:  # the runs it fine-tuned
        if Path(init).suffix == ".onnx":  # exported weights: their manifest as the run found it (kept, see train)
            made_from = link.get("init_manifest")
            if made_from is None:
                raise ValueError(f"a run fine-tuned {init} but its checkpoint keeps no manifest of those weights")
            shipped = made_from["commands"]
            base[:0] = [*(made_from.get("fine_tuned_from") or []), {
                "onnx": _relative(init), "step": made_from.get("step"), "seconds": made_from.get("training_seconds"),
                "best_val_rel_l2": made_from.get("best_val_rel_l2")}]
            break
        if not Path(init).is_file():
            break
        start = link = torch.load(init, map_location="cpu", weights_only=False)
        runs.insert(0, (init, train_command(start["options"], start["step"])))
        base.insert(0, {"checkpoint": init, "step": start.get("step"), "seconds": start.get("seconds"),
                        "best_val_rel_l2": start.get("best_val_rel_l2")})
        init = start["options"].get("init")
    runs = [(os.path.normpath(path), command) for path, command in runs]
    earlier = {os.path.normpath(path): command for path, command in (earlier or {}).items()}
    unknown = set(earlier) - {path for path, _ in runs[:-1]}
    if unknown:
        raise ValueError(f"--made-by-for names no checkpoint this one was fine-tuned from: {sorted(unknown)}")
    made = {**earlier, **({runs[-1][0]: made_by} if made_by else {})}
    commands = shipped + ["make data"] * (any(path not in made for path, _ in runs) and "make data" not in shipped)
    for path, command in runs:
        commands += ([made[path]] if path in made else []) + [command]
    exported = ["python", "-m", "export", network, str(checkpoint), str(onnx_path),
                *["--made-by", made_by] * bool(made_by)]
    for path, command in earlier.items():
        exported += ["--made-by-for", path, command]
    log = checkpoint.parent / LOG
    rows = list(csv.DictReader(log.open())) if log.is_file() else []
    train_rows = [r for r in rows if r["kind"] == "train" and int(r["step"]) <= ckpt["step"]]
    val_rows = [r for r in rows if r["kind"] == "val"]
    return {
        "network": network,
        "file": onnx_path.name,
        "bytes": onnx_path.stat().st_size,
        "parameters": count_parameters(net),
        "config": ckpt["config"],
        "commands": [*commands, shlex.join(exported)],
        "seed": opts.get("seed"),
        "step": ckpt.get("step"),
        "data": ckpt.get("data"),
        "validation": ckpt.get("val"),
        "best_val_rel_l2": ckpt.get("best_val_rel_l2"),
        "final_train_loss": {k: float(train_rows[-1][k]) for k in LOG_TERMS if train_rows[-1].get(k)}
        if train_rows else None,  # the last log row at or before the exported step
        "validation_curve": [{"step": int(r["step"]), "rel_l2": float(r["val_rel_l2"]),
                              "temporal": float(r["val_temporal"])} for r in val_rows
                             if int(r["step"]) <= ckpt["step"]],
        "training_seconds": ckpt.get("seconds"),  # wall time of this run up to the exported checkpoint
        "fine_tuned_from": base,
        "machine": ckpt.get("machine"),
        "trained": datetime.fromtimestamp(checkpoint.stat().st_mtime, UTC).date().isoformat(),  # the checkpoint's day
    }


def export_checkpoint(network: str, checkpoint: str | Path, out: str | Path, made_by: str = "",
                      earlier: dict[str, str] | None = None) -> Path:
    """Export a models.train checkpoint of `network` (a NETWORKS key) to `out` (.onnx) and its manifest to `out`
    with .json (`made_by`, `earlier`: `manifest`'s). The training options, step and validation score also go
    into the ONNX metadata under `training`. ValueError if the checkpoint was trained for another network, or
    `earlier` names a checkpoint outside its chain."""
    checkpoint, out = Path(checkpoint), Path(out)
    ckpt = torch.load(checkpoint, map_location="cpu", weights_only=False)
    trained = (ckpt.get("options") or {}).get("net", "rae")
    if trained != network:
        raise ValueError(f"{checkpoint} holds a '{trained}' network, not '{network}'")
    load, export_bytes = NETWORKS[network]
    training = {"options": ckpt.get("options"), "step": ckpt.get("step"),
                "best_val_rel_l2": ckpt.get("best_val_rel_l2"), "machine": ckpt.get("machine")}
    net = load(inference_state(ckpt))
    path = onnx_export.write(export_bytes(net, extra={"training": training}), out)
    info = manifest(ckpt, net, checkpoint, path, network, made_by, earlier)
    path.with_suffix(".json").write_text(json.dumps(info, indent=1) + "\n")
    return path
