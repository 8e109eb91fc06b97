"""`python -m bench.error_estimate --sequences DIR... [--pipelines NAME...] [--tile 32]`: how well the
reference-free error estimate (service/stages/error_estimate.py) ranks denoisers, tile by tile.

Per sequence, every candidate runs through its own state on the frames as they are, giving f(C), and at
every frame, from a copy of that state before the frame, on the frame whose `color` is half A alone or
half B alone (the halves removed), giving f(A) and f(B): as `auto` evaluates a candidate it runs, here at
every frame. Per frame and tile, with scale the median of the candidates' f(A) and f(B), and m the median of
their f(C):
- one way: `tile_error(f(A), colorA, colorB, scale, cap=FIREFLY_CAP)`;
- both ways: `cross_tile_error(f(A), f(B), ...)`, the estimate auto chooses by (service/pipelines/tiled.py);
- controlled: both ways with m as scale and control variate (`control=m`), the estimate auto's `error` layer
  is made of (there m is the median of the candidates it evaluates);
- averaged: controlled, averaged with the previous frame's (weights 1/2, 1/2) in the tiles whose content moved
  by at most `tiled.MOVED` pixels (`motion`), from the third frame on, as auto averages an evaluation with the
  previous one. Not auto's exact estimate: here every candidate runs, and is evaluated, at every frame, while
  auto evaluates at the first two frames and every `every` frames, a temporal candidate it does not run from
  a state stepped through the previous frame only;
- the truth: the tile's relL2 of f(C) against the reference (what a per-tile choice would serve), and of
  f(A) (what the one-way estimate estimates).
Printed per sequence: Spearman's rank correlation between each estimate and the truth over the (frame,
tile) pairs of each candidate, its median over candidates ("rho 1-way", "rho both", "rho ctrl", "rho avg"),
and the averaged estimate's over all (frame, tile, candidate) triples; then, for both ways averaged the
same way (the control variate is the same for every candidate in a tile, so it changes no choice), the share
of tiles whose estimated best candidate is the true best and the relL2 of a frame assembled per tile from
the estimated best candidate's f(C) ("chosen"), beside the best single candidate's and the per-tile
oracle's. Candidates must run without the half buffers (not crossregression or crossreg, which need them).
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from service.exr import list_sequence, read_frame
from service.frame import Frame
from service.metrics import rel_l2, rel_l2_map
from service.pipelines.tiled import CANDIDATES, FIREFLY_CAP, HALVES, MOVED, one_half, run_half, tile_motion
from service.process import configure
from service.stages.error_estimate import TILE, cross_tile_error, tile_error, tile_means

DEFAULT_CANDIDATES = CANDIDATES
def spearman(x: np.ndarray, y: np.ndarray) -> float:
    """Spearman's rank correlation of two 1-D arrays (ties broken by position: float errors rarely tie)."""
    rx, ry = (np.argsort(np.argsort(v)).astype(np.float64) for v in (x, y))
    rx -= rx.mean()
    ry -= ry.mean()
    return float((rx * ry).sum() / np.sqrt((rx * rx).sum() * (ry * ry).sum()))


def assemble(outputs: np.ndarray, choice: np.ndarray, tile: int) -> np.ndarray:
    """(H, W, 3) frame taking each tile from the candidate `choice[ty, tx]` indexes in `outputs` (K, H, W, 3)."""
    height, width = outputs.shape[1:3]
    index = np.repeat(np.repeat(choice, tile, axis=0), tile, axis=1)[:height, :width]
    return np.take_along_axis(outputs, index[None, :, :, None], axis=0)[0]


@dataclass
class SequenceReport:
    name: str
    candidates: list[str]
    one_way: list[float]  # Spearman, one-way estimate vs f(C) truth over (frame, tile), per candidate
    both_ways: list[float]  # the same for the estimate both ways
    controlled: list[float]  # the same both ways with the control variate
    per_candidate: list[float]  # the same for the averaged controlled estimate
    pooled: float  # Spearman of the averaged estimate over (frame, tile, candidate)
    pooled_half: float  # the one-way estimate's against f(A)'s true error
    best_match: float  # share of (frame, tile) whose estimated best (averaged) is the true best (f(C))
    chosen: float  # mean relL2 over frames of the frame assembled from the estimated best per tile
    best_single: tuple[str, float]  # the candidate of lowest mean relL2, and it
    oracle: float  # mean relL2 of the frame assembled from the true best per tile


def evaluate(folder: Path, names: list[str], tile: int = TILE) -> SequenceReport:
    from service import pipelines

    frames = [read_frame(p) for p in list_sequence(folder)]
    if not all("reference" in f and "colorA" in f and "colorB" in f for f in frames):
        raise ValueError(f"{folder}: frames need 'reference', 'colorA' and 'colorB'")
    runs = {n: _run(pipelines.get(n), frames) for n in names}
    full, half_a, half_b = ({n: run[k] for n, run in runs.items()} for k in range(3))
    one, both, ctrl, avg, avg_ctrl, truth, truth_half = [], [], [], [], [], [], []
    chosen, oracle, single = [], [], {n: [] for n in names}
    for i, frame in enumerate(frames):
        a, b = frame["colorA"], frame["colorB"]
        outs = np.stack([full[n][i] for n in names])
        scale = np.median([half_a[n][i] for n in names] + [half_b[n][i] for n in names], axis=0)
        consensus = np.median(outs, axis=0)
        one.append(np.stack([tile_error(half_a[n][i], a, b, scale, tile, cap=FIREFLY_CAP).mean for n in names]))
        both.append(np.stack([cross_tile_error(half_a[n][i], half_b[n][i], a, b, scale, tile, cap=FIREFLY_CAP).mean
                              for n in names]))
        ctrl.append(np.stack([cross_tile_error(half_a[n][i], half_b[n][i], a, b, consensus, tile, cap=FIREFLY_CAP,
                                               control=consensus).mean for n in names]))
        keep = i > 1 and _static(frame, tile)
        avg.append(np.where(keep, 0.5 * (avg[-1] + both[-1]), both[-1]) if i else both[-1])
        avg_ctrl.append(np.where(keep, 0.5 * (avg_ctrl[-1] + ctrl[-1]), ctrl[-1]) if i else ctrl[-1])
        t = np.stack([tile_means(rel_l2_map(full[n][i], frame["reference"]), tile) for n in names])
        truth.append(t)
        truth_half.append(np.stack([tile_means(rel_l2_map(half_a[n][i], frame["reference"]), tile) for n in names]))
        chosen.append(rel_l2(assemble(outs, avg[-1].argmin(axis=0), tile), frame["reference"]))
        oracle.append(rel_l2(assemble(outs, t.argmin(axis=0), tile), frame["reference"]))
        for n in names:
            single[n].append(rel_l2(full[n][i], frame["reference"]))
    # (K, frames, th, tw)
    one, both, ctrl, avg, est, truth, truth_half = (np.stack(x, axis=1)
                                                    for x in (one, both, ctrl, avg, avg_ctrl, truth, truth_half))
    means = {n: float(np.mean(v)) for n, v in single.items()}
    best = min(means, key=means.get)

    def per_candidate(e: np.ndarray) -> list[float]:
        return [spearman(e[k].ravel(), truth[k].ravel()) for k in range(len(names))]

    return SequenceReport(
        folder.name, names, per_candidate(one), per_candidate(both), per_candidate(ctrl), per_candidate(est),
        spearman(est.ravel(), truth.ravel()), spearman(one.ravel(), truth_half.ravel()),
        float((avg.argmin(axis=0) == truth.argmin(axis=0)).mean()),
        float(np.mean(chosen)), (best, means[best]), float(np.mean(oracle)),
    )


def _static(frame: Frame, tile: int) -> np.ndarray | bool:
    """Per tile, whether `frame`'s content moved by at most MOVED pixels on average since the previous frame
    (`motion`; without it, everywhere), as auto decides what to average."""
    if "motion" not in frame:
        return True
    return tile_motion(frame["motion"], tile) <= MOVED


def _run(pipeline, frames: list[Frame]) -> tuple[list[np.ndarray], list[np.ndarray], list[np.ndarray]]:
    """The pipeline's outputs f(C), f(A), f(B) per frame, each (H, W, 3): f(C) through its own state, f(A) and
    f(B) each from a copy of that state before the frame (as `auto` evaluates a running candidate)."""
    state = pipeline.start(frames[0].height, frames[0].width)
    outs: tuple[list[np.ndarray], list[np.ndarray], list[np.ndarray]] = ([], [], [])
    for frame in frames:
        for half, kept in zip(HALVES, outs[1:], strict=True):
            kept.append(run_half(pipeline, one_half(frame, half), state))
        out, state = pipeline.step(frame, state)
        outs[0].append(out["color"])
    state.close()
    return outs


def main(argv: list[str] | None = None) -> int:
    configure()
    parser = argparse.ArgumentParser(prog="python -m bench.error_estimate", description=__doc__.splitlines()[0])
    parser.add_argument("--sequences", type=Path, nargs="+", required=True)
    parser.add_argument("--pipelines", nargs="+", default=list(DEFAULT_CANDIDATES))
    parser.add_argument("--tile", type=int, default=TILE)
    args = parser.parse_args(argv)
    print(f"tile {args.tile}; candidates {', '.join(args.pipelines)}")
    print(f"{'sequence':14s} {'rho 1-way':>9s} {'rho both':>8s} {'rho ctrl':>8s} {'rho avg':>7s} {'rho all':>7s} "
          f"{'rho f(A)':>8s} {'best hit':>8s} {'chosen':>8s} {'best single':>22s} {'oracle':>8s}")
    for folder in args.sequences:
        r = evaluate(folder, args.pipelines, args.tile)
        print(f"{r.name:14s} {np.median(r.one_way):9.3f} {np.median(r.both_ways):8.3f} {np.median(r.controlled):8.3f} "
              f"{np.median(r.per_candidate):7.3f} {r.pooled:7.3f} {r.pooled_half:8.3f} {r.best_match:8.2f} "
              f"{r.chosen:8.4f} {r.best_single[0]:>12s} {r.best_single[1]:8.4f} {r.oracle:8.4f}")
        print(" " * 15 + "rho avg per candidate: " + ", ".join(
            f"{n} {v:.3f}" for n, v in zip(r.candidates, r.per_candidate, strict=True)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
