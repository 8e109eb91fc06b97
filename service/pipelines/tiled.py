"""`auto`: per tile, the cheapest of several denoisers whose error, estimated without a reference, is within
a tolerance of the best one's.

Every `every` frames (and at the first), each candidate (CANDIDATES whose layers the frame has) denoises
half A alone and half B alone (`both_halves`; else half A only), from a copy of its state where it is
running (a temporal candidate judged with its history, as it will run), else from a fresh state;
`service.stages.error_estimate` gives its per-tile relL2 estimate from the halves, both ways
(`cross_tile_error`: half the variance of one way), normalised by the median of the candidates' outputs
(the same for all; halves clipped at FIREFLY_CAP times that level, so that fireflies do not decide),
averaged with the previous evaluation's where there is one (steadier, but older). Per tile
the cheapest candidate (CANDIDATES is in order of cost) whose estimate is within `tolerance` of the
tile's lowest is chosen. Every frame, the chosen candidates denoise the frame from their own states (a
temporal one keeps its history while it stays chosen, and starts afresh when chosen again) and their
outputs are blended with per-candidate weights interpolated between tile centres, so that tiles meet
without seams.

Outputs: `color`, and `error` (H, W, 1): the chosen tiles' estimates from the last evaluation (up to
`every` - 1 frames old, at fixed tile positions) interpolated the same way: the estimated relL2 of the
chosen candidates run on half the samples without the guards (FRAME_FORMAT.md's
`error`: a relative scale to send more samples by, not the error of `color` itself). Without
`colorA`/`colorB`, or with no candidate the frame can feed, the sequence goes to
`service.pipelines.auto(layers)`'s choice whole, as the CLI did before this pipeline, and there is no
`error` layer.
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
from service.stages.error_estimate import TILE, cross_tile_error, interpolate_tiles, interpolation_matrix, tile_error

# Candidates: the pipelines that run on one half alone (crossregression and crossreg need both), cheapest at
# 1280x720 first (README): flr, bmfr, svgf, kpn
CANDIDATES = ("flr", "bmfr", "svgf", "kpn")
HALVES = ("colorA", "colorB")
FIREFLY_CAP = 4.0  # the estimate clips the halves at 4x the candidates' level (error_estimate `cap`)


@dataclass(frozen=True)
class AutoOptions:
    tile: int = option(TILE, low=8, high=256)  # side of the tiles chosen for, pixels
    every: int = option(4, low=1, high=1000)  # frames between two evaluations of the candidates
    # a candidate is eligible in a tile when its estimate is at most (1 + tolerance) x the tile's best
    tolerance: float = option(0.05, low=0.0, high=10.0)
    # run every candidate on both halves at an evaluation (twice its cost, half the estimate's variance)
    both_halves: bool = option(True)


@dataclass
class AutoState(SequenceState):
    """The candidates' pipelines and states, and the last evaluation."""

    fallback: Pipeline | None = None  # the whole-sequence choice when the frames have no halves
    fallback_state: SequenceState | None = None
    candidates: dict[str, Pipeline] = field(default_factory=dict)  # name -> pipeline, in CANDIDATES order
    states: dict[str, SequenceState] = field(default_factory=dict)  # the chosen candidates' states
    estimate: np.ndarray | None = None  # (K, th, tw) float64 running per-tile relL2 estimates
    choice: np.ndarray | None = None  # (th, tw) int64 index into `candidates`
    weights: np.ndarray | None = None  # (K, H, W) float32 blend weights of `choice`
    error: np.ndarray | None = None  # (H, W, 1) float32 the chosen tiles' estimates, interpolated

    def close(self) -> None:
        for state in (*self.states.values(), self.fallback_state):
            if state is not None:
                state.close()


@register
class AutoPipeline(Pipeline):
    name = pipelines.AUTO
    summary = ("per tile, the cheapest of flr, bmfr, svgf and kpn within a tolerance of the lowest error estimated "
               "from the half buffers; also outputs that estimate (`error`)")
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
        """Also: once the first frame's halves started the per-tile choice, every frame must have them."""
        super().check(frame, state)
        if isinstance(state, AutoState) and state.candidates:
            for name in HALVES:
                if name not in frame:
                    raise FrameError(f"pipeline 'auto' chooses per tile from the half buffers since the sequence's "
                                     f"first frame; this frame has no layer '{name}'", name)

    def denoise_split(self, frame: Frame, state: SequenceState) -> Split:
        """The candidates take the frame whole (each splits off its emission itself)."""
        buffers, state = self.denoise(frame, state)
        return buffers, {"color", "error"} & set(buffers), state

    def denoise(self, frame: Frame, state: SequenceState) -> tuple[dict[str, np.ndarray], SequenceState]:
        assert isinstance(state, AutoState)
        if state.frame_index == 0:
            self._setup(frame, state)
        if state.fallback is not None:
            out, state.fallback_state = state.fallback.step(frame, state.fallback_state)
            return {"color": out["color"]}, state
        if state.frame_index % self.options.every == 0:
            self._evaluate(frame, state)
        names = list(state.candidates)
        chosen = sorted(set(state.choice.ravel().tolist()))
        for index, name in enumerate(names):  # a candidate that left the choice loses its history
            if index not in chosen and name in state.states:
                state.states.pop(name).close()
        weights = state.weights
        color = np.zeros((frame.height, frame.width, 3), np.float32)
        for index in chosen:
            name = names[index]
            pipeline = state.candidates[name]
            sub = state.states.get(name) or pipeline.start(frame.height, frame.width)
            out, state.states[name] = pipeline.step(frame, sub)
            color += weights[index][..., None] * out["color"]
        return {"color": color, "error": state.error.copy()}, state

    def _setup(self, frame: Frame, state: AutoState) -> None:
        state.close()  # a first frame that failed may have set some of it
        state.fallback = state.fallback_state = state.estimate = state.choice = None
        state.candidates, state.states = {}, {}
        layers = set(frame.buffers)
        names = [n for n in CANDIDATES if set(pipelines.pipeline_class(n).requires) <= layers]
        if not names or not set(HALVES) <= layers:
            state.fallback = pipelines.get(pipelines.auto(layers))
            state.fallback_state = state.fallback.start(frame.height, frame.width)
            return
        state.candidates = {n: pipelines.get(n) for n in names}

    def _evaluate(self, frame: Frame, state: AutoState) -> None:
        """Estimate every candidate's per-tile error on the halves (`run_half`) and choose per tile."""
        halves = HALVES if self.options.both_halves else HALVES[:1]
        outputs = {h: [run_half(pipeline, one_half(frame, h), state.states.get(name))
                       for name, pipeline in state.candidates.items()] for h in halves}
        # robust to one candidate blowing up (a sky through a window)
        scale = np.median([out for outs in outputs.values() for out in outs], axis=0)
        a, b, tile = frame["colorA"], frame["colorB"], self.options.tile
        if self.options.both_halves:
            estimate = np.stack([cross_tile_error(out_a, out_b, a, b, scale, tile, cap=FIREFLY_CAP).mean
                                 for out_a, out_b in zip(outputs["colorA"], outputs["colorB"], strict=True)])
        else:
            estimate = np.stack([tile_error(out_a, a, b, scale, tile, cap=FIREFLY_CAP).mean
                                 for out_a in outputs["colorA"]])
        if state.estimate is not None:
            estimate = 0.5 * (state.estimate + estimate)
        state.estimate = estimate
        state.choice = choose(estimate, self.options.tolerance)
        height, width = frame.height, frame.width
        state.weights = tile_weights(state.choice, len(state.candidates), tile, height, width)
        chosen = np.take_along_axis(estimate, state.choice[None], axis=0)[0]
        state.error = np.maximum(interpolate_tiles(chosen, tile, height, width), 0.0)[..., None].astype(np.float32)


def run_half(pipeline: Pipeline, frame: Frame, running: SequenceState | None) -> np.ndarray:
    """(H, W, 3) float32: `pipeline`'s output for `frame` (one half, `one_half`) from a copy of its running
    state (its history is made of earlier frames' samples, independent of this frame's halves, so the
    estimate stays unbiased), or from a fresh state when it has none."""
    sub = copy.deepcopy(running) if running is not None else pipeline.start(frame.height, frame.width)
    out, sub = pipeline.step(frame, sub)
    sub.close()
    return out["color"]


def one_half(frame: Frame, half: str = "colorA") -> Frame:
    """`frame` with one half (`colorA` or `colorB`) as its `color` and the halves removed: what a candidate's
    f(A) or f(B) is computed from."""
    buffers = {k: v for k, v in frame.buffers.items() if k not in HALVES}
    return Frame({**buffers, "color": frame[half]}, dict(frame.nonfinite))


def choose(estimate: np.ndarray, tolerance: float) -> np.ndarray:
    """Per tile, the index of the first (cheapest: candidates come cheapest first) candidate whose estimate is
    at most the tile's lowest plus `tolerance` times its magnitude. estimate: (K, th, tw). Returns (th, tw)
    int64."""
    best = estimate.min(axis=0)
    eligible = estimate <= best + tolerance * np.abs(best)
    return eligible.argmax(axis=0)


def tile_weights(choice: np.ndarray, count: int, tile: int, height: int, width: int) -> np.ndarray:
    """(count, H, W) float32 blend weights of the candidates from the per-tile `choice` (th, tw): each
    candidate's tile indicator interpolated between tile centres; they sum to 1 at every pixel."""
    rows, cols = interpolation_matrix(height, tile), interpolation_matrix(width, tile)
    return np.stack([rows @ (choice == k).astype(np.float64) @ cols.T for k in range(count)]).astype(np.float32)
