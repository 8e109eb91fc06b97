"""`python -m bench run`: every method on every sequence, in one process, under one thread setting.

For each sequence (a folder of EXR frames with a `reference` layer) and each method (bench.methods):
a warm-up of WARMUP_FRAMES steps on a throw-away state (numba compilation, ONNX session and OIDN filter
set-up happen there; two frames, so a temporal pipeline's with-history path is compiled too), then
every frame in order through a fresh state, scored, then TIMING_REPEATS - 1 more timed passes. The time
of a frame is the wall time of `pipeline.step` alone (reading the EXR and scoring are outside it); a
method's speed on a sequence is the median over the frames of all passes. Frames are read from disk
again for each pass, so memory stays at a few frames whatever the sequence length.
"""

from __future__ import annotations

import os
import time
import traceback
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from bench import environment
from bench.methods import Method
from bench.scoring import SequenceScore, disoccluded_mask, score_frame
from service.exr import list_sequence, read_frame
from service.metrics import TRIM_FRACTION
from service.pipelines.base import Pipeline
from service.pipelines.tiled import AutoState

TIMING_REPEATS = 3  # timed passes over each sequence per method; ms per frame is the median of all of them
WARMUP_FRAMES = 2  # steps on a discarded state before the timed pass: the first frame and one with history
CROP_SIZE = 96  # side of the square crop shown side by side in report.html, pixels
REFERENCE_METHOD = "oidn-high"  # the anchor the overall table compares against


@dataclass(frozen=True)
class Sequence:
    """A sequence folder as the benchmark sees it."""

    name: str
    path: Path
    frames: tuple[Path, ...]
    height: int
    width: int
    layers: frozenset[str]

    @property
    def megapixels(self) -> float:
        return self.height * self.width / 1e6


def open_sequence(path: str | Path, name: str | None = None) -> Sequence:
    """Describe the sequence in folder `path` from its first frame.

    Raises FrameError when the folder holds no EXR frame, ValueError when the frames carry no
    `reference` (nothing to score against).
    """
    path = Path(path)
    frames = tuple(list_sequence(path))
    first = read_frame(frames[0])
    if "reference" not in first:
        raise ValueError(f"sequence '{path}' has no 'reference' layer; the benchmark needs one to score")
    return Sequence(name or path.name, path, frames, first.height, first.width, frozenset(first.buffers))


def unique_names(paths: list[Path]) -> list[str]:
    """Short display names for sequence folders: the folder name, with its parent where names repeat."""
    names = [p.name for p in paths]
    return [f"{p.parent.name}/{p.name}" if names.count(p.name) > 1 else p.name for p in paths]


def choose_crop(reference: np.ndarray, size: int = CROP_SIZE) -> tuple[int, int, int, int]:
    """(y0, x0, height, width) of the square window with the most detail in `reference`.

    reference: (H, W, 3) float32 linear radiance. Detail is the variance of log(1 + luminance) in the
    window, so edges, textures and shadows win over flat regions; candidates are on a grid of
    quarter-window steps. The window is the whole frame when the frame is smaller than `size`.
    """
    height, width = reference.shape[:2]
    ch, cw = min(size, height), min(size, width)
    lum = np.log1p(np.maximum(reference.astype(np.float64).mean(axis=-1), 0.0))
    # Integral images of lum and lum^2 give each window's variance in O(1).
    s1 = np.pad(lum.cumsum(0).cumsum(1), ((1, 0), (1, 0)))
    s2 = np.pad((lum * lum).cumsum(0).cumsum(1), ((1, 0), (1, 0)))
    best, best_var = (0, 0), -1.0
    for y in range(0, height - ch + 1, max(1, ch // 4)):
        for x in range(0, width - cw + 1, max(1, cw // 4)):
            n = ch * cw
            t1 = s1[y + ch, x + cw] - s1[y, x + cw] - s1[y + ch, x] + s1[y, x]
            t2 = s2[y + ch, x + cw] - s2[y, x + cw] - s2[y + ch, x] + s2[y, x]
            var = t2 / n - (t1 / n) ** 2
            if var > best_var:
                best, best_var = (y, x), var
    return best[0], best[1], ch, cw


@dataclass
class SequenceRun:
    """Everything measured on one sequence: results per method and the crops for the HTML report."""

    sequence: Sequence
    crop: tuple[int, int, int, int]  # y0, x0, height, width, in frame `crop_frame`
    crop_frame: int
    results: dict[str, dict[str, Any]] = field(default_factory=dict)  # method -> result record
    crops: dict[str, np.ndarray] = field(default_factory=dict)  # "input", "reference", method -> (h, w, 3)


def _masks(seq: Sequence, progress: bool) -> list[np.ndarray | None]:
    """Disoccluded-pixel mask of every frame (None for the first and where the frame has no motion)."""
    masks: list[np.ndarray | None] = [None]
    prev = read_frame(seq.frames[0])
    for path in tqdm(seq.frames[1:], desc=f"{seq.name}: disocclusion", leave=False, disable=not progress):
        frame = read_frame(path)
        masks.append(disoccluded_mask(frame, prev))
        prev = frame
    return masks


def _timed_pass(pipeline: Pipeline, seq: Sequence) -> list[float]:
    """Milliseconds of `pipeline.step` for every frame of `seq` through a fresh state (no scoring)."""
    state = pipeline.start(seq.height, seq.width)
    ms = []
    for path in seq.frames:
        frame = read_frame(path)
        start = time.perf_counter()
        _, state = pipeline.step(frame, state)
        ms.append(1e3 * (time.perf_counter() - start))
    return ms


def run_method(
    method: Method, seq: Sequence, masks: list[np.ndarray | None], crop: tuple[int, int, int, int],
    crop_frame: int, *, flip: bool = True, progress: bool = True, repeats: int = TIMING_REPEATS,
) -> tuple[dict[str, Any], np.ndarray | None]:
    """Run `method` over `seq`; returns (result record, the output crop of frame `crop_frame`).

    The first pass is timed and scored; `repeats - 1` more passes through fresh states are only timed,
    so the median has repeats x frames samples on a busy machine.

    The record has status "ok" with summary, per-frame scores and timings; "skipped" with a note when
    the sequence lacks a required layer; "failed" with the error when the method raised.
    """
    missing = method.missing(seq.layers)
    if missing:
        return {"status": "skipped", "note": f"sequence lacks required layer(s) {', '.join(missing)}"}, None
    y0, x0, ch, cw = crop
    score = SequenceScore()
    out_crop = None
    shares: dict[str, float] = {}  # auto's candidates: blend weight, mean over tiles and frames
    try:
        pipeline = method.make()
        warm = pipeline.start(seq.height, seq.width)
        for path in seq.frames[:WARMUP_FRAMES]:
            _, warm = pipeline.step(read_frame(path), warm)
        state = pipeline.start(seq.height, seq.width)
        prev = None
        bar = tqdm(seq.frames, desc=f"{seq.name}: {method.name}", leave=False, disable=not progress)
        for index, path in enumerate(bar):
            frame = read_frame(path)
            start = time.perf_counter()
            out, state = pipeline.step(frame, state)
            score.ms.append(1e3 * (time.perf_counter() - start))
            if isinstance(state, AutoState):
                for name, share in state.shares().items():
                    shares[name] = shares.get(name, 0.0) + share / len(seq.frames)
            image, reference = out["color"], frame["reference"]
            score.frames.append(score_frame(image, reference, prev, masks[index], flip=flip, noisy=frame["color"]))
            prev = (image, reference)
            if index == crop_frame:
                out_crop = image[y0 : y0 + ch, x0 : x0 + cw].copy()
        for _ in range(repeats - 1):
            score.ms.extend(_timed_pass(pipeline, seq))
    except Exception as err:  # a failing method is a result, not the end of the benchmark
        return {
            "status": "failed",
            "note": f"{type(err).__name__}: {err}",
            "traceback": traceback.format_exc(limit=6),
        }, None
    return {
        "status": "ok",
        "summary": score.summary(seq.megapixels),
        "ms": score.ms,
        "per_frame": [f.as_dict() for f in score.frames],
        **({"shares": dict(sorted(shares.items(), key=lambda kv: -kv[1]))} if shares else {}),
    }, out_crop


def run_sequence(seq: Sequence, methods: list[Method], *, flip: bool = True, progress: bool = True,
                 repeats: int = TIMING_REPEATS, outer: tqdm | None = None) -> SequenceRun:
    """All methods on one sequence; crops are taken from its last frame."""
    crop_frame = len(seq.frames) - 1
    last = read_frame(seq.frames[crop_frame])
    crop = choose_crop(last["reference"])
    y0, x0, ch, cw = crop
    run = SequenceRun(seq, crop, crop_frame)
    run.crops["input"] = last["color"][y0 : y0 + ch, x0 : x0 + cw].copy()
    run.crops["reference"] = last["reference"][y0 : y0 + ch, x0 : x0 + cw].copy()
    masks = _masks(seq, progress)
    for method in methods:
        if outer is not None:
            outer.set_postfix_str(f"{seq.name} / {method.name}")
        record, out_crop = run_method(method, seq, masks, crop, crop_frame, flip=flip, progress=progress,
                                     repeats=repeats)
        run.results[method.name] = record
        if out_crop is not None:
            run.crops[method.name] = out_crop
        if outer is not None:
            outer.update(1)
    return run


def overall(runs: list[SequenceRun], methods: list[Method]) -> dict[str, dict[str, Any]]:
    """Per method, across the sequences it ran on: mean of each error, median of ms per megapixel, the largest
    worst tile and the failing tiles summed, and the geometric mean over sequences of relL2 / relL2 of
    `REFERENCE_METHOD` (OIDN high)."""
    table: dict[str, dict[str, Any]] = {}
    for method in methods:
        ok = [r for r in runs if r.results.get(method.name, {}).get("status") == "ok"]
        summaries = [r.results[method.name]["summary"] for r in ok]
        row: dict[str, Any] = {"kind": method.kind, "is_temporal": method.temporal,
                               "sequences": len(ok), "of": len(runs)}
        for key in ("rel_l2", "dssim", "flip", "temporal", "disoccluded_rel_l2"):
            values = [s[key] for s in summaries if s[key] is not None]
            row[key] = float(np.mean(values)) if values else None
        tiles = [s["worst_tile"] for s in summaries if s["worst_tile"] is not None]
        row["worst_tile"] = max(tiles) if tiles else None
        row["failing_tiles"] = sum(s["failing_tiles"] for s in summaries if s["failing_tiles"] is not None)
        ms = [s["ms_per_megapixel"] for s in summaries]
        row["ms_per_megapixel"] = float(np.median(ms)) if ms else None
        ratios = []
        for r in ok:
            anchor = r.results.get(REFERENCE_METHOD, {})
            if anchor.get("status") == "ok" and anchor["summary"]["rel_l2"]:
                ratios.append(r.results[method.name]["summary"]["rel_l2"] / anchor["summary"]["rel_l2"])
        row["rel_l2_vs_oidn_high"] = float(np.exp(np.mean(np.log(ratios)))) if ratios else None
        table[method.name] = row
    return table


def benchmark(
    sequence_dirs: list[Path], methods: list[Method], *, flip: bool = True, progress: bool = True,
    repeats: int = TIMING_REPEATS, command: list[str] | None = None,
) -> tuple[dict[str, Any], list[SequenceRun]]:
    """Run every method on every sequence. Returns (results.json content, the runs with their crops)."""
    sequences = [open_sequence(p, n) for p, n in zip(sequence_dirs, unique_names(sequence_dirs), strict=True)]
    env = environment.describe()
    started = time.perf_counter()
    runs = []
    with tqdm(total=len(sequences) * len(methods), desc="benchmark", unit="run", disable=not progress) as outer:
        for seq in sequences:
            runs.append(run_sequence(seq, methods, flip=flip, progress=progress, repeats=repeats, outer=outer))
    env["machine"]["load_average_1m_end"] = os.getloadavg()[0]  # other work on the machine skews timings
    results = {
        "created": datetime.now(UTC).isoformat(timespec="seconds"),
        "command": command,
        "wall_seconds": time.perf_counter() - started,
        "environment": env,
        "settings": {
            "warmup": f"the first {WARMUP_FRAMES} frames through a discarded state before the timed pass",
            "ms_per_frame": f"median over all frames of {repeats} passes of the wall time of pipeline.step (EXR "
                            "reading and scoring excluded); ms_per_megapixel = ms_per_frame / (H * W / 1e6)",
            "timing_repeats": repeats,
            "rel_l2_trim": TRIM_FRACTION,
            "flip": flip,
            "overall": "errors: mean over the sequences a method ran on; ms_per_megapixel: median over them; "
                       "worst_tile: the largest over them, failing_tiles: summed; "
                       "rel_l2_vs_oidn_high: geometric mean over sequences of relL2 / relL2(oidn-high)",
        },
        "methods": [m.describe() for m in methods],
        "sequences": [
            {
                "name": r.sequence.name,
                "path": str(r.sequence.path),
                "width": r.sequence.width,
                "height": r.sequence.height,
                "frames": len(r.sequence.frames),
                "layers": sorted(r.sequence.layers),
                "crop": {"frame": r.crop_frame, "y0": r.crop[0], "x0": r.crop[1], "height": r.crop[2],
                         "width": r.crop[3]},
                "results": r.results,
            }
            for r in runs
        ],
        "overall": overall(runs, methods),
    }
    return results, runs
