"""`python -m service COMMAND ...`: one module per command in this package, each with `add_args(parser)`
(argparse only) and `run(args) -> int`, which imports what the command needs when it runs.

Exit status: 0 on success, 2 with a one-line `error: ...` on bad input or options.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence

# (command, module of this package, one-line help)
COMMANDS = (
    ("denoise", "denoise", "denoise every frame of a sequence folder"),
    ("pipelines", "pipelines", "list pipelines with their required and optional layers"),
    ("inspect", "inspect_exr", "layers, channel types, size and value statistics of an EXR file"),
    ("warm", "warm", "compile the numba kernels of pipelines ahead of their first frame (cached per machine)"),
    ("serve", "serve", "serve every pipeline over HTTP: REST frames, sessions, WebSocket streams"),
    ("cluster", "cluster", "N `serve` replicas behind HAProxy: sticky sessions, stateless frames spread"),
    ("stream", "stream", "stream a sequence folder through a running service, write the results"),
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m service", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    for name, module_name, help_text in COMMANDS:
        module = importlib.import_module(f"{__name__}.{module_name}")
        p = sub.add_parser(name, help=help_text, description=help_text)
        module.add_args(p)
        p.set_defaults(run=module.run)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Parse `argv` (default: sys.argv[1:]), apply `service.process.configure()` and run the command."""
    from service.frame import FrameError
    from service.process import configure

    args = build_parser().parse_args(argv)
    configure()
    try:
        return args.run(args)
    except (FrameError, ValueError, KeyError, OSError) as err:
        message = str(err).splitlines()[0] if str(err) else type(err).__name__
        print(f"error: {message}", file=sys.stderr)
        return 2
