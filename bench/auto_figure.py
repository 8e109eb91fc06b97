"""`python -m bench.auto_figure SEQUENCE OUT.png [--frame N]`: how `auto` blended its candidates on one frame,
beside its `error` layer and the true error.

`auto` runs over the sequence (every frame up to N, the last by default, in order, as it would be served);
the figure shows, for frame N: the reference and `auto`'s output (service.preview.tonemap), each tile's
blend (the candidates' colours mixed by their weights) and the `error` layer (the reference-free estimate,
FRAME_FORMAT.md), both from the last evaluation up to frame N (named in the panels), and the true relL2 of
`auto`'s output per tile (`service.metrics.rel_l2_map` averaged over the same tiles), the last two on one
log scale.
The sequence's frames need `colorA`, `colorB` and `reference`.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.colors  # noqa: E402  (the backend must be chosen first)
import matplotlib.patches  # noqa: E402
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from service import pipelines  # noqa: E402
from service.exr import list_sequence, read_frame  # noqa: E402
from service.metrics import rel_l2_map  # noqa: E402
from service.preview import tonemap  # noqa: E402
from service.process import configure  # noqa: E402
from service.stages.error_estimate import tile_means  # noqa: E402


def run_auto(folder: Path, frame_index: int | None = None) -> dict:
    """`auto` over `folder`'s frames up to `frame_index` (the last when None). Returns a dict: `reference`,
    `color` (H, W, 3) float32, `error` (H, W) float32 (the estimate), `truth` (th, tw) float64 (the true relL2
    of `color` per tile), `blend` (K, th, tw) float64 weights of `candidates` (names), `tile` (pixels), `frame`,
    `evaluated`, the frame whose evaluation gave the blend and the estimate, and `shares` (AutoState.shares)."""
    paths = list_sequence(folder)
    index = len(paths) - 1 if frame_index is None else frame_index
    if not 0 <= index < len(paths):
        raise ValueError(f"{folder}: frame {index} is not in 0..{len(paths) - 1}")
    pipeline = pipelines.get(pipelines.AUTO)
    state = None
    try:
        for path in paths[: index + 1]:
            frame = read_frame(path)
            frame.require(("colorA", "colorB", "reference"), who="bench.auto_figure")
            state = state if state is not None else pipeline.start(frame.height, frame.width)
            out, state = pipeline.step(frame, state)
        tile = pipeline.options.tile
        return {"reference": frame["reference"], "color": out["color"], "error": out["error"][..., 0],
                "truth": tile_means(rel_l2_map(out["color"], frame["reference"]), tile), "blend": state.blend,
                "candidates": list(state.candidates), "tile": tile, "frame": index, "evaluated": state.evaluated,
                "shares": state.shares()}
    finally:
        if state is not None:
            state.close()


def write_figure(result: dict, out: Path, title: str) -> None:
    """The five panels of the module docstring into `out` (PNG)."""
    tile, (height, width) = result["tile"], result["color"].shape[:2]
    extent = (0, width, height, 0)
    names = result["candidates"]
    fig, axes = plt.subplots(1, 5, figsize=(17, 3.8), dpi=100)
    axes[0].imshow(tonemap(result["reference"]))
    axes[0].set_title("reference", fontsize=9)
    axes[1].imshow(tonemap(result["color"]))
    axes[1].set_title(f"auto, frame {result['frame']} (blend from frame {result['evaluated']})", fontsize=9)
    palette = np.array(plt.get_cmap("tab10").colors[: len(names)])
    axes[2].imshow(np.einsum("kyx,kc->yxc", result["blend"], palette), extent=extent, interpolation="nearest")
    handles = [matplotlib.patches.Patch(color=c, label=n) for c, n in zip(palette, names, strict=True)]
    axes[2].legend(handles=handles, fontsize=7, loc="lower right")
    axes[2].set_title(f"weights per {tile}x{tile} tile (colours mixed)", fontsize=9)
    floor = 1e-5
    truth = np.maximum(result["truth"], floor)
    estimate = np.maximum(result["error"], floor)
    norm = matplotlib.colors.LogNorm(vmin=max(min(truth.min(), estimate.min()), floor),
                                     vmax=max(truth.max(), estimate.max(), 2 * floor))
    axes[3].imshow(estimate, norm=norm, cmap="magma")
    axes[3].set_title(f"`error` layer (frame {result['evaluated']}'s estimate)", fontsize=9)
    shown = axes[4].imshow(truth, norm=norm, cmap="magma", extent=extent, interpolation="nearest")
    axes[4].set_title("true relL2 of the output per tile", fontsize=9)
    fig.colorbar(shown, ax=axes[3:], fraction=0.03)
    for ax in axes:
        ax.set_xticks([])
        ax.set_yticks([])
    fig.suptitle(title, fontsize=10)
    fig.savefig(out, format="png")
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    configure()
    parser = argparse.ArgumentParser(prog="python -m bench.auto_figure", description=__doc__.splitlines()[0])
    parser.add_argument("sequence", type=Path)
    parser.add_argument("out", type=Path)
    parser.add_argument("--frame", type=int, default=None, help="frame index (default: the last)")
    args = parser.parse_args(argv)
    result = run_auto(args.sequence, args.frame)
    write_figure(result, args.out, f"{args.sequence.name}: auto's blend, its error estimate and the true error")
    print(", ".join(f"{n} {100 * c:.0f}%" for n, c in result["shares"].items()) + f"; written {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
