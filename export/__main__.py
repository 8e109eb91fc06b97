"""`python -m export NET CHECKPOINT OUT.onnx`: export a trained network with its metadata contract.

NET: `rae` (a models.train checkpoint). The crossreg U-Net has its own command,
`python -m export.crossreg_unet CHECKPOINT OUT` (its checkpoints come from models/train/warm_start.py).
"""

from __future__ import annotations

import argparse
from pathlib import Path

EXPORTERS = {"rae": "export.rae"}  # NET -> module with export_checkpoint(checkpoint, out)


def main(argv: list[str] | None = None) -> int:
    import importlib

    parser = argparse.ArgumentParser(prog="python -m export", description=__doc__.splitlines()[0])
    parser.add_argument("net", choices=sorted(EXPORTERS))
    parser.add_argument("checkpoint", type=Path)
    parser.add_argument("out", type=Path)
    args = parser.parse_args(argv)
    path = importlib.import_module(EXPORTERS[args.net]).export_checkpoint(args.checkpoint, args.out)
    print(f"wrote {path} ({path.stat().st_size / 1e6:.2f} MB)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
