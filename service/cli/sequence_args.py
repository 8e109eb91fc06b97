"""What the commands that run a sequence folder through a pipeline share (`denoise`, `stream`): their
arguments, `KEY=VALUE` options and the choice of pipeline for 'auto'."""

from __future__ import annotations

import argparse
import json
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from service.dialects import ChannelMap

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
    p.add_argument("--second-half", type=Path, metavar="DIR",
                   help="a second render of the same frames with another seed: frame i of each makes the halves "
                        "colorA, colorB (the split-buffer pipelines need them)")
    add_dialect_args(p)


def add_dialect_args(p: argparse.ArgumentParser) -> None:
    """How the files' channels map to layers, where the reader's detection (`service.dialects`) needs help."""
    p.add_argument("--channel-map", type=Path, metavar="FILE.json",
                   help="JSON map from the files' channel names to frame-format layers (README, frame format)")
    p.add_argument("--view-layer", metavar="NAME", help="the Blender view layer to read, when a file holds several")


def channel_map(args: argparse.Namespace) -> ChannelMap | None:
    """The `--channel-map` file, parsed (ValueError naming what is wrong), or None."""
    from service.dialects import ChannelMap

    return None if args.channel_map is None else ChannelMap.from_json(args.channel_map)


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


def resolve_pipeline(name: str, in_dir: Path, mapping: ChannelMap | None = None, view_layer: str | None = None,
                     split: bool = False) -> str:
    """`name`; for 'auto' it says on stdout what `auto` does with the sequence's first frame's layers (read
    from its header, in its dialect; with `split`, the halves of two renders too)."""
    from service import pipelines
    from service.exr import list_sequence, read_header

    if name != AUTO:
        return name
    first = list_sequence(in_dir)[0]
    layers = read_header(first, mapping, view_layer).layers | ({"colorA", "colorB"} if split else set())
    if {"colorA", "colorB"} <= layers:
        print(f"pipeline: auto (per tile among the candidates that {first.name}'s layers feed)")
    else:
        print(f"pipeline: auto -> {pipelines.auto(layers)} ({first.name} has no half buffers)")
    return name
