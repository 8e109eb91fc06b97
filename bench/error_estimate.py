"""`python -m bench.error_estimate --sequences DIR... [--pipelines NAME...] [--tile 32]`: how well the
reference-free error estimate (service/stages/error_estimate.py) ranks denoisers, tile by tile.

Per sequence, every candidate runs twice through its own state: on the frames as they are, giving f(C),
and on frames whose `color` is half A alone (the halves removed), giving f(A). Per frame and tile:
- the estimate auto's is made of (service/pipelines/tiled.py): `tile_error(f(A), colorA, colorB, scale,
  cap=FIREFLY_CAP)`, scale the median of the candidates' f(A). Not auto's exact estimate: here f(A) runs
  every frame through its own state (a temporal candidate with its history), while auto runs it from a
  fresh state every `every` frames and averages with the previous evaluation;
- the truth: the tile's relL2 of f(C) against the reference (what a per-tile choice would serve), and of
  f(A) (what the estimate estimates).
Printed per sequence: Spearman's rank correlation between estimate and truth over the (frame, tile) pairs
of each candidate, its median over candidates, and over all (frame, tile, candidate) triples; the share
of tiles whose estimated best candidate is the true best; and the relL2 of a frame assembled per tile from
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
from service.pipelines.tiled import CANDIDATES, FIREFLY_CAP, half_a
from service.process import configure
from service.stages.error_estimate import TILE, tile_error, tile_means

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
    per_candidate: list[float]  # Spearman estimate vs f(C) truth over (frame, tile), per candidate
    pooled: float  # Spearman over (frame, tile, candidate)
    pooled_half: float  # the same against f(A)'s true error
    best_match: float  # share of (frame, tile) whose estimated best is the true best (f(C))
    chosen: float  # mean relL2 over frames of the frame assembled from the estimated best per tile
    best_single: tuple[str, float]  # the candidate of lowest mean relL2, and it
    oracle: float  # mean relL2 of the frame assembled from the true best per tile


def evaluate(folder: Path, names: list[str], tile: int = TILE) -> SequenceReport:
    from service import pipelines

    frames = [read_frame(p) for p in list_sequence(folder)]
    if not all("reference" in f and "colorA" in f and "colorB" in f for f in frames):
        raise ValueError(f"{folder}: frames need 'reference', 'colorA' and 'colorB'")
    full = {n: _run(pipelines.get(n), frames) for n in names}
    half = {n: _run(pipelines.get(n), [half_a(f) for f in frames]) for n in names}
    est, truth, truth_half, chosen, oracle, single = [], [], [], [], [], {n: [] for n in names}
    for i, frame in enumerate(frames):
        outs = np.stack([full[n][i] for n in names])
        scale = np.median([half[n][i] for n in names], axis=0)
        e = np.stack([tile_error(half[n][i], frame["colorA"], frame["colorB"], scale, tile, cap=FIREFLY_CAP).mean
                      for n in names])
        t = np.stack([tile_means(rel_l2_map(full[n][i], frame["reference"]), tile) for n in names])
        th = np.stack([tile_means(rel_l2_map(half[n][i], frame["reference"]), tile) for n in names])
        est.append(e)
        truth.append(t)
        truth_half.append(th)
        chosen.append(rel_l2(assemble(outs, e.argmin(axis=0), tile), frame["reference"]))
        oracle.append(rel_l2(assemble(outs, t.argmin(axis=0), tile), frame["reference"]))
        for n in names:
            single[n].append(rel_l2(full[n][i], frame["reference"]))
    est, truth, truth_half = (np.stack(a, axis=1) for a in (est, truth, truth_half))  # (K, frames, th, tw)
    means = {n: float(np.mean(v)) for n, v in single.items()}
    best = min(means, key=means.get)
    return SequenceReport(
        folder.name, names,
        [spearman(est[k].ravel(), truth[k].ravel()) for k in range(len(names))],
        spearman(est.ravel(), truth.ravel()), spearman(est.ravel(), truth_half.ravel()),
        float((est.argmin(axis=0) == truth.argmin(axis=0)).mean()),
        float(np.mean(chosen)), (best, means[best]), float(np.mean(oracle)),
    )


def _run(pipeline, frames: list[Frame]) -> list[np.ndarray]:
    state = pipeline.start(frames[0].height, frames[0].width)
    outs = []
    for frame in frames:
        out, state = pipeline.step(frame, state)
        outs.append(out["color"])
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
    print(f"{'sequence':14s} {'rho med':>7s} {'rho all':>7s} {'rho f(A)':>8s} {'best hit':>8s} "
          f"{'chosen':>8s} {'best single':>22s} {'oracle':>8s}")
    for folder in args.sequences:
        r = evaluate(folder, args.pipelines, args.tile)
        print(f"{r.name:14s} {np.median(r.per_candidate):7.3f} {r.pooled:7.3f} {r.pooled_half:8.3f} "
              f"{r.best_match:8.2f} {r.chosen:8.4f} {r.best_single[0]:>12s} {r.best_single[1]:8.4f} {r.oracle:8.4f}")
        print(" " * 15 + "per candidate: " + ", ".join(f"{n} {v:.3f}" for n, v in zip(r.candidates, r.per_candidate,
                                                                                        strict=True)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
