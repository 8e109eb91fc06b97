"""`auto`: a per-tile blend of denoisers whose weights minimise their error, estimated without a reference,
within a cost budget.

At the first two frames (of the sequence, or since a refused frame started it again: `AutoState.forget`) and
every `every` frames, each candidate (CANDIDATES whose layers the frame has)
denoises half A alone and half B alone (`both_halves`; else half A only), with a history where it is temporal:
from a copy of its running state, or, where it is not running, from a state stepped through the previous frame
(`_history`; the first frame has none: all start fresh), so that a temporal candidate is judged as it would
run; `service.stages.error_estimate.tile_covariance` gives, per tile, the covariance of their relative errors
estimated from the halves, both ways (half the variance of one way; a candidate run on one half has no halves
of its own, so svgf is judged without its halves' variance: a little worse than it runs where its history is
short), normalised by the median of the candidates' outputs (the same for all; halves clipped at FIREFLY_CAP
times that level, so that fireflies do not decide), averaged with the previous evaluation's except the first
frame's (made without history) and in the tiles whose content moved more than MOVED pixels since (the
frames' `motion` summed: there the previous estimate is of other content).
`service.stages.candidate_blend.choose` then picks the set of candidates to
run (the last one while its summed estimate stays within `tolerance` of the lowest, else the cheapest that is,
costing at most `budget` times the one it weighs most, by COSTS) and per tile their convex weights of least
estimated error: two candidates whose errors are not fully correlated blend to less error than either. Every
frame, the members denoise the frame from their own states (a temporal one keeps its history while it stays a
member, and starts afresh when it joins again) and their outputs are blended with the weights interpolated
between tile centres, so that tiles meet without seams.

Outputs: `color`, and `error` (H, W, 1): the blend's estimate per tile from the last evaluation (up to
`every` - 1 frames old, at fixed tile positions): its halves' outputs (the members' f(A) and f(B) blended)
against the halves both ways, with the median of every candidate's output for the whole frame (the running
ones stepped through it for real at the evaluation, the others from copies: one more run of each candidate
that is not running) as scale and control variate (service/stages/error_estimate.py: it ranks tiles closer
to the truth, and reads higher than the blend's error where the median keeps its own samples' noise),
averaged as the covariance is where the blend it estimates is the same, at least the standard error of that
estimate (this evaluation's, its variance scaled per tile as the running average scales it), interpolated the
same way: the estimated relL2 of the blend run on half the samples without the guards (FRAME_FORMAT.md's
`error`: a relative scale to send more samples by, not the error of `color` itself). The floor keeps a tile whose
estimate fell to zero or below by chance from reading as error-free (before the control variate, 5-22%
of 32x32 tiles at 2 spp per half, where the log of max(estimate, its sd) followed the log of the true error
more closely than the estimate clipped at 1e-6: kpn and bmfr, frames 0-3, all four sequences but kpn on
shadows). Without `colorA`/`colorB`, or with no candidate the frame can feed, the sequence goes to
`service.pipelines.auto(layers)`'s choice whole, as the CLI did before this pipeline, and there is no `error` layer.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field

import numpy as np

from service import pipelines
from service.frame import LAYERS, Frame, FrameError
from service.pipelines import register
from service.pipelines.base import Pipeline, SequenceState, Split
from service.pipelines.options import option
from service.stages.candidate_blend import choose
from service.stages.error_estimate import (
    TILE,
    cross_tile_error,
    interpolate_tiles,
    tile_covariance,
    tile_error,
    tile_means,
)
from service.stages.input_history import InputHistory

# Candidates: the pipelines that run on one half alone (crossregression and crossreg need both), cheapest first,
# with their cost: median ms a 1280x720 frame on 2 cores (`python -m bench.classical_speed`, 2026-11-27; runs
# differ by ~10%). Only the ratios matter (`choose`). At 128x128 they are closer (kpn ~4x flr, not 7.5x):
# the default `budget` lets kpn take one of flr and bmfr beside it, not both, and svgf none (1.26x with flr).
COSTS = {"flr": 54.0, "bmfr": 61.0, "svgf": 206.0, "kpn": 404.0}
CANDIDATES = tuple(COSTS)
# Options of a candidate other than its defaults. flr keeps its ao guide here: without it (flr's default since
# 2026-11-28) flr alone is better on all four `make bench` sequences, but this blend was worse on shadows (relL2
# 0.0221 -> 0.0232) and fireflies (0.0206 -> 0.0212), its estimate choosing other tiles (out/bench/report-s48e).
CANDIDATE_OPTIONS = {"flr": {"ao": True}}
HALVES = ("colorA", "colorB")
FIREFLY_CAP = 4.0  # the estimate clips the halves at 4x the candidates' level (error_estimate `cap`)
MOVED = 3.0  # pixels a tile's content may have moved since the last evaluation for its estimate to be averaged in


@dataclass(frozen=True)
class AutoOptions:
    tile: int = option(TILE, low=8, high=256)  # side of the tiles blended per, pixels
    every: int = option(8, low=1, high=1000)  # frames between two evaluations of the candidates
    # a set of candidates is near-best where its summed estimate is within tolerance x |lowest| of the lowest
    tolerance: float = option(0.05, low=0.0, high=10.0)
    # run every candidate on both halves at an evaluation (one more run each, half the estimate's variance)
    both_halves: bool = option(True)
    # the candidates run on a frame cost at most this times the one of largest weight (COSTS)
    budget: float = option(1.25, low=1.0, high=100.0)


@dataclass
class AutoState(SequenceState):
    """The candidates' pipelines and states, and the last evaluation."""

    fallback: Pipeline | None = None  # the whole-sequence choice when the frames have no halves
    fallback_state: SequenceState | None = None
    candidates: dict[str, Pipeline] = field(default_factory=dict)  # name -> pipeline, in CANDIDATES order
    states: dict[str, SequenceState] = field(default_factory=dict)  # the members' states
    covariance: np.ndarray | None = None  # (K, K, th, tw) float64 running per-tile relL2 error covariance estimate
    blend: np.ndarray | None = None  # (K, th, tw) float64 per-tile weights of the candidates, summing to 1
    weights: np.ndarray | None = None  # (K, H, W) float32 `blend` interpolated between tile centres
    error: np.ndarray | None = None  # (H, W, 1) float32 the blend's estimate per tile, at least its sd, interpolated
    error_tiles: np.ndarray | None = None  # (th, tw) float64 the blend's running per-tile estimate
    # per tile, the running average's variance against one evaluation's: 1, then f <- f / 4 + 1 / 4 at each average
    variance_factor: np.ndarray | None = None
    moved: np.ndarray | None = None  # (th, tw) float64 pixels each tile's content moved since the last evaluation
    members: tuple[int, ...] | None = None  # indices of the candidates the blend runs
    evaluated: int | None = None  # the frame index of the last evaluation
    begun: int | None = None  # the frame index the sequence (last) started at, set up there; None: the next
    previous: Frame | None = None  # the last frame, for a temporal candidate's history at an evaluation

    def shares(self) -> dict[str, float]:
        """Per candidate the blend runs, its mean weight over the tiles (empty before an evaluation or with the
        fallback)."""
        if self.blend is None:
            return {}
        means = self.blend.reshape(len(self.candidates), -1).mean(axis=1)
        return {name: float(means[k]) for k, name in enumerate(self.candidates) if k in self.members}

    def close(self) -> None:
        self.previous = None
        for state in (*self.states.values(), self.fallback_state):
            if state is not None:
                state.close()

    def forget(self) -> None:
        """The next frame starts the sequence again (`AutoPipeline._setup`, with the candidates its layers allow:
        a layer a candidate requires, or the halves, may be what the refused frame lacked); frame_index goes on."""
        super().forget()
        self.begun = None

    def since_start(self, index: int) -> int:
        """Frame `index` of the sequence counted from where it (last) started (after the set-up)."""
        assert self.begun is not None
        return index - self.begun


@register
class AutoPipeline(Pipeline):
    name = pipelines.AUTO
    summary = ("a per-tile blend of flr, bmfr, svgf and kpn weighted by their error estimated from the half buffers, "
               "within a cost budget; also outputs that estimate (`error`)")
    requires = ("color",)
    optional = tuple(k for k in LAYERS if k not in ("color", "reference", "error"))  # any candidate or fallback reads
    temporal = True
    # each candidate's own step runs the guards (run once on the blend of their outputs, auto measured
    # worse in make bench: relL2 and temporal error higher)
    guards = False
    Options = AutoOptions

    def new_state(self, height: int, width: int) -> AutoState:
        return AutoState(height, width)

    def check(self, frame: Frame, state: SequenceState) -> None:
        """Also: once the first frame's halves started the per-tile blend, every frame must have them."""
        super().check(frame, state)
        if isinstance(state, AutoState) and state.candidates and state.begun is not None:
            for name in HALVES:
                if name not in frame:
                    raise FrameError(f"pipeline 'auto' blends per tile from the half buffers since the sequence's "
                                     f"first frame; this frame has no layer '{name}'", name)

    def denoise_split(self, frame: Frame, state: SequenceState) -> Split:
        """The candidates take the frame whole (each splits off its emission itself)."""
        buffers, state = self.denoise(frame, state)
        return buffers, {"color", "error"} & set(buffers), state

    def denoise(self, frame: Frame, state: SequenceState) -> tuple[dict[str, np.ndarray], SequenceState]:
        assert isinstance(state, AutoState)
        if state.begun is None:
            self._setup(frame, state)
        if state.fallback is not None:
            out, state.fallback_state = state.fallback.step(frame, state.fallback_state)
            return {"color": out["color"]}, state
        if state.evaluated is not None:  # the first frame's motion points before the sequence
            self._track_motion(frame, state)
        stepped = self._evaluate(frame, state) if self.evaluates(state.since_start(state.frame_index)) else {}
        names = list(state.candidates)
        for index, name in enumerate(names):  # a candidate that left the blend loses its history
            if index not in state.members and name in state.states:
                state.states.pop(name).close()
        weights = state.weights
        color = np.zeros((frame.height, frame.width, 3), np.float32)
        for index in state.members:
            name = names[index]
            out = stepped.get(name)  # a running member the evaluation already stepped through this frame
            if out is None:
                pipeline = state.candidates[name]
                sub = state.states.get(name) or pipeline.start(frame.height, frame.width)
                out, state.states[name] = pipeline.step(frame, sub)
                out = out["color"]
            color += weights[index][..., None] * out
        state.previous = frame if self.evaluates(state.since_start(state.frame_index + 1)) else None  # the next only
        return {"color": color, "error": state.error.copy()}, state

    def evaluates(self, index: int) -> bool:
        """Whether frame `index` (0-based) of a sequence evaluates the candidates: the first two and every `every`."""
        return index <= 1 or index % self.options.every == 0

    def _setup(self, frame: Frame, state: AutoState) -> None:
        state.close()  # a first frame that failed may have set some of it
        state.fallback = state.fallback_state = state.covariance = state.blend = None
        state.previous = state.members = state.evaluated = state.error_tiles = state.variance_factor = None
        state.moved, state.begun = None, state.frame_index
        state.candidates, state.states = {}, {}
        layers = set(frame.buffers)
        names = [n for n in CANDIDATES if set(pipelines.pipeline_class(n).requires) <= layers]
        if not names or not set(HALVES) <= layers:
            state.fallback = pipelines.get(pipelines.auto(layers))
            state.fallback_state = state.fallback.start(frame.height, frame.width)
            return
        state.candidates = {n: pipelines.get(n, **CANDIDATE_OPTIONS.get(n, {})) for n in names}

    def _evaluate(self, frame: Frame, state: AutoState) -> dict[str, np.ndarray]:
        """Estimate the candidates' per-tile error covariance on the halves (`run_half`) and blend per tile; then
        each candidate's output for the whole frame, the running ones stepped through it for real (after the
        choice, so that a choice that fails leaves them as they were), and the `error` layer from their median.
        Returns {name: (H, W, 3) output} of the running candidates stepped."""
        halves = HALVES if self.options.both_halves else HALVES[:1]
        histories = {name: self._history(name, state) for name in state.candidates}
        stepped: dict[str, np.ndarray] = {}
        try:
            outputs = {h: [run_half(pipeline, one_half(frame, h), histories[name])
                           for name, pipeline in state.candidates.items()] for h in halves}
            a, b, tile = frame["colorA"], frame["colorB"], self.options.tile
            # robust to one candidate blowing up (a sky through a window); with the emission, as relL2's reference
            scale = np.median([out for outs in outputs.values() for out in outs], axis=0)
            outs_b = outputs.get("colorB")
            covariance = tile_covariance(outputs["colorA"], a, b, scale, tile, cap=FIREFLY_CAP, outs_b=outs_b)
            keep = state.moved is None or state.moved <= MOVED  # per tile: the last estimate is of the same content
            first = state.covariance is None or state.since_start(state.frame_index) <= 1  # made without history
            if not first:
                covariance = np.where(keep, 0.5 * (state.covariance + covariance), covariance)
            costs = np.array([COSTS[name] for name in state.candidates])
            # frame 0's members stay at frame 1 while near the lowest: made without history, it still tells
            # (fireflies: kpn, fresh, best at frame 0, svgf within 1% at frame 1; kpn 0.0220 against svgf's
            # 0.0327 over the sequence)
            blend, members = choose(covariance, costs, self.options.tolerance, self.options.budget, state.members)
            full = []  # every candidate on the whole frame: the running ones for real, the others from a copy
            for name, pipeline in state.candidates.items():
                if name in state.states:
                    out, state.states[name] = pipeline.step(frame, state.states[name])
                    stepped[name] = out["color"]
                    histories[name] = state.states[name]
                    full.append(stepped[name])
                else:
                    full.append(run_half(pipeline, frame, histories[name]))
        finally:
            for name, history in histories.items():
                if history is not None and history is not state.states.get(name):
                    history.close()
        same_blend = state.blend is not None and np.all(np.abs(blend - state.blend) <= 1e-9, axis=0)
        state.covariance, state.evaluated, state.moved = covariance, state.frame_index, None
        state.blend, state.members = blend, members
        height, width = frame.height, frame.width
        state.weights = interpolate_tiles(blend, tile, height, width).astype(np.float32)
        # the error layer: the blend's estimate on the halves against the candidates' median on the whole frame
        consensus = np.median(full, axis=0)
        pixel_blend = np.repeat(np.repeat(blend, tile, axis=1), tile, axis=2)[:, :height, :width, None]
        blended = [sum(w * out for w, out in zip(pixel_blend, outs, strict=True)) for outs in outputs.values()]
        if outs_b is not None:
            estimate = cross_tile_error(*blended, a, b, consensus, tile, cap=FIREFLY_CAP, control=consensus)
        else:
            estimate = tile_error(blended[0], a, b, consensus, tile, cap=FIREFLY_CAP, control=consensus)
        if first:
            state.error_tiles, state.variance_factor = estimate.mean, np.ones_like(estimate.mean)
        else:  # averaged where the content stayed and the blend it estimates is the same
            averaged = keep & same_blend
            state.error_tiles = np.where(averaged, 0.5 * (state.error_tiles + estimate.mean), estimate.mean)
            state.variance_factor = np.where(averaged, 0.25 * state.variance_factor + 0.25, 1.0)
        floored = np.maximum(state.error_tiles, np.sqrt(state.variance_factor * estimate.variance))
        state.error = interpolate_tiles(floored, tile, height, width)[..., None].astype(np.float32)
        return stepped

    def _track_motion(self, frame: Frame, state: AutoState) -> None:
        """Add the frame's per-tile mean `motion` (the larger of |x| and |y|, pixels) to `state.moved`, the
        distance each tile's content moved since the last evaluation; a frame without `motion` adds none."""
        if "motion" not in frame:
            return
        shift = tile_motion(frame["motion"], self.options.tile)
        state.moved = shift if state.moved is None else state.moved + shift

    @staticmethod
    def _history(name: str, state: AutoState) -> SequenceState | None:
        """The state candidate `name` is judged from: its running one; for a temporal candidate not running, one
        made by a step through the previous frame (whose samples are independent of this frame's halves), so
        that it is judged with a history as it would run; else None (a fresh state)."""
        if name in state.states:
            return state.states[name]
        pipeline = state.candidates[name]
        if not pipeline.temporal or state.previous is None:
            return None
        _, history = pipeline.step(state.previous, pipeline.start(state.previous.height, state.previous.width))
        return history


def tile_motion(motion: np.ndarray, tile: int) -> np.ndarray:
    """Per tile x tile tile, the mean over its pixels of the larger of |x| and |y| of `motion` ((H, W, 2) float32
    pixels): how far its content moved in one frame, (ceil(H / tile), ceil(W / tile)) float64."""
    return tile_means(np.abs(motion).max(axis=-1).astype(np.float64), tile)


def run_half(pipeline: Pipeline, frame: Frame, running: SequenceState | None) -> np.ndarray:
    """(H, W, 3) float32: `pipeline`'s output for `frame` (one half, `one_half`, or the whole) from a copy of its
    running state (its history is made of earlier frames' samples, independent of this frame's halves, so the
    estimate stays unbiased), or from a fresh state when it has none. Without halves the blend is not run, so
    the copy leaves the blend's accumulated input behind (~29 MB at 1280x720)."""
    if running is None:
        sub = pipeline.start(frame.height, frame.width)
    else:
        halves = all(name in frame for name in HALVES)
        sub = copy.deepcopy(running, {} if halves else {id(running.input_history): InputHistory()})
    out, sub = pipeline.step(frame, sub)
    sub.close()
    return out["color"]


def one_half(frame: Frame, half: str = "colorA") -> Frame:
    """`frame` with one half (`colorA` or `colorB`) as its `color` and the halves removed: what a candidate's
    f(A) or f(B) is computed from."""
    buffers = {k: v for k, v in frame.buffers.items() if k not in HALVES}
    return Frame({**buffers, "color": frame[half]}, dict(frame.nonfinite))
