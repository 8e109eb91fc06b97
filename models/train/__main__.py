"""`python -m models.train NET --data DIR --val DIR --out DIR [--steps N] [--resume]`: train an offline network.

NET is one of models.train.train.RECIPES (`rae`, `flnr`, `kpn`). DIR folders hold sequence folders rendered by
`python -m models.data dataset`. See models/train/train.py for what the output folder holds.
"""

from __future__ import annotations

import argparse
import dataclasses

from models.train.kpn import MOTIONS
from models.train.train import DEVICES, RECIPES, TrainOptions, train
from service.process import configure


def _parser() -> argparse.ArgumentParser:
    defaults = {f.name: f.default for f in dataclasses.fields(TrainOptions) if f.default is not dataclasses.MISSING}
    p = argparse.ArgumentParser(prog="python -m models.train", description=__doc__.splitlines()[0])
    p.add_argument("net", choices=sorted(RECIPES))
    p.add_argument("--data", required=True, help="folder of training sequence folders")
    p.add_argument("--val", required=True, help="folder of held-out sequence folders (validation)")
    p.add_argument("--out", required=True, help="output folder: checkpoints, log.csv, curves.png")
    p.add_argument("--resume", action="store_true", help="continue from OUT/checkpoint.pt")
    for name in ("steps", "batch", "warmup", "seed", "threads", "val_every", "log_every", "checkpoint_every"):
        p.add_argument("--" + name.replace("_", "-"), type=int, default=defaults[name])
    p.add_argument("--lr", type=float, default=defaults["lr"])
    p.add_argument("--ema", type=float, default=defaults["ema"], help="weight-average decay (0: raw weights)")
    p.add_argument("--clip-grad", type=float, default=defaults["clip_grad"],
                   help="largest global gradient norm a step applies, 0..1000 (0: no clipping)")
    p.add_argument("--tone-eps", type=float, default=defaults["tone_eps"],
                   help="added to radiance before the loss's power 0.2, in (0, 1] (default: the shipped weights')")
    p.add_argument("--minutes", type=float, default=defaults["minutes"], help="wall-time limit (0: none)")
    p.add_argument("--warp", action="store_true", help="warp the recurrent state by motion between frames")
    p.add_argument("--device", choices=DEVICES, default=defaults["device"], help="where the network trains")
    p.add_argument("--motion", choices=MOTIONS, default=defaults["motion"],
                   help="kpn: warp the previous output by motionDual (dual, where the frame has it) or motion (plain)")
    p.add_argument("--occlusion-from", type=float, default=defaults["occlusion_from"],
                   help="kpn: share of the steps after which the motion-occlusion loss joins (0..1)")
    p.add_argument("--temporal-weight", type=float, default=defaults["temporal_weight"],
                   help="rae: the loss's temporal L1 weight, 0..0.9; the spatial one is 0.9 minus it (paper: 0.1)")
    p.add_argument("--init", default="",
                   help="start from this checkpoint's weights (a fine-tune), or an exported .onnx file's")
    return p


def main(argv: list[str] | None = None) -> int:
    configure()  # an entry point that runs the service's kernels (service/process.py)
    args = vars(_parser().parse_args(argv))
    resume = args.pop("resume")
    try:
        opts = TrainOptions(**args)
    except ValueError as exc:
        raise SystemExit(f"python -m models.train: {exc}") from None
    ckpt = train(opts, resume=resume)
    print(f"step {ckpt['step']}: best held-out relL2 {ckpt['best_val_rel_l2']:.4f}; files in {opts.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
