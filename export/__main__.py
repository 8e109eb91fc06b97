"""`python -m export NET CHECKPOINT OUT.onnx`: export a trained network (rae, flnr, kpn) with its metadata contract.

NET names the network as `python -m models.train NET` does (the shipped manifests' commands carry it);
the crossreg U-Net has its own command, `python -m export.crossreg_unet CHECKPOINT OUT` (its checkpoints
come from models/train/warm_start.py).
"""

from __future__ import annotations

import argparse
from pathlib import Path


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m export", description=__doc__.splitlines()[0])
    parser.add_argument("net", choices=["flnr", "kpn", "rae"], help="the network (a models.train checkpoint)")
    parser.add_argument("checkpoint", type=Path)
    parser.add_argument("out", type=Path)
    parser.add_argument("--made-by", default="", metavar="COMMAND",
                        help="the command that rendered the data of the checkpoint's run and ran it, where that "
                             "was not `make data` and the run's own command (models/train/accelerator.sh ...)")
    parser.add_argument("--made-by-for", nargs=2, action="append", default=[], metavar=("CKPT", "COMMAND"),
                        help="the same for the run that made CKPT, a checkpoint this one was fine-tuned from "
                             "(as its --init named it); repeatable")
    args = parser.parse_args(argv)
    named = [path for path, _ in args.made_by_for]
    if len(set(named)) < len(named):
        parser.error("--made-by-for names a checkpoint twice")
    from export.checkpoint import export_checkpoint  # torch: imported once the arguments are good
    from service.process import configure

    configure()  # an entry point that reaches the service's kernels (service/process.py)

    try:
        path = export_checkpoint(args.net, args.checkpoint, args.out, made_by=args.made_by,
                                 earlier=dict(args.made_by_for))
    except ValueError as err:
        raise SystemExit(f"python -m export: {err}") from None
    print(f"wrote {path} ({path.stat().st_size / 1e6:.2f} MB)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
