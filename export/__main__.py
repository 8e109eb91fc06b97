"""`python -m export rae CHECKPOINT OUT.onnx`: export a trained recurrent autoencoder with its metadata contract.

`rae` names the network as `python -m models.train rae` does (the shipped manifests' commands carry it);
the crossreg U-Net has its own command, `python -m export.crossreg_unet CHECKPOINT OUT` (its checkpoints
come from models/train/warm_start.py).
"""

from __future__ import annotations

import argparse
from pathlib import Path


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m export", description=__doc__.splitlines()[0])
    parser.add_argument("net", choices=["rae"], help="the network (a models.train checkpoint)")
    parser.add_argument("checkpoint", type=Path)
    parser.add_argument("out", type=Path)
    args = parser.parse_args(argv)
    from export.rae import export_checkpoint  # torch: imported once the arguments are good
    from service.process import configure

    configure()  # an entry point that reaches the service's kernels (service/process.py)

    path = export_checkpoint(args.checkpoint, args.out)
    print(f"wrote {path} ({path.stat().st_size / 1e6:.2f} MB)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
