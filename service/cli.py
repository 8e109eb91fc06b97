"""`python -m service ...`: denoise a sequence folder, list pipelines, inspect an EXR file, compile kernels ahead.

Exit status: 0 on success, 2 with a one-line `error: ...` on bad input or options.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from service import pipelines
from service.api.cli import add_serve_args, add_stream_args, run_serve, run_stream
from service.exr import list_sequence, read_channels, read_header
from service.frame import FrameError
from service.sequence import denoise_folder
from service.warmup import CompileNotice, warm_up


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


def cmd_denoise(args: argparse.Namespace) -> int:
    options = parse_options(args.option)
    if args.online:
        options["online"] = True  # a pipeline without this option refuses it: "has no option 'online'"
    pipeline = pipelines.get(resolve_pipeline(args.pipeline, args.in_dir), **options)
    print(f"{'frame':<24} {'ms':>9} {'relL2 in':>10} {'relL2 out':>10} {'NaN/Inf':>8}", flush=True)
    results = []
    with CompileNotice(pipeline.name) as notice:  # a frame's ms include any kernels compiled for it
        for r in denoise_folder(pipeline, args.in_dir, args.out_dir, png=args.png):
            notice.report()
            results.append(r)
            noisy = "" if r.rel_l2_noisy is None else f"{r.rel_l2_noisy:.4f}"
            out = "" if r.rel_l2_out is None else f"{r.rel_l2_out:.4f}"
            print(f"{r.name:<24} {r.ms:>9.1f} {noisy:>10} {out:>10} {r.nonfinite:>8}", flush=True)
    ms = [r.ms for r in results]
    line = f"{pipeline.name}: {len(results)} frames, median {np.median(ms):.1f} ms/frame (mean {np.mean(ms):.1f})"
    scored = [r for r in results if r.rel_l2_out is not None]
    if scored:
        noisy = np.mean([r.rel_l2_noisy for r in scored])
        out = np.mean([r.rel_l2_out for r in scored])
        line += f", relL2 (0.1% trimmed) {noisy:.4f} -> {out:.4f}"
    print(line)
    if results and results[-1].online is not None:
        status = results[-1].online
        print(f"online training: {status['state']}, {status['frames_trained']} frames trained, "
              f"{status['frames_dropped']} dropped, weights version {status['weights_version']}"
              + (f", last error: {status['last_error']}" if status.get("last_error") else ""))
    print(f"outputs in {args.out_dir}")
    return 0


def cmd_pipelines(args: argparse.Namespace) -> int:
    infos = pipelines.describe()
    if args.json:
        print(json.dumps(infos, indent=2))
        return 0
    for info in infos:
        flag = " (temporal)" if info["temporal"] else ""
        default = " [default]" if info["name"] == pipelines.DEFAULT else ""
        print(f"{info['name']}{flag}{default}: {info['summary']}")
        print(f"    requires: {', '.join(info['requires']) or '-'}")
        print(f"    optional: {', '.join(info['optional']) or '-'}")
        for option, spec in info["option_specs"].items():
            print(f"    option {option} = {json.dumps(spec['default'])}: {spec['allowed']}")
    return 0


def cmd_inspect(args: argparse.Namespace) -> int:
    channels, header = read_channels(args.file)
    first = next(iter(channels.values()))
    print(f"{args.file}: {first.shape[1]}x{first.shape[0]}, {len(channels)} channels, "
          f"compression {header.get('compression')}")
    print(f"{'channel':<16} {'type':<8} {'min':>12} {'max':>12} {'mean':>12} {'NaN':>7} {'Inf':>7}")
    for name in sorted(channels):
        pixels = channels[name]
        kind = {"float16": "half", "float32": "float", "uint32": "uint"}.get(pixels.dtype.name, pixels.dtype.name)
        values = pixels.astype(np.float64)
        finite = values[np.isfinite(values)]
        lo, hi, mean = (finite.min(), finite.max(), finite.mean()) if finite.size else (np.nan,) * 3
        print(f"{name:<16} {kind:<8} {lo:>12.5g} {hi:>12.5g} {mean:>12.5g} "
              f"{int(np.isnan(values).sum()):>7} {int(np.isinf(values).sum()):>7}")
    return 0


def cmd_warm(args: argparse.Namespace) -> int:
    """Compile (or load from the cache) the kernels of the named pipelines, or of all, by `warm_up`."""
    names = args.names or pipelines.names()
    for name in names:
        pipelines.pipeline_class(name)  # an unknown name fails before any compiling
    for name in names:
        with CompileNotice(name):
            seconds = warm_up(pipelines.get(name))
        print(f"{name}: ready in {seconds:.1f} s", flush=True)
    return 0


Command = tuple[str, str, Callable[[argparse.ArgumentParser], None], Callable[[argparse.Namespace], int]]


def resolve_pipeline(name: str, in_dir: Path) -> str:
    """`name`, or for 'auto' the preferred pipeline whose required layers the sequence's first frame has
    (read from its header); says which on stdout."""
    if name != pipelines.AUTO:
        return name
    first = list_sequence(in_dir)[0]
    name = pipelines.auto(read_header(first).layers)
    print(f"pipeline: {name} (auto: the preferred pipeline whose layers {first.name} has)")
    return name


def add_sequence_args(p: argparse.ArgumentParser) -> None:
    """Arguments of the commands that run a sequence folder through a pipeline (`denoise`, `stream`)."""
    p.add_argument("in_dir", type=Path, help="sequence folder of frame EXR files")
    p.add_argument("out_dir", type=Path, help="folder for the denoised EXR files (same names)")
    p.add_argument("--pipeline", default=pipelines.AUTO,
                   help="pipeline name, or 'auto' (default): the best pipeline the first frame's layers can feed")
    p.add_argument("--option", "-o", action="append", default=[], metavar="KEY=VALUE",
                   help="pipeline option, repeatable (see `pipelines --json`)")
    p.add_argument("--online", action="store_true",
                   help="fine-tune the pipeline's network while the sequence runs (sets option online=true)")


def _args_denoise(p: argparse.ArgumentParser) -> None:
    add_sequence_args(p)
    p.add_argument("--png", action="store_true", help="also write tone-mapped PNG previews")


def _args_pipelines(p: argparse.ArgumentParser) -> None:
    p.add_argument("--json", action="store_true", help="machine-readable output")


def _args_inspect(p: argparse.ArgumentParser) -> None:
    p.add_argument("file", type=Path, help="an OpenEXR file")


def _args_warm(p: argparse.ArgumentParser) -> None:
    p.add_argument("names", nargs="*", metavar="PIPELINE", help="pipelines to warm (default: all)")


COMMANDS: list[Command] = [
    ("denoise", "denoise every frame of a sequence folder", _args_denoise, cmd_denoise),
    ("pipelines", "list pipelines with their required and optional layers", _args_pipelines, cmd_pipelines),
    ("inspect", "layers, channel types, size and value statistics of an EXR file", _args_inspect, cmd_inspect),
    ("warm", "compile the numba kernels of pipelines ahead of their first frame (cached per machine)", _args_warm,
     cmd_warm),
    ("serve", "serve every pipeline over HTTP: REST frames, sessions, WebSocket streams", add_serve_args, run_serve),
    ("stream", "stream a sequence folder through a running service, write the results", add_stream_args, run_stream),
]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m service", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    for name, help_text, add_args, run in COMMANDS:
        p = sub.add_parser(name, help=help_text, description=help_text)
        add_args(p)
        p.set_defaults(run=run)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.run(args)
    except (FrameError, ValueError, KeyError, OSError) as err:
        message = str(err).splitlines()[0] if str(err) else type(err).__name__
        print(f"error: {message}", file=sys.stderr)
        return 2
