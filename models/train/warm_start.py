"""Offline warm start of the crossreg U-Net: the online scheme of Choi et al. 2024 (sec. 4.3: one Adam
step per frame, self-supervised loss of eqs. 11-13, no reference images) replayed over many rendered
sequences, so a serving session starts from useful weights instead of random ones.

Each epoch walks every sequence in frame order exactly as the serving pipeline does (the same
`prepare_frame` from service/pipelines/crossreg.py: cross-regression, reprojection, screening), with the
network being trained producing the history of the next frame. It trains through the paper's filter: neither
crossreg's `min_alpha` nor its `pilot_bandwidth` floor applies here (the shipped weights were trained so, and
serve with both). Pilots do not depend on the network and
are computed once per frame. Writes CHECKPOINT.pt (constructor args + weights + manifest), the .onnx
export and a JSON manifest (data, steps, seed, loss curve) to --out.

    python -m models.train.warm_start --data out/crossreg_train --synthetic 6 --minutes 12 --out models/weights
"""

from __future__ import annotations

import argparse
import json
import logging
import platform
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from export.crossreg_unet import export_onnx
from models.nets import count_parameters
from models.nets.crossreg_unet import make_unet, save_checkpoint
from models.train.step import LEARNING_RATE, forward, make_optimizer, samples_to_tensor
from service.exr import list_sequence, read_frame
from service.frame import RADIANCE_LAYERS, Frame
from service.pipelines.crossreg import History, Prepared, averaged_frame_pilots, next_history, prepare_frame
from service.process import configure
from service.stages.cross_regression import cross_regression
from service.stages.emission import subtract_emission

log = logging.getLogger("models.train.warm_start")

NAME = "crossreg_unet"  # file stem of the shipped weights


@dataclass
class Sequence:
    """Frames of one sequence (emission removed as Pipeline.step removes it: `subtract_emission`, its clip at an
    emitter's edge included) with their cached pilots."""

    name: str
    frames: list[Frame]
    pilots: list[tuple[np.ndarray, np.ndarray]]
    source: dict[str, Any]


def _without_emission(frame: Frame) -> Frame:
    emission = frame.get("emission")
    if emission is None:
        return frame
    names = [k for k in RADIANCE_LAYERS if k in frame]
    return frame.replace(**dict(zip(names, subtract_emission([frame[k] for k in names], emission), strict=True)))


def _with_pilots(name: str, frames: list[Frame], source: dict[str, Any], averaged: bool = False) -> Sequence:
    """The sequence with its pilots: the paper's (`cross_regression` of each frame's halves) or, `averaged`, those
    crossreg serves by default (its `average_halves` option: service.stages.averaged_halves, in frame order)."""
    frames = [_without_emission(f) for f in frames]
    if not averaged:
        pilots = [cross_regression(f["colorA"], f["colorB"], f["albedo"], f["normal"]) for f in frames]
        return Sequence(name, frames, pilots, source)
    pilots, history = [], None
    for f in frames:  # the pilots do not depend on the network: a history of the halves alone
        halves, frame_pilots = averaged_frame_pilots(f, history)
        pilots.append(frame_pilots)
        history = History(np.empty((0, *halves.shape[1:]), np.float32), f["normal"], f.get("depth"), halves)
    return Sequence(name, frames, pilots, source)


def load_folders(root: Path, averaged: bool = False) -> list[Sequence]:
    """Every sequence folder under `root` (folders holding EXR frames), sorted by name."""
    out = []
    for folder in sorted({p.parent for p in root.rglob("*.exr")}):
        frames = [read_frame(p) for p in list_sequence(folder)]
        meta_path = folder / "sequence.json"
        meta = json.loads(meta_path.read_text()) if meta_path.is_file() else {}
        keep = {k: meta[k] for k in ("source", "scene", "seed", "spp", "size") if k in meta}
        out.append(_with_pilots(folder.name, frames, {"folder": str(folder), **keep}, averaged))
    return out


def synthetic(count: int, seed: int, averaged: bool = False) -> list[Sequence]:
    """`count` bench.synthetic sequences of assorted sizes (24x40 to 128x96: the network must not over-smooth
    small frames, where its 11x11 window spans whole objects) and seeds 100 + seed + i (8 frames, 8 spp)."""
    from bench.synthetic import synthetic_sequence

    sizes = [(24, 40), (64, 96), (32, 48), (96, 128), (48, 64), (80, 80), (40, 64), (128, 96)]
    out = []
    for i in range(count):
        height, width = sizes[i % len(sizes)]
        layers = synthetic_sequence(height, width, 8, spp=8, seed=seed + 100 + i)
        frames = [Frame.from_buffers(x) for x in layers]
        source = {"bench.synthetic": {"height": height, "width": width, "frames": 8, "spp": 8, "seed": seed + 100 + i}}
        out.append(_with_pilots(f"synthetic_{i}", frames, source, averaged))
    return out


def _step_frame(net, optimizer, prepared: Prepared) -> tuple[float, np.ndarray]:
    """One Adam step on the whole frame; returns (loss, filter output colour (3, H, W) log1p, detached)."""
    net.train()
    optimizer.zero_grad(set_to_none=True)
    loss, result = forward(net, samples_to_tensor(prepared.sample()))
    loss.backward()
    optimizer.step()
    return float(loss.detach()), result.color.detach()[0].numpy()


def train(sequences: list[Sequence], *, seconds: float, max_steps: int, seed: int) -> tuple[Any, dict[str, Any]]:
    """Train until `seconds` or `max_steps`; returns (net, summary with the loss curve)."""
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    net = make_unet(seed=seed)
    optimizer = make_optimizer(net, LEARNING_RATE)
    losses: list[float] = []
    start = time.monotonic()
    epochs = 0
    while time.monotonic() - start < seconds and len(losses) < max_steps:
        for index in rng.permutation(len(sequences)):
            seq = sequences[index]
            history: History | None = None
            for frame, pilots in zip(seq.frames, seq.pilots, strict=True):
                prepared = prepare_frame(frame, history, pilots=pilots)
                loss, color = _step_frame(net, optimizer, prepared)
                losses.append(loss)
                history = next_history(frame, prepared, color)
            if time.monotonic() - start >= seconds or len(losses) >= max_steps:
                break
        epochs += 1
        tail = np.mean(losses[-200:])
        elapsed = time.monotonic() - start
        log.info("epoch %d: %d steps, mean loss of the last 200 %.5f, %.0f s", epochs, len(losses), tail, elapsed)
    curve = [float(np.mean(losses[i : i + 50])) for i in range(0, len(losses), 50)]
    summary = {
        "steps": len(losses),
        "epochs_started": epochs,
        "seconds": round(time.monotonic() - start, 1),
        "loss_first_50": curve[0] if curve else None,
        "loss_last_200": float(np.mean(losses[-200:])) if losses else None,
        "loss_curve_per_50_steps": [round(v, 6) for v in curve],
    }
    return net, summary


def main(argv: list[str] | None = None) -> int:
    configure()  # an entry point that runs the service's kernels (service/process.py)
    parser = argparse.ArgumentParser(prog="python -m models.train.warm_start", description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, action="append", default=[], help="folder of sequences (repeatable)")
    parser.add_argument("--synthetic", type=int, default=0, help="also this many bench.synthetic sequences")
    parser.add_argument("--minutes", type=float, default=12.0, help="training time budget")
    parser.add_argument("--max-steps", type=int, default=1_000_000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=1, help="torch threads (1 is fastest on a shared CPU)")
    parser.add_argument("--out", type=Path, default=Path("models/weights"))
    parser.add_argument("--pilots", choices=("paper", "averaged"), default="paper",
                        help="the paper's pilots, or those of crossreg's average_halves (its default)")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    torch.set_num_threads(args.threads)
    averaged = args.pilots == "averaged"
    sequences = [s for root in args.data for s in load_folders(root, averaged)] + synthetic(args.synthetic, args.seed,
                                                                                             averaged)
    if not sequences:
        parser.error("no training data: give --data folders and/or --synthetic N")
    log.info("%d sequences, %d frames", len(sequences), sum(len(s.frames) for s in sequences))
    net, summary = train(sequences, seconds=60 * args.minutes, max_steps=args.max_steps, seed=args.seed)
    manifest = {
        "network": NAME,
        "parameters": count_parameters(net),
        "method": "self-supervised loss of Choi 2024 eqs. 11-13 (no references), one Adam step per frame "
        f"(lr {LEARNING_RATE}) on whole frames, sequences replayed in frame order as the pipeline runs them",
        "seed": args.seed,
        "pilots": args.pilots,
        "data": [
            {"name": s.name, "frames": len(s.frames), "height_width": list(s.frames[0]["colorA"].shape[:2]), **s.source}
            for s in sequences
        ],
        "command": "python -m models.train.warm_start " + " ".join(argv if argv is not None else sys.argv[1:]),
        "torch": str(torch.__version__),
        "machine": f"{platform.machine()}, {args.threads} torch threads",
        **summary,
    }
    args.out.mkdir(parents=True, exist_ok=True)
    save_checkpoint(str(args.out / f"{NAME}.pt"), net, manifest=manifest)
    training = {k: manifest[k] for k in ("seed", "steps", "loss_last_200")}
    export_onnx(net, args.out / f"{NAME}.onnx", extra={"training": training})
    (args.out / f"{NAME}.json").write_text(json.dumps(manifest, indent=1) + "\n")
    steps, final = summary["steps"], summary["loss_last_200"]
    log.info("wrote %s.{pt,onnx,json} to %s: %d steps, final loss %.5f", NAME, args.out, steps, final)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
