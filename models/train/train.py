"""The offline training loop shared by every offline-trained network (`python -m models.train NET ...`).

One run writes into its output folder:
- `checkpoint.pt`: network constructor args and weights, optimizer, step, random-generator states and the
  run's arguments, every `checkpoint_every` steps and at the end; `--resume` continues from it exactly;
- `best.pt`: the step with the lowest validation relL2 so far, without the optimiser state and the raw weights
  (what export/ exports and `--init` starts from: its weight average, `inference_state`);
- `log.csv`: one row per `log_every` steps (mean loss terms, learning rate, sequences per second) and one
  per validation (relL2 and temporal error on the held-out sequences, service/metrics.py);
- `curves.png`: the training loss and the validation scores against the step.

Optimiser (Chaitanya 2017 sec. 5.3): Adam, lr 1e-3, betas (0.9, 0.99), minibatches of 4 windows; the learning
rate ramps up tenfold geometrically over the first `warmup` steps (from 1e-4 to the paper's 1e-3: we read
"ramped up tenfold" as ending at the stated rate), then falls as 1/sqrt(step).
"""

from __future__ import annotations

import contextlib
import copy
import csv
import json
import math
import os
import platform
import time
from collections.abc import Iterator
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any

import numba
import numpy as np
import torch

from export.onnx import checkpoint_state
from models.nets import state_for
from models.train.dataset import SequenceBank, collate
from models.train.flnr import FlnrRecipe
from models.train.kpn import MOTIONS, KpnRecipe
from models.train.rae import RaeRecipe
from models.train.rae_loss import TEMPORAL_WEIGHTS, TONE_EPS, WEIGHTS
from service.metrics import TRIM_FRACTION, rel_l2, temporal_rel_l2

RECIPES = {"rae": RaeRecipe, "flnr": FlnrRecipe, "kpn": KpnRecipe}  # NET name -> how to build, feed and score it
Recipe = RaeRecipe | FlnrRecipe | KpnRecipe
RESUME_MAY_CHANGE = ("steps", "minutes", "threads", "out", "device")  # options a resumed run may set anew
CHECKPOINT = "checkpoint.pt"
BEST = "best.pt"
LOG = "log.csv"
CURVES = "curves.png"
DEVICES = ("cpu", "cuda")
KPN_ONLY = {"motion": "dual", "occlusion_from": 0.5}  # TrainOptions only kpn reads, and their defaults
RAE_ONLY = {"temporal_weight": WEIGHTS[2]}  # TrainOptions only rae reads, and their defaults
LOG_FIELDS = ("step", "kind", "loss", "spatial", "gradient", "temporal", "occlusion", "lr", "seq_per_s", "val_rel_l2",
              "val_temporal", "seconds")
TERMS = ("total", "spatial", "gradient", "temporal", "occlusion")  # LossTerms fields, logged as LOG_TERMS
LOG_TERMS = ("loss", "spatial", "gradient", "temporal", "occlusion")


@dataclass(frozen=True)
class TrainOptions:
    """One training run."""

    net: str  # key of RECIPES
    data: str  # folder of training sequence folders (models.data dataset)
    val: str  # folder of held-out sequence folders scored at every validation
    out: str  # output folder
    steps: int = 4000  # optimiser steps in all (a resumed run continues to this count)
    batch: int = 4  # windows per step (Chaitanya 2017: 4)
    lr: float = 1e-3  # peak learning rate (Chaitanya 2017: 0.001)
    warmup: int = 200  # steps of the tenfold geometric ramp-up
    seed: int = 0  # network initialisation and window sampling
    threads: int = 0  # torch's threads and, at most as many, numba's (0: each library's default)
    val_every: int = 250  # steps between validations
    log_every: int = 25  # steps per log.csv row
    checkpoint_every: int = 250  # steps between checkpoints
    minutes: float = 0.0  # stop (with a checkpoint) after this much wall time of this invocation; 0: no limit
    warp: bool = False  # warp recurrent state by motion between frames (the pipeline option of the same name)
    init: str = ""  # start from this checkpoint's or exported .onnx's weights (a fine-tune: fresh optimiser, step 0)
    ema: float = 0.999  # decay of the exponential moving average of the weights that is validated and
    # exported (Polyak averaging; 0: the raw weights). Batches of 4 windows make single steps noisy.
    device: str = "cpu"  # where the network trains and its windows are cut: "cpu" or "cuda"
    # the largest global gradient norm a step applies (larger ones are scaled down to it), in [0, 1e3]; 0: no
    # clipping. The shipped rae's norms were 0.3-0.6, with outliers of 1.4 (16 steps of batch 16); its H100
    # runs' loss jumped with and without clipping at 1.0 (docs/training.md), so it stays off by default.
    clip_grad: float = 0.0
    # added to the loss's radiance before its power 0.2 (models/train/rae_loss.py `tone`), in (0, 1]: 1e-3 made
    # the shipped weights; near-black pixels' gradients are up to 0.2 eps^-0.8 (docs/training.md, "Gradient norms")
    tone_eps: float = TONE_EPS
    # kpn: the motion that warps the previous output, "dual" (motionDual) or "plain" (motion)
    motion: str = KPN_ONLY["motion"]
    # kpn: share of `steps` after which the motion-occlusion loss term joins (Zeng 2023 sec. 5: half), in [0, 1]
    occlusion_from: float = KPN_ONLY["occlusion_from"]
    # rae: the loss's temporal weight wt in [0, 0.9], the spatial one 0.9 - wt (models/train/rae_loss.py; the
    # paper's 0.1). A larger one trades relL2 for frame-to-frame steadiness (docs/training.md).
    temporal_weight: float = RAE_ONLY["temporal_weight"]

    def __post_init__(self):
        if self.net not in RECIPES:
            raise ValueError(f"unknown network '{self.net}'; networks: {', '.join(RECIPES)}")
        for name in ("steps", "batch", "warmup", "val_every", "log_every", "checkpoint_every"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.threads < 0:
            raise ValueError(f"threads must be >= 0 (0: each library's default), got {self.threads}")
        if not 0 < self.lr <= 1:
            raise ValueError(f"lr must be in (0, 1], got {self.lr}")
        if not 0 <= self.ema < 1:
            raise ValueError(f"ema must be in [0, 1), got {self.ema}")
        if self.motion not in MOTIONS:
            raise ValueError(f"motion must be one of {', '.join(MOTIONS)}, got '{self.motion}'")
        if self.net != "kpn" and self.motion != KPN_ONLY["motion"]:
            raise ValueError("--motion is kpn's (the network that warps its previous output)")
        if not 0 <= self.occlusion_from <= 1:
            raise ValueError(f"occlusion_from must be in [0, 1], got {self.occlusion_from}")
        if self.net != "kpn" and self.occlusion_from != KPN_ONLY["occlusion_from"]:
            raise ValueError("--occlusion-from is kpn's (the network trained with the motion-occlusion loss)")
        if not TEMPORAL_WEIGHTS[0] <= self.temporal_weight <= TEMPORAL_WEIGHTS[1]:
            raise ValueError(f"temporal_weight must be in [{TEMPORAL_WEIGHTS[0]}, {TEMPORAL_WEIGHTS[1]}], "
                             f"got {self.temporal_weight}")
        if self.net != "rae" and self.temporal_weight != RAE_ONLY["temporal_weight"]:
            raise ValueError("--temporal-weight is rae's (the recurrent network trained on windows of frames)")
        if not 0 < self.tone_eps <= 1:
            raise ValueError(f"tone_eps must be in (0, 1], got {self.tone_eps}")
        if not 0 <= self.clip_grad <= 1e3:
            raise ValueError(f"clip_grad must be in [0, 1000], got {self.clip_grad}")
        if self.device not in DEVICES:
            raise ValueError(f"device must be one of {', '.join(DEVICES)}, got '{self.device}'")


def make_recipe(opts: TrainOptions) -> Recipe:
    """The recipe of `opts.net` with the options it reads (ValueError for one it cannot take)."""
    if opts.net == "kpn":
        return KpnRecipe(warp=opts.warp, motion=opts.motion, occlusion_step=round(opts.occlusion_from * opts.steps),
                         tone_eps=opts.tone_eps)
    if opts.net == "rae":
        return RaeRecipe(warp=opts.warp, tone_eps=opts.tone_eps, temporal_weight=opts.temporal_weight)
    return RECIPES[opts.net](warp=opts.warp, tone_eps=opts.tone_eps)


def learning_rate(step: int, peak: float, warmup: int) -> float:
    """Chaitanya 2017 sec. 5.3: peak / 10 ramped geometrically to `peak` over `warmup` steps, then
    peak * sqrt(warmup / step)."""
    if step < warmup:
        return peak * 10.0 ** (step / warmup - 1.0)
    return peak * math.sqrt(warmup / max(step, 1))


def validate(recipe: Recipe, net: torch.nn.Module, bank: SequenceBank) -> tuple[float, float]:
    """(relL2, temporal relL2) of the network over the held-out sequences, each as the benchmark scores a
    sequence (bench/scoring.py: relL2 with the 0.1% trim, mean over frames; temporal error, mean over frames
    1..N-1), then the geometric mean over sequences: the held-out scenes' errors span three decades (a dim
    room ~1e-3, a sky of 1e3 seen through a window ~1), and an arithmetic mean would follow one scene."""
    net.eval()
    errors, temporal = [], []
    for seq in bank.sequences:
        out = recipe.denoise(net, seq).numpy().transpose(0, 2, 3, 1)
        ref = seq.reference.transpose(0, 2, 3, 1)
        errors.append(np.mean([rel_l2(o, r, trim=TRIM_FRACTION) for o, r in zip(out, ref, strict=True)]))
        temporal.append(np.mean([temporal_rel_l2(out[i - 1], out[i], ref[i - 1], ref[i]) for i in range(1, len(out))]))
    net.train()
    return _geometric_mean(errors), _geometric_mean(temporal)


def _geometric_mean(values: list[float]) -> float:
    return float(np.exp(np.mean(np.log(np.maximum(values, 1e-12)))))


def machine(device: str = "cpu") -> dict[str, Any]:
    """Where training runs: device (the GPU's name with cuda), CPU model, torch threads and version (stored in
    every checkpoint)."""
    cpu = platform.processor() or platform.machine()
    cpuinfo = Path("/proc/cpuinfo")
    if cpuinfo.is_file():
        names = [line.split(":", 1)[1].strip() for line in cpuinfo.read_text().splitlines()
                 if line.startswith("model name")]
        cpu = names[0] if names else cpu
    where = torch.cuda.get_device_name() if device == "cuda" else "cpu"
    return {"device": where, "cpu": cpu, "cores": os.cpu_count(), "threads": torch.get_num_threads(),
            "numba_threads": numba.get_num_threads(), "torch": torch.__version__,
            "python": platform.python_version()}


def _state(net, ema, optimizer, step, rng, opts, best, seconds, extra) -> dict[str, Any]:
    return {"net": net.__class__.__name__, **state_for(net), "ema_state_dict": ema.state_dict(),
            "optimizer": optimizer.state_dict(), "step": step, "rng": rng.bit_generator.state,
            "torch_rng": torch.get_rng_state(), "options": asdict(opts), "best_val_rel_l2": best,
            "seconds": seconds, **extra}


def _append_log(path: Path, row: dict[str, Any]) -> None:
    """Append `row` to the CSV log under the file's own header (a run resumed from an older version keeps its
    columns; fields the header lacks are left out), or LOG_FIELDS for a new file."""
    fields = LOG_FIELDS
    if path.exists():
        with path.open(newline="") as f:
            fields = tuple(next(csv.reader(f), LOG_FIELDS))
    new = not path.exists()
    with path.open("a", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=fields)
        if new:
            writer.writeheader()
        writer.writerow({k: row.get(k, "") for k in fields})


def plot_curves(log_path: Path, png_path: Path) -> None:
    """curves.png from log.csv: training loss (left) and validation relL2 / temporal error (right)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    with log_path.open() as f:
        rows = list(csv.DictReader(f))
    train = [(int(r["step"]), float(r["loss"])) for r in rows if r["kind"] == "train"]
    val = [(int(r["step"]), float(r["val_rel_l2"]), float(r["val_temporal"])) for r in rows if r["kind"] == "val"]
    fig, (a, b) = plt.subplots(1, 2, figsize=(10, 3.6))
    if train:
        a.plot(*zip(*train, strict=True))
    a.set(xlabel="step", ylabel="training loss", title="loss (Chaitanya 2017 sec. 4.4)", yscale="log")
    if val:
        steps, rel, tmp = zip(*val, strict=True)
        b.plot(steps, rel, "o-", label="relL2")
        b.plot(steps, tmp, "s-", label="temporal relL2")
        b.legend()
    b.set(xlabel="step", ylabel="error", title="held-out sequences", yscale="log")
    fig.tight_layout()
    fig.savefig(png_path, dpi=100)
    plt.close(fig)


def inference_state(ckpt: dict[str, Any]) -> dict[str, Any]:
    """{'config', 'state_dict'} of the weights a checkpoint serves with: the averaged ones when it has them."""
    return {"config": ckpt["config"], "state_dict": ckpt.get("ema_state_dict") or ckpt["state_dict"]}


def init_state(path: str) -> dict[str, Any]:
    """{'config', 'state_dict'} that `--init PATH` fine-tunes: a checkpoint's `inference_state`, or, for an
    exported `.onnx` file (the shipped weights, models/weights), the weights it holds."""
    if Path(path).suffix == ".onnx":
        return checkpoint_state(Path(path).read_bytes())
    return inference_state(torch.load(path, map_location="cpu", weights_only=False))


def exported_manifest(path: str) -> dict[str, Any]:
    """The manifest beside exported weights (`python -m export`'s OUT.json, for OUT.onnx at `path`), which a
    fine-tune of them keeps in its checkpoints (`init_manifest`) for its own manifest to start from. ValueError
    where there is none: weights fine-tuned from them could not say how they were made."""
    manifest_path = Path(path).with_suffix(".json")
    if not manifest_path.is_file():
        raise ValueError(f"--init {path}: no manifest {manifest_path.name} beside it says how those weights were made")
    made = json.loads(manifest_path.read_text())
    if not isinstance(made.get("commands"), list):
        raise ValueError(f"{manifest_path}: the manifest lists no commands")
    return made


def update_average(ema: torch.nn.Module, net: torch.nn.Module, decay: float, step: int) -> None:
    """ema <- d ema + (1 - d) net with d = min(decay, (1 + step) / (10 + step)) (a short average early on);
    decay 0 copies the weights."""
    d = min(decay, (1 + step) / (10 + step))
    with torch.no_grad():
        for average, weight in zip(ema.parameters(), net.parameters(), strict=True):
            average.mul_(d).add_(weight, alpha=1 - d)


def _start(opts: TrainOptions, recipe: Recipe, ckpt_path: Path, resume: bool):
    """(net, weight average, optimizer, step, best validation relL2, sampling rng, seconds trained so far): from the
    checkpoint with `resume`, else fresh (from `opts.init`'s weights when given) with fixed seeds."""
    if resume:
        if not ckpt_path.is_file():
            raise FileNotFoundError(f"--resume: no {ckpt_path}")
        ckpt = torch.load(ckpt_path, map_location="cpu", weights_only=False)
        stored = {f.name: ckpt["options"].get(f.name, f.default) for f in fields(TrainOptions)}  # older runs:
        changed = {k: (v, getattr(opts, k)) for k, v in stored.items()  # options added since, at their default
                   if k not in RESUME_MAY_CHANGE and getattr(opts, k) != v}
        if changed:
            raise ValueError("--resume with other options than the run had (was, now): "
                             + ", ".join(f"{k} {old!r} -> {new!r}" for k, (old, new) in changed.items()))
        net = recipe.load(ckpt)
        net.to(opts.device)  # before the optimizer, whose loaded state follows its parameters' device
        optimizer = torch.optim.Adam(net.parameters(), lr=opts.lr, betas=(0.9, 0.99))
        optimizer.load_state_dict(ckpt["optimizer"])
        rng = np.random.default_rng()
        rng.bit_generator.state = ckpt["rng"]
        torch.set_rng_state(ckpt["torch_rng"])
        ema = copy.deepcopy(net)
        ema.load_state_dict(ckpt["ema_state_dict"])
        return net, ema, optimizer, int(ckpt["step"]), float(ckpt["best_val_rel_l2"]), rng, float(ckpt["seconds"])
    torch.manual_seed(opts.seed)
    if opts.init:  # a fine-tune: the weights the checkpoint serves with
        net = recipe.load(init_state(opts.init))
    else:
        net = recipe.build(opts.seed)
    net.to(opts.device)
    optimizer = torch.optim.Adam(net.parameters(), lr=opts.lr, betas=(0.9, 0.99))
    return net, copy.deepcopy(net), optimizer, 0, math.inf, np.random.default_rng(opts.seed), 0.0


@contextlib.contextmanager
def held_threads(threads: int) -> Iterator[None]:
    """Within the block, torch and numba (the served stages a recipe calls: flnr's firefly clamp) use `threads`
    threads, restored after; 0 leaves both as they are. Runs side by side (models/train/accelerator.sh) share
    the cores, and numba would otherwise start a thread per core in each. numba's count holds for the calling
    thread, the one that trains."""
    if not threads:
        yield
        return
    before = torch.get_num_threads(), numba.get_num_threads()
    try:
        torch.set_num_threads(threads)
        numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))
        yield
    finally:
        torch.set_num_threads(before[0])
        numba.set_num_threads(before[1])


def train(opts: TrainOptions, *, resume: bool = False, progress: bool = True) -> dict[str, Any]:
    """Run (or resume) training with `opts.threads` threads; returns the final checkpoint dict."""
    with held_threads(opts.threads):
        return _train(opts, resume, progress)


def _train(opts: TrainOptions, resume: bool, progress: bool) -> dict[str, Any]:
    """`train`'s work."""
    from tqdm import tqdm

    if opts.device == "cuda":
        if not torch.cuda.is_available():
            raise ValueError("device cuda: torch sees no CUDA GPU here")
        torch.backends.cudnn.benchmark = True  # fixed window shapes: let cuDNN pick its fastest convolutions
    out = Path(opts.out)
    out.mkdir(parents=True, exist_ok=True)
    recipe = make_recipe(opts)
    bank, held_out = SequenceBank.from_root(opts.data, opts.device), SequenceBank.from_root(opts.val)
    ckpt_path, log_path = out / CHECKPOINT, out / LOG
    extra = {"data": [s.name for s in bank.sequences], "val": [s.name for s in held_out.sequences],
             "machine": machine(opts.device)}
    if Path(opts.init).suffix == ".onnx" and not resume:  # kept in every checkpoint: the file may be exported over
        extra["init_manifest"] = exported_manifest(opts.init)
    net, ema, optimizer, step, best, rng, elapsed = _start(opts, recipe, ckpt_path, resume)
    if Path(opts.init).suffix == ".onnx" and resume:
        extra["init_manifest"] = torch.load(ckpt_path, map_location="cpu", weights_only=False).get("init_manifest")
        if extra["init_manifest"] is None:
            raise ValueError(f"--resume: {ckpt_path} keeps no manifest of the weights it fine-tunes ({opts.init}); "
                             "start the run afresh")
    if step == 0:
        log_path.unlink(missing_ok=True)
    started = time.perf_counter() - elapsed  # wall time counts across resumes
    sums, count, tick = torch.zeros(len(TERMS), device=opts.device), 0, time.perf_counter()
    bar = tqdm(total=opts.steps, initial=step, unit="step", disable=not progress, desc=opts.net)
    net.train()
    while step < opts.steps:
        for group in optimizer.param_groups:
            group["lr"] = learning_rate(step, opts.lr, opts.warmup)
        batch = collate([bank.sample(rng, recipe.frames, recipe.crop, reverse=recipe.reverse)
                         for _ in range(opts.batch)])
        terms = recipe.loss(net, batch, step)
        optimizer.zero_grad(set_to_none=True)
        terms.total.backward()
        if opts.clip_grad:
            torch.nn.utils.clip_grad_norm_(net.parameters(), opts.clip_grad)
        optimizer.step()
        update_average(ema, net, opts.ema, step)
        step += 1
        # summed on the device: no synchronisation per step, so the next windows are cut while the GPU works
        sums += torch.stack([getattr(terms, name).to(sums) for name in TERMS]).detach()
        count += 1
        bar.update(1)
        if step % opts.log_every == 0:
            now = time.perf_counter()
            rate = count * opts.batch / (now - tick)
            mean = (sums / count).tolist()
            _append_log(log_path, {"step": step, "kind": "train", **dict(zip(LOG_TERMS, mean, strict=True)),
                                   "lr": optimizer.param_groups[0]["lr"], "seq_per_s": rate, "seconds": now - started})
            bar.set_postfix(loss=f"{mean[0]:.4f}", seq_s=f"{rate:.2f}")
            sums, count, tick = torch.zeros(len(TERMS), device=opts.device), 0, now
        timed_out = opts.minutes > 0 and time.perf_counter() - started - elapsed > 60 * opts.minutes
        if step % opts.val_every == 0 or step == opts.steps or timed_out:
            rel, tmp = validate(recipe, ema, held_out)
            _append_log(log_path, {"step": step, "kind": "val", "val_rel_l2": rel, "val_temporal": tmp,
                                   "seconds": time.perf_counter() - started})
            plot_curves(log_path, out / CURVES)
            bar.write(f"step {step}: held-out relL2 {rel:.4f}, temporal {tmp:.4f}")
            if rel < best:
                best = rel
                state = _state(net, ema, optimizer, step, rng, opts, best, time.perf_counter() - started, extra)
                torch.save({k: v for k, v in state.items() if k not in ("optimizer", "state_dict")}, out / BEST)
        if step % opts.checkpoint_every == 0 or step == opts.steps or timed_out:
            torch.save(_state(net, ema, optimizer, step, rng, opts, best, time.perf_counter() - started, extra),
                       ckpt_path)
        if timed_out:
            break
    bar.close()
    return torch.load(ckpt_path, map_location="cpu", weights_only=False)
