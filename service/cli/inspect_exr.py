"""`python -m service inspect`: an EXR file's channels, pixel types, size, min/max/mean and NaN/Inf counts,
then the dialect its channels were recognised as and how each frame-format layer is made from them."""

from __future__ import annotations

import argparse
from pathlib import Path

from service.cli.sequence_args import add_dialect_args, channel_map


def add_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("file", type=Path, help="an OpenEXR file")
    add_dialect_args(p)


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from service.exr import read_channels, read_header

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
    mapping = read_header(args.file, channel_map(args), args.view_layer).mapping
    print(f"dialect: {mapping.dialect}" + "".join(f"; {note}" for note in mapping.notes))
    for layer, source in mapping.layers.items():
        print(f"  {layer:<12} <- {source.describe()}")
    return 0
