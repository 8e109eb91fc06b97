"""`crossreg`: online neural denoising with cross-regression (Choi et al. 2024).

Stages, per frame (emission already split off by Pipeline.step, added back after):
  1. cross-regression of the two half buffers -> pilots A, B in log1p space (sec. 4.1); with `average_halves`
     (the default, ours) each pilot's features and weights from its half averaged over the frames
     (service.stages.averaged_halves), fitted to this frame's other half
  2. reprojection of the previous output and pilots with depth/normal checks, mask eroded 3x3 (authors' code;
     a clamped Catmull-Rom sample where its taps are consistent, ours), then history screening against the
     current pilots' 7x7 range (authors' code)
  3. U-Net in ONNX Runtime on [pilots, previous output, albedo, normal] -> theta per pixel (sec. 4.2, 4.4)
  4. spatiotemporal filter: 11x11 cross-bilateral means, temporal blend, A/B combination (eqs. 8-10); the
     pilot-colour bandwidths at most sqrt(pilot_bandwidth) times the pilots' local disagreement (ours)
  5. optional: the frame's training sample goes to the online worker (sec. 4.3); weights it publishes are
     swapped into ONNX Runtime at the start of a later frame
Between the stages arrays are channel planes (C, H, W), the network's layout: the U-Net's input planes are
stacked once, and the filter reads them and the network's output as they are.
State kept explicitly in CrossregState: previous output and pilots (log1p), previous depth and normal, the
halves averaged so far (`average_halves`), the ONNX model of the sequence, the online trainer. The shipped warm
start was trained on the paper's pilots (models/train/warm_start.py caches them) and serves the averaged ones
as it is. Without `online` the shipped warm-start weights
(models/weights/crossreg_unet.onnx) serve; with it they are the starting point, or random weights with
`random_init` (the paper's setting).
"""

from __future__ import annotations

import functools
import logging
import weakref
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from service.frame import Frame
from service.layout import CROSSREG_INPUTS, CROSSREG_SAMPLE, channel_slices, stack_planes, total_channels
from service.online.trainer import OnlineConfig, OnlineTrainer, require_torch
from service.pipelines import register
from service.pipelines.base import Pipeline, SequenceState
from service.pipelines.networks import registered_model
from service.pipelines.options import MAX_THREADS, OptionError, option
from service.runtime import OnnxModel, WeightError, default_init, weight_names
from service.stages.averaged_halves import average_halves, averaged_pilots
from service.stages.cross_regression import CrossRegressionParams, cross_regression, log_to_linear
from service.stages.reprojection import ReprojectionParams, reproject
from service.stages.spatiotemporal_filter import (
    MAX_PILOT_BANDWIDTH,
    FilterOutput,
    screen_history,
    spatiotemporal_filter,
)

log = logging.getLogger(__name__)

NETWORK = "crossreg_unet"  # the network a `weights` file must hold (its ONNX metadata)
DEFAULT_WEIGHTS = "crossreg_unet"  # shipped warm start: models/weights/crossreg_unet.onnx (and .json manifest)
# Depth and normal consistency, success mask eroded 3x3 (Choi 2024 authors' code: reproject + erosion2d): the
# halves' average. The history (previous output and pilots) also takes the clamped Catmull-Rom sample (ours;
# service.stages.reprojection): warped by bilinear samples frame after frame it blurred (64-frame textures relL2
# 0.0131 -> 0.0121 with the spline; on the halves' average it cost shadows 1.6%; docs/benchmarks.md).
REPROJECTION = ReprojectionParams(erode=True)
HISTORY_REPROJECTION = replace(REPROJECTION, catmull_rom=True)
# lockstep: longest wait for the worker on one frame, seconds (its first frame includes importing torch); below
# the HTTP frame deadline (MCDENOISE_FRAME_TIMEOUT_S, 120 s by default). After one timeout the session stops waiting.
LOCKSTEP_TIMEOUT_S = 60.0


@dataclass(frozen=True)
class CrossregOptions:
    # U-Net weights: a name from the registry (service.runtime.weight_files: shipped models/weights/*.onnx
    # and $MCDENOISE_WEIGHTS_DIR), never a path
    weights: str = option(DEFAULT_WEIGHTS, choices=functools.partial(weight_names, NETWORK))
    online: bool = option(False)  # fine-tune online in a torch worker process (needs the `train` extra)
    # with online: wait for the worker's step on each frame before answering it (the paper's schedule: no frame
    # is dropped and weights follow every K frames exactly; each frame's time includes a training step).
    # Without it frames never wait, and those that arrive while the worker is busy are not trained on.
    lockstep: bool = option(False)
    publish_every: int = option(4, low=1, high=1000)  # K: frames the worker trains between weight publications
    # side of the random training crop sent to the worker, pixels (0: whole frame)
    crop: int = option(128, low=0, high=4096)
    random_init: bool = option(False)  # start from random weights (Choi 2024 sec. 4.4) instead of the warm start
    steps_per_frame: int = option(1, low=1, high=16)  # worker gradient steps per frame (Choi 2024: 1)
    worker_threads: int = option(1, low=1, high=MAX_THREADS)  # torch threads of the worker
    # ONNX Runtime intra-op threads (0: $MCDENOISE_ORT_THREADS or ORT's default)
    threads: int = option(0, low=0, high=MAX_THREADS)
    screen: bool = option(True)  # reject history outside the current pilots' 7x7 range (authors' code)
    # floor of the network's temporal weight theta_alpha (the current frame's share, eq. 8); 0: the paper's
    # filter, 1: no history (a spatial filter of the pilots). `make bench-long` (docs/benchmarks.md): 0.8 gave
    # lower relL2 and temporal error than 0 on 3 of its 4 sequences each
    min_alpha: float = option(0.8, low=0.0, high=1.0)
    # floor of the pilot-colour precisions kA, kB (eq. 9): 1 / (b s^2), s^2 the pilots' local disagreement
    # (service.stages.spatiotemporal_filter, ours); 0: the network's bandwidths as they are (the paper's).
    # Served only: online training goes through the network's own (docs/benchmarks.md, "Long sequences")
    pilot_bandwidth: float = option(32.0, low=0.0, high=MAX_PILOT_BANDWIDTH)
    # the pilots' features and weights from each half averaged over the frames (service.stages.averaged_halves,
    # ours); false: this frame's halves, the paper's
    average_halves: bool = option(True)
    seed: int = option(0, low=0, high=2**32 - 1)  # random initialisation and crop positions


@dataclass
class History:
    """What frame t keeps for frame t + 1."""

    colors: np.ndarray  # (9, H, W) float32 planes: pilot A, pilot B, filter output f(x), log1p; reprojected in one pass
    normal: np.ndarray  # (H, W, 3) float32, for the reprojection's normal test
    depth: np.ndarray | None  # (H, W, 1) float32, for the depth test, when the frames carry depth
    halves: np.ndarray | None = None  # (7, H, W) float32: the halves averaged so far (`average_halves`), or None


_INPUT = channel_slices(CROSSREG_INPUTS)
# The input groups that History.colors keeps and the screening compares, in this order, first in the input
_SCREENED = ("pilotA", "pilotB", "previous")
_PILOTS = slice(0, _INPUT["pilotB"].stop)  # pilot A, pilot B
_HISTORY = slice(0, _INPUT["previous"].stop)  # pilot A, pilot B, previous: History.colors' planes
assert [_INPUT[name].start for name in _SCREENED] == [0, _INPUT["pilotA"].stop, _INPUT["pilotB"].stop]


@dataclass
class Prepared:
    """One frame ready for the network and the filter; log1p radiance unless stated."""

    planes: np.ndarray  # (15, H, W) float32 network input in layout.CROSSREG_INPUTS order; `previous` is the
    # reprojected previous output where `valid`, the pilots' mean elsewhere. The filter reads its planes.
    valid: np.ndarray  # (H, W) bool: history usable (reprojected, consistent, screened)
    previous_pilots: np.ndarray  # (6, H, W) float32: the previous pilots A, B reprojected where each passed
    # its screening, the current ones elsewhere: temporal labels of outputs B and A (eq. 13)
    halves: np.ndarray | None = None  # (7, H, W) float32: the halves averaged with this frame, with `average`

    def plane_group(self, name: str) -> np.ndarray:
        """(c, H, W) float32 view of the input group `name` (layout.CROSSREG_INPUTS)."""
        return self.planes[_INPUT[name]]

    def sample(self) -> np.ndarray:
        """(H, W, 22) float32 training sample in layout.CROSSREG_SAMPLE order: a view of channel planes
        (crop it, then copy)."""
        valid = self.valid[None].astype(np.float32)
        out = np.concatenate([self.planes, valid, self.previous_pilots], axis=0)
        assert out.shape[0] == total_channels(CROSSREG_SAMPLE)
        return out.transpose(1, 2, 0)


def prepare_frame(
    frame: Frame,
    history: History | None,
    *,
    screen: bool = True,
    params: CrossRegressionParams | None = None,
    pilots: tuple[np.ndarray, np.ndarray] | None = None,
    average: bool = False,
) -> Prepared:
    """Stages 1-2 and the network input. frame: emission-free Frame with colorA, colorB, albedo, normal,
    motion (depth optional). history: the previous frame's, or None at the start of a sequence.
    pilots: the frame's `cross_regression` (pilot_a, pilot_b), (3, H, W) float32 log1p planes, when already
    computed (offline training caches them). average (with pilots None): the pilots' features from the halves
    averaged over the frames (`averaged_halves`), kept in the result's `halves` for the next frame.
    A history whose frame had `depth` where this one has none, or the reverse, is not used (a new start)."""
    albedo, normal = frame["albedo"], frame["normal"]
    if history is not None and (history.depth is None) != (frame.get("depth") is None):
        history = None
    halves = None
    if pilots is None and average:
        halves, pilots = averaged_frame_pilots(frame, history, params)
    elif pilots is None:
        pilots = cross_regression(frame["colorA"], frame["colorB"], albedo, normal, params)
    pilot_a, pilot_b = (p.transpose(1, 2, 0) for p in pilots)  # (H, W, 3) views; stack_planes copies planes
    mean = 0.5 * (pilot_a + pilot_b)
    groups = {"pilotA": pilot_a, "pilotB": pilot_b, "previous": mean, "albedo": albedo, "normal": normal}
    planes = stack_planes(CROSSREG_INPUTS, groups)
    if history is None:
        return Prepared(planes, np.zeros(mean.shape[:2], bool), planes[_PILOTS], halves)
    warped, valid = reproject(
        history.colors.transpose(1, 2, 0), frame["motion"], depth=frame.get("depth"), prev_depth=history.depth,
        normal=normal, prev_normal=history.normal, params=HISTORY_REPROJECTION,
    )  # fmt: skip
    warped = warped.transpose(2, 0, 1)  # (9, H, W): the planes of History.colors, warped
    current = planes[_HISTORY]  # pilot A, pilot B, their mean: what each history plane is screened against
    if screen:  # each previous pilot against its current pilot, the output against the pilots' mean
        masks, screened = screen_history(current, warped, valid, groups=3)
    else:
        masks = np.broadcast_to(valid, (3, *valid.shape))
        screened = np.where(valid, warped, current)
    planes[_INPUT["previous"]] = screened[_INPUT["previous"]]
    return Prepared(planes, masks[_SCREENED.index("previous")], screened[_PILOTS], halves)


def averaged_frame_pilots(frame: Frame, history: History | None, params: CrossRegressionParams | None = None
                          ) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray]]:
    """(halves, (pilot_a, pilot_b)): the frame's halves averaged with those `history` keeps
    (`averaged_halves.average_halves`, reprojected as crossreg's history is) and the pilots of those averages
    (`averaged_pilots`). frame: emission-free Frame with colorA, colorB, albedo, normal, motion (depth optional);
    history: the previous frame's, or None at a start (only its halves, depth and normal are read)."""
    previous = None if history is None else history.halves
    halves = average_halves(
        frame["colorA"], frame["colorB"], previous, frame["motion"], depth=frame.get("depth"),
        prev_depth=None if history is None else history.depth, normal=frame["normal"],
        prev_normal=None if history is None else history.normal, params=REPROJECTION,
    )  # fmt: skip
    return halves, averaged_pilots(frame["colorA"], frame["colorB"], halves, frame["albedo"], frame["normal"], params)


def filter_frame(prepared: Prepared, params: np.ndarray, min_alpha: float = 0.0,
                 pilot_bandwidth: float = 0.0) -> FilterOutput:
    """Stage 4: eqs. 8-10 with the network's output params (6, H, W), in log1p space, on the input planes,
    alpha floored at min_alpha, the pilot-colour precisions by pilot_bandwidth (`spatiotemporal_filter`)."""
    p = prepared.plane_group
    return spatiotemporal_filter(
        p("pilotA"), p("pilotB"), p("albedo"), p("normal"), params, p("previous"), prepared.valid,
        min_alpha=min_alpha, pilot_bandwidth=pilot_bandwidth,
    )


def next_history(frame: Frame, prepared: Prepared, color: np.ndarray) -> History:
    """What frame t + 1 needs from frame t; color: (3, H, W) float32 filter output f(x), log1p radiance."""
    colors = np.concatenate([prepared.planes[_PILOTS], color], axis=0, dtype=np.float32)
    return History(colors, frame["normal"], frame.get("depth"), prepared.halves)


@dataclass
class CrossregState(SequenceState):
    """Per-sequence state: history of the previous frame, the sequence's model, the online trainer."""

    history: History | None = None
    model: OnnxModel | None = None
    trainer: OnlineTrainer | None = None
    refused: int = 0  # weight sets refused (non-finite or not fitting the graph)
    last_refusal: str | None = None
    init: str = "warm start"  # where the running weights started: "warm start" or "random"

    @property
    def online_status(self) -> dict[str, Any]:
        """What the HTTP service reports: state (off / starting / running / lagging / crashed / stopped),
        running, crashed, lagging, frames_trained, frames_dropped, weights_version, last_error, ..."""
        version = self.model.version if self.model is not None else 0
        if self.trainer is None:
            status: dict[str, Any] = {
                "state": "off", "running": False, "crashed": False, "lagging": False,
                "frames_submitted": 0, "frames_trained": 0, "frames_dropped": 0, "last_loss": None,
                "last_error": None,
            }  # fmt: skip
        else:
            status = self.trainer.status()
        status.update(weights_version=version, weights_refused=self.refused, init=self.init)
        if self.last_refusal and not status.get("last_error"):
            status["last_error"] = self.last_refusal
        return status

    def close(self) -> None:
        """Stop the online worker, if any (also done when the state is garbage-collected)."""
        if self.trainer is not None:
            self.trainer.close()

    def forget(self) -> None:
        """The history goes; the model and the online trainer (what the sequence has learned) stay."""
        super().forget()
        self.history = None


@register
class CrossregPipeline(Pipeline):
    name = "crossreg"
    summary = (
        "cross-regression pilots + U-Net-driven spatiotemporal filter (Choi 2024); warm-start weights, "
        "optional online fine-tuning (online=true); keeps shadows and texture"
    )
    requires = ("colorA", "colorB", "albedo", "normal", "motion")
    optional = ("depth", "emission")
    temporal = True
    Options = CrossregOptions

    def __init__(self, **options: Any):
        super().__init__(**options)
        opt = self.options
        if opt.lockstep and not opt.online:
            raise OptionError("pipeline 'crossreg': option 'lockstep' needs online=true", "lockstep")
        if opt.online:
            require_torch()
        self._online_config = OnlineConfig(
            publish_every=opt.publish_every, crop=opt.crop, steps_per_frame=opt.steps_per_frame,
            worker_threads=opt.worker_threads, seed=opt.seed, min_alpha=opt.min_alpha,
        )  # fmt: skip
        self._model: OnnxModel | None = None  # loaded on first use, shared by states that never swap

    def model(self) -> OnnxModel:
        """The sequence-shared U-Net of the `weights` named (OptionError when the file is gone or holds
        no crossreg U-Net: an operator's folder may change after the option was checked)."""
        if self._model is None:
            self._model = registered_model(self.options.weights, NETWORK, threads=self.options.threads or None)
        return self._model

    def new_state(self, height: int, width: int) -> CrossregState:
        opt = self.options
        shared = self.model()
        state = CrossregState(height, width)
        if not (opt.online or opt.random_init):
            state.model = shared
            return state
        state.model = shared.copy()
        initial = None
        if opt.random_init:
            initial = default_init(state.model.info.weight_shapes, opt.seed)
            state.model.swap_weights(initial)
            state.init = "random"
        if opt.online:
            config = replace(self._online_config, alignment=state.model.info.alignment)
            state.trainer = OnlineTrainer(state.model.model_bytes, initial, config)
            weakref.finalize(state, state.trainer.close)
        return state

    def denoise(self, frame: Frame, state: SequenceState) -> tuple[dict[str, np.ndarray], SequenceState]:
        assert isinstance(state, CrossregState) and state.model is not None
        if state.trainer is not None:
            self._take_published_weights(state)
        prepared = prepare_frame(frame, state.history, screen=self.options.screen, average=self.options.average_halves)
        params = state.model.run_planes(prepared.planes)
        output = filter_frame(prepared, params, self.options.min_alpha, self.options.pilot_bandwidth)
        if state.trainer is not None:
            state.trainer.submit(prepared.sample(), state.frame_index,
                                 wait=LOCKSTEP_TIMEOUT_S if self.options.lockstep else 0.0)
        state.history = next_history(frame, prepared, output.color)
        radiance = np.maximum(log_to_linear(output.color), np.float32(0.0)).transpose(1, 2, 0)
        return {"color": np.ascontiguousarray(radiance)}, state

    @staticmethod
    def _take_published_weights(state: CrossregState) -> None:
        """Swap in the newest weights the worker published; refuse (and report) weights that do not fit."""
        assert state.trainer is not None and state.model is not None
        published = state.trainer.poll()
        if published is None:
            return
        version, weights = published
        try:
            state.model.swap_weights(weights)
        except WeightError as err:
            state.refused += 1
            state.last_refusal = f"worker weights v{version} refused: {err}"
            log.warning("crossreg: %s; keeping weights version %d", state.last_refusal, state.model.version)
