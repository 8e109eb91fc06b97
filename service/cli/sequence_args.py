"""What the commands that run a sequence folder through a pipeline share (`denoise`, `stream`): their
arguments, `KEY=VALUE` options and the choice of pipeline for 'auto'."""

from __future__ import annotations

import argparse
import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

AUTO = "auto"  # service.pipelines.AUTO, without importing the pipelines to build the parser


def add_sequence_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("in_dir", type=Path, help="sequence folder of frame EXR files")
    p.add_argument("out_dir", type=Path, help="folder for the denoised EXR files (same names)")
    p.add_argument("--pipeline", default=AUTO,
                   help="pipeline name, or 'auto' (default): the best pipeline the first frame's layers can feed")
    p.add_argument("--option", "-o", action="append", default=[], metavar="KEY=VALUE",
                   help="pipeline option, repeatable (see `pipelines --json`)")
    p.add_argument("--online", action="store_true",
                   help="fine-tune the pipeline's network while the sequence runs (sets option online=true)")


def parse_options(items: Sequence[str]) -> dict[str, Any]:
    """`KEY=VALUE` strings -> dict; values are parsed as JSON when they are JSON (numbers, true, ...)."""
    options: dict[str, Any] = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise ValueError(f"option '{item}' is not KEY=VALUE")
        try:
            options[key] = json.loads(value)
        except json.JSONDecodeError:
            options[key] = value
    return options


def resolve_pipeline(name: str, in_dir: Path) -> str:
    """`name`, or for 'auto' the preferred pipeline whose required layers the sequence's first frame has
    (read from its header); says which on stdout."""
    from service import pipelines
    from service.exr import list_sequence, read_header

    if name != AUTO:
        return name
    first = list_sequence(in_dir)[0]
    name = pipelines.auto(read_header(first).layers)
    print(f"pipeline: {name} (auto: the preferred pipeline whose layers {first.name} has)")
    return name
