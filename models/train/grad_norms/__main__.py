"""`python -m models.train.grad_norms`: the command line of models/train/grad_norms (its docstring)."""

from __future__ import annotations

import argparse

from models.train.dataset import SequenceBank
from models.train.grad_norms import __doc__ as DOC
from models.train.grad_norms import options_for, report, window_norms
from models.train.train import RECIPES, held_threads
from service.process import configure


def main(argv: list[str] | None = None) -> int:
    configure()  # an entry point whose imports reach the service's kernels (service/process.py)
    parser = argparse.ArgumentParser(prog="python -m models.train.grad_norms", description=DOC.splitlines()[0])
    parser.add_argument("net", choices=sorted(RECIPES))
    parser.add_argument("--data", required=True, help="folder of training sequence folders")
    parser.add_argument("--init", default="", help="checkpoint whose weights are measured (default: fresh ones)")
    parser.add_argument("--windows", type=int, default=300)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--tone-eps", type=float, default=None, help="the loss's (default: --init's run's)")
    parser.add_argument("--top", type=int, default=8)
    parser.add_argument("--threads", type=int, default=0, help="torch's and numba's threads (0: their defaults)")
    args = parser.parse_args(argv)
    if args.windows < 1 or args.top < 0 or args.threads < 0:
        raise SystemExit("python -m models.train.grad_norms: --windows must be >= 1, --top and --threads >= 0")
    try:
        opts = options_for(args.net, args.data, args.init, args.tone_eps)
    except ValueError as exc:
        raise SystemExit(f"python -m models.train.grad_norms: {exc}") from None
    with held_threads(args.threads):
        print(report(window_norms(opts, SequenceBank.from_root(args.data), args.windows, args.seed), args.top))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
