"""`python -m bench ...`: benchmark commands. `synthetic` writes the analytic test sequence."""

import argparse
import sys
from pathlib import Path

from bench.synthetic import write_synthetic_sequence


def main() -> int:
    parser = argparse.ArgumentParser(prog="python -m bench")
    sub = parser.add_subparsers(dest="command", required=True)
    syn = sub.add_parser("synthetic", help="write the analytic synthetic sequence (all layers + reference)")
    syn.add_argument("--out", type=Path, required=True)
    syn.add_argument("--size", default="96x64", help="WxH")
    syn.add_argument("--frames", type=int, default=4)
    syn.add_argument("--spp", type=int, default=8)
    syn.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    width, height = (int(v) for v in args.size.lower().split("x"))
    paths = write_synthetic_sequence(args.out, height=height, width=width, frames=args.frames,
                                     spp=args.spp, seed=args.seed)
    print(f"wrote {len(paths)} frames to {args.out}")
    return 0


sys.exit(main())
