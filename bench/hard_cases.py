"""Rendered hard cases: small path-traced frames of what real renderers send, judged per tile.

Each case is a short sequence rendered by `models.data` (Mitsuba 3) from the scene library, committed
under `models/data/samples/hard/<sequence>` so that `make test` needs no renderer. Several cases share
one rendered sequence and differ in what the denoiser is given: most renderers write no `emission`
layer, so the cases with a visible emitter drop it.

A pipeline passes a case when, on every frame:
1. the relL2 of its output (untrimmed, `service.metrics.rel_l2`) is below MAX_OVERALL_RATIO times the
   noisy input's;
2. no TILE x TILE tile is worse than the noisy input there: with e(x) the mean of `rel_l2_map(x, ref)`
   over the tile, e(out) + TILE_FLOOR <= (1 + TILE_SLACK) (e(noisy) + TILE_FLOOR). A mean over the frame
   can hide a black ring around a light; a tile cannot;
3. pixels the renderer computed exactly (both halves agree and, with an emission layer, the pixel is all
   emission: `service.stages.exact.exact_mask`) come out as they went in, to EXACT_RTOL.

`python -m bench.hard_cases render` renders the sequences (5 min 26 s on 2 cores with Mitsuba's
scalar variant); `python -m bench.hard_cases table [--pipelines ...]` prints relL2 and the worst tile
ratio per pipeline and case, with OIDN-high when `pyoidn` is installed.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from service.exr import read_sequence
from service.frame import Frame
from service.metrics import rel_l2_map
from service.pipelines.base import Pipeline
from service.process import configure
from service.stages.error_estimate import tile_means as stage_tile_means
from service.stages.exact import exact_mask

HARD_DIR = Path(__file__).resolve().parents[1] / "models" / "data" / "samples" / "hard"
TILE = 16  # tile side of the per-tile check, pixels
TILE_FLOOR = 1e-3  # added to both tile errors, so that tiles with no noise compare sanely (relL2 units)
TILE_SLACK = 0.10  # a tile may be at most 10% worse than the noisy input's tile
MAX_OVERALL_RATIO = 0.5  # the frame's relL2 must be below half the noisy input's
EXACT_RTOL = 1e-4  # exact pixels come out within this relative difference of their input


@dataclass(frozen=True)
class Sequence:
    """One rendered sequence of the hard-case set (`python -m models.data render` arguments)."""

    scene: str
    spp: int
    seed: int = 0
    frames: int = 2
    size: int = 64  # square frames, pixels
    ref_spp: int = 2048


@dataclass(frozen=True)
class Case:
    """A hard case: a rendered sequence and what the denoiser is given of it."""

    name: str
    sequence: str  # key of SEQUENCES
    emission: bool  # whether the frames keep their `emission` layer
    what: str  # one line: what makes it hard


SEQUENCES: dict[str, Sequence] = {
    "bulb": Sequence("fireflies", spp=2),
    "caustics": Sequence("fireflies", spp=2, seed=1),
    "veiled": Sequence("veiled_light", spp=4),
    "dark": Sequence("dark", spp=4),
    "window": Sequence("window", spp=8),
    "window_1spp": Sequence("window", spp=2, seed=1),
    "glints": Sequence("glossy_env", spp=2),
}

CASES: tuple[Case, ...] = (
    Case("bulb", "bulb", False, "a visible sphere light of radiance 3e3, no emission layer, 2 spp"),
    Case("bulb_emission", "bulb", True, "the same with the emission layer"),
    Case("caustics", "caustics", True, "caustic fireflies of ~1e3 from glossy metal at 1 spp per half"),
    Case("veiled", "veiled", False, "a light of radiance 1e3 partly covered by thin bars, no emission layer"),
    Case("dark", "dark", True, "a dim room (radiance ~1e-2) lit by a weak point light and a small window"),
    Case("window", "window", False, "a sky of radiance 1e3 seen through a window, no emission layer"),
    Case("window_1spp", "window_1spp", False, "the same at 1 spp per half: every pixel a firefly-heavy estimate"),
    Case("glints", "glints", False, "near-mirror metal under a sun of radiance 2e4, 1 spp per half"),
)
_BY_NAME = {c.name: c for c in CASES}
CASE_NAMES = tuple(_BY_NAME)


def case(name: str) -> Case:
    """The case `name`; ValueError listing the names when unknown."""
    try:
        return _BY_NAME[name]
    except KeyError:
        raise ValueError(f"unknown hard case '{name}'; cases: {', '.join(CASE_NAMES)}") from None


def frames(name: str, folder: Path = HARD_DIR) -> list[Frame]:
    """The frames of case `name`, as the denoiser gets them (with `reference`, for scoring)."""
    c = case(name)
    seq = [frame for _path, frame in read_sequence(folder / c.sequence)]
    if c.emission:
        return seq
    return [Frame({k: v for k, v in f.buffers.items() if k != "emission"}, dict(f.nonfinite)) for f in seq]


@dataclass(frozen=True)
class FrameScore:
    """How one output frame compares with its noisy input, against the reference."""

    rel_l2: float  # untrimmed relL2 of the output
    noisy_rel_l2: float  # untrimmed relL2 of the noisy `color`
    worst_tile_ratio: float  # max over tiles of (e(out) + TILE_FLOOR) / (e(noisy) + TILE_FLOOR)
    worst_tile: tuple[int, int]  # (row, column) of that tile's top-left pixel
    exact_error: float  # largest relative change of an exact pixel (0 when there is none)

    def failures(self) -> list[str]:
        """Why the frame fails the case's criterion; empty when it passes."""
        out = []
        if not self.rel_l2 < MAX_OVERALL_RATIO * self.noisy_rel_l2:
            out.append(f"relL2 {self.rel_l2:.4g} is not below {MAX_OVERALL_RATIO} x noisy {self.noisy_rel_l2:.4g}")
        if self.worst_tile_ratio > 1.0 + TILE_SLACK:
            out.append(f"tile at {self.worst_tile} is {self.worst_tile_ratio:.3g}x the noisy input's error")
        if self.exact_error > EXACT_RTOL:
            out.append(f"an exact pixel changed by {self.exact_error:.3g} (relative)")
        return out


def tile_means(errors: np.ndarray, tile: int = TILE) -> np.ndarray:
    """Mean of `errors` ((H, W) float64) over each tile x tile tile (the stage's, at the criterion's tile)."""
    return stage_tile_means(errors, tile)


def tile_ratios(out_map: np.ndarray, noisy_map: np.ndarray) -> np.ndarray:
    """Criterion 2's ratio per TILE x TILE tile, (e(out) + TILE_FLOOR) / (e(noisy) + TILE_FLOOR), from the
    output's and the noisy input's (H, W) relL2 maps (`rel_l2_map`); (th, tw) float64, ragged border tiles
    included. The tile passes at 1 + TILE_SLACK or below."""
    return (tile_means(out_map) + TILE_FLOOR) / (tile_means(noisy_map) + TILE_FLOOR)


def worst_tile(ratios: np.ndarray) -> tuple[float, tuple[int, int]]:
    """(the largest of `tile_ratios`' ratios, (row, column) of that tile's top-left pixel)."""
    worst = np.unravel_index(int(np.argmax(ratios)), ratios.shape)
    return float(ratios[worst]), (int(worst[0]) * TILE, int(worst[1]) * TILE)


def score(out: np.ndarray, frame: Frame) -> FrameScore:
    """Score `out` ((H, W, 3) float32 denoised radiance) against `frame`'s noisy `color` and `reference`."""
    reference, noisy = frame["reference"], frame["color"]
    out_map, noisy_map = rel_l2_map(out, reference), rel_l2_map(noisy, reference)
    ratio, at = worst_tile(tile_ratios(out_map, noisy_map))
    exact = None
    if "colorA" in frame and "colorB" in frame:
        exact = exact_mask(frame["colorA"], frame["colorB"], frame["color"], frame.get("emission"))
    exact_error = 0.0
    if exact is not None and exact.any():
        given = noisy[exact].astype(np.float64)
        change = np.abs(out[exact] - given) / np.maximum(np.abs(given), 1e-30)
        exact_error = float(change.max())
    return FrameScore(float(out_map.mean()), float(noisy_map.mean()), ratio, at, exact_error)


def run(pipeline: Pipeline, name: str) -> list[FrameScore]:
    """Scores of `pipeline` over case `name`'s frames, stepped in order as one sequence."""
    seq = frames(name)
    state = pipeline.start(seq[0].height, seq[0].width)
    scores = []
    for frame in seq:
        out, state = pipeline.step(frame, state)
        scores.append(score(out["color"], frame))
    state.close()
    return scores


# ----------------------------------------------------------------------------------------------- commands


def render(names: list[str], folder: Path = HARD_DIR) -> None:
    """Render the sequences `names` (keys of SEQUENCES) into `folder`, skipping finished ones."""
    from models.data import scenes
    from models.data.render import RenderOptions
    from models.data.sequence import render_sequence

    for name in names:
        seq, out = SEQUENCES[name], folder / name
        if (out / "sequence.json").is_file():
            print(f"{name}: exists, skipped")
            continue
        opts = RenderOptions(seq.size, seq.size, seq.spp, seq.ref_spp, seed=seq.seed)
        seconds = render_sequence(scenes.get(seq.scene), out, opts, seq.frames)
        print(f"{name}: {seq.frames} frames in {sum(seconds):.1f} s -> {out}")


def table(pipeline_names: list[str], oidn: bool) -> None:
    """Print relL2 (mean over frames) and the worst tile ratio (max over frames) per method and case."""
    from bench.methods import anchor_method, pipeline_method

    methods = [pipeline_method(n) for n in pipeline_names]
    if oidn:
        methods.append(anchor_method("oidn-high"))
    print(f"{'case':14s} {'noisy':>8s} " + " ".join(f"{m.name[:18]:>18s}" for m in methods))
    for c in CASES:
        seq = frames(c.name)
        noisy = np.mean([float(rel_l2_map(f["color"], f["reference"]).mean()) for f in seq])
        cells = []
        for m in methods:
            if m.missing(set(seq[0].buffers)):
                cells.append(f"{'-':>18s}")
                continue
            scores = run(m.make(), c.name)
            rel = np.mean([s.rel_l2 for s in scores])
            tile = max(s.worst_tile_ratio for s in scores)
            ok = "" if not any(s.failures() for s in scores) else "!"
            cells.append(f"{rel:9.4g} {tile:6.3g}x{ok:1s}")
        print(f"{c.name:14s} {noisy:8.4g} " + " ".join(cells))


def main(argv: list[str] | None = None) -> int:
    configure()
    parser = argparse.ArgumentParser(prog="python -m bench.hard_cases", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)
    r = sub.add_parser("render", help="render the hard-case sequences (skips finished ones)")
    r.add_argument("names", nargs="*", help=f"sequences to render (default: all): {', '.join(SEQUENCES)}")
    t = sub.add_parser("table", help="relL2 and worst tile ratio per pipeline and case")
    t.add_argument("--pipelines", nargs="+", default=None)
    t.add_argument("--no-oidn", action="store_true")
    args = parser.parse_args(argv)
    if args.command == "render":
        unknown = sorted(set(args.names) - set(SEQUENCES))
        if unknown:
            parser.error(f"unknown sequences {unknown}; sequences: {', '.join(SEQUENCES)}")
        render(args.names or list(SEQUENCES))
        return 0
    from service import pipelines

    table(args.pipelines or pipelines.names(), oidn=not args.no_oidn)
    return 0


if __name__ == "__main__":
    sys.exit(main())
