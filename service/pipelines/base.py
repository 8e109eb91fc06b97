"""The one interface every denoiser implements (shared ARCHITECTURE.md):

    pipeline = pipelines.get(name, **options)
    state = pipeline.start(height, width)
    out, state = pipeline.step(frame, state)

`Pipeline.step` does what all denoisers share, in order: check the frame against the declared layers
and the sequence size (before any work), find the exact pixels when the frame has halves but no
`emission` layer (`service.stages.exact`: they become its emission), split off `emission` from the
radiance layers, call the denoiser's `denoise`, add emission back, clip the result below at the input's lowest
value or 0 (`service.stages.radiance_floor`), return the pixels where nothing was hit
and no emission is given as they came (`service.stages.background`), keep the result within the noise the
halves show or at the input's firefly clip (`service.stages.noise_clamp`), blend it per tile with the input
by the weight the halves say is best (`service.stages.noise_blend`; a temporal pipeline's input accumulated
over the sequence where the halves say it is better, `service.stages.input_history`), and make sure nothing
non-finite leaves.
The split is `Pipeline.denoise_split` (`service.stages.emission.subtract_emission`, which also clips the remainder
at an emitter's edge).
"""

from __future__ import annotations

import dataclasses
from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np

from service.frame import RADIANCE_LAYERS, Frame, FrameError
from service.pipelines.options import build as build_options
from service.pipelines.options import describe as describe_options
from service.stages.background import pass_background
from service.stages.emission import add_emission, subtract_emission
from service.stages.exact import exact_emission
from service.stages.input_history import InputHistory
from service.stages.noise_blend import firefly_clip, noise_blend
from service.stages.noise_clamp import noise_clamp
from service.stages.radiance_floor import radiance_floor


@dataclass
class SequenceState:
    """Per-sequence state. Pipelines with history subclass it; the pipeline owns and may mutate it."""

    height: int
    width: int
    frame_index: int = 0  # frames completed in this sequence
    input_history: InputHistory = field(default_factory=InputHistory)  # a temporal pipeline's, for the blend

    def close(self) -> None:
        """Release what the state holds (an online worker); called once the sequence ends."""

    def forget(self) -> None:
        """Drop what the frames so far left, as a new sequence has none; called on a refused frame (the next
        frame's motion points to it, which no history holds, and a stage that failed may have left part of
        its history written). Subclasses drop their own history too and keep their resources."""
        self.input_history.clear()


# What `Pipeline.denoise_split` returns: the buffers, the names of those known to be finite, the state
Split = tuple[dict[str, np.ndarray], set[str], SequenceState]


@dataclass(frozen=True)
class NoOptions:
    """A pipeline without options."""


class Pipeline(ABC):
    """A denoiser behind the common interface. Subclasses set the class attributes and `denoise`."""

    name: ClassVar[str]
    summary: ClassVar[str]  # one line: what it is and what it is good at
    requires: ClassVar[tuple[str, ...]]  # layers a frame must have
    optional: ClassVar[tuple[str, ...]] = ()  # layers used when present
    temporal: ClassVar[bool] = False  # whether the output depends on earlier frames
    Options: ClassVar[type] = NoOptions  # frozen dataclass of algorithm options
    # True: the step's hard-case guards run (exact pixels as emission, the noise clamp and blend, the background
    # passed through); the benchmark's anchors turn them off, so that OIDN is measured as its users call it
    guards: ClassVar[bool] = True

    def __init__(self, **options: Any):
        """Raises OptionError (a ValueError) naming an unknown option or a value outside its declared range."""
        self.options = build_options(self.Options, options, f"pipeline '{self.name}'")

    @classmethod
    def declared(cls) -> tuple[str, ...]:
        """`color` (the frame contract fills it in, every pipeline may read it), required and optional layers."""
        return tuple(dict.fromkeys(("color", *cls.requires, *cls.optional)))

    @classmethod
    def reads(cls) -> tuple[str, ...]:
        """Every layer the pipeline's step may read: `color` (the frame contract fills it in), required,
        optional, and with `guards` the halves, `emission` (exact pixels, noise clamp), `normal` and `depth`
        (the background, the noise clamp's surfaces), and for a temporal pipeline `motion` (the blend's
        accumulated input). Readers decode only these (service/api/codec.py)."""
        guarded = ("colorA", "colorB", "emission", "normal", "depth") if cls.guards else ()
        guarded += ("motion",) if cls.guards and cls.temporal else ()
        return tuple(dict.fromkeys((*cls.declared(), *guarded)))

    def start(self, height: int, width: int) -> SequenceState:
        """State for a new sequence of frames of `height` x `width` pixels."""
        if height < 1 or width < 1:
            raise ValueError(f"frame size must be at least 1x1, got {width}x{height}")
        return self.new_state(height, width)

    def new_state(self, height: int, width: int) -> SequenceState:
        return SequenceState(height, width)

    def check(self, frame: Frame, state: SequenceState) -> None:
        """Raise FrameError when `frame` lacks a required layer or does not match the sequence size."""
        frame.require(self.requires, who=f"pipeline '{self.name}'")
        if (frame.height, frame.width) != (state.height, state.width):
            raise FrameError(
                f"frame is {frame.width}x{frame.height} but the sequence is {state.width}x{state.height}"
            )

    def step(self, frame: Frame, state: SequenceState) -> tuple[Frame, SequenceState]:
        """Denoise the next frame of the sequence.

        frame: validated Frame with at least `requires`. Returns (Frame with `color`: (H, W, 3)
        float32 linear radiance, finite, plus documented diagnostics; the updated state).
        The input's NaN/Inf repair counts are carried to the output frame's `nonfinite`.
        """
        try:
            return self._step(frame, state)
        except Exception:  # a refused frame: the next frame's motion points to it, not to any history
            state.forget()
            raise

    def _step(self, frame: Frame, state: SequenceState) -> tuple[Frame, SequenceState]:
        """`step`'s work."""
        self.check(frame, state)
        given = frame
        if self.guards:
            frame = with_exact_emission(frame)
        buffers, finite, state = self.denoise_split(frame, state)
        if self.guards:  # no radiance below the input's (0 for a renderer's ordinary output): no black ring
            buffers["color"] = radiance_floor(buffers["color"], given["color"])
        if self.guards and "normal" in given:  # before the clamp and blend: a pixel as it came stays so there
            buffers["color"] = pass_background(buffers["color"], given["color"], given["normal"],
                                               given.get("emission"))
        for name, value in buffers.items():
            if name not in finite and not np.isfinite(value).all():  # a guard: stages are tested never to get here
                raise FloatingPointError(f"pipeline '{self.name}' produced non-finite '{name}'")
        if self.guards and "colorA" in given and "colorB" in given:  # within the noise the halves show
            halves = given["colorA"], given["colorB"]  # (finite in, finite out: the band is finite or +inf)
            exact = "emission" in frame  # the renderer's, or the exact pixels `with_exact_emission` found
            # with the exact pixels' emission when the frame had none: the clamp's exact pass overrides them there
            clipped, admitted = firefly_clip(given["color"], *halves, frame.buffers.get("emission"))
            clamped = noise_clamp(buffers["color"], given["color"], *halves, given.get("emission"), exact=exact,
                                  normal=given.get("normal"), depth=given.get("depth"), admitted=admitted)
            history = state.input_history if self.temporal else None  # the accumulated input it may take back
            buffers["color"] = noise_blend(clamped, given["color"], *halves, frame.buffers.get("emission"),
                                           history=history, motion=given.get("motion"), depth=given.get("depth"),
                                           normal=given.get("normal"), clipped=clipped)
        else:  # no blend: the accumulated input has a gap
            state.input_history.clear()
        state.frame_index += 1
        return Frame(buffers, dict(frame.nonfinite)), state

    def denoise_split(self, frame: Frame, state: SequenceState) -> Split:
        """`denoise` with the frame's `emission` (when it has one) taken out of the radiance layers the
        pipeline declares and added back to the result's `color`. Returns (buffers, the names of those known
        to be finite, state)."""
        emission = frame.get("emission")
        if emission is None:
            buffers, state = self.denoise(frame, state)
            return buffers, set(), state
        # the halves only where the pipeline declares them: each layer subtracted is a full frame read and written
        declared = self.declared()
        names = [k for k in RADIANCE_LAYERS if k in frame and k in declared]  # "color" at least
        split = subtract_emission([frame[k] for k in names], emission)
        buffers, state = self.denoise(frame.replace(**dict(zip(names, split, strict=True))), state)
        buffers["color"], finite = add_emission(buffers["color"], emission)
        return buffers, {"color"} if finite else set(), state

    @abstractmethod
    def denoise(self, frame: Frame, state: SequenceState) -> tuple[dict[str, np.ndarray], SequenceState]:
        """The denoiser proper: emission already removed; returns buffers with at least `color`."""

    @classmethod
    def describe(cls) -> dict[str, Any]:
        """What clients see: name, summary, layers, temporal flag, options with defaults, and each option's
        type and range (`option_specs`, see service/pipelines/options.py)."""
        return {
            "name": cls.name,
            "summary": cls.summary,
            "requires": list(cls.requires),
            "optional": list(cls.optional),
            "temporal": cls.temporal,
            "options": {f.name: f.default for f in dataclasses.fields(cls.Options)},
            "option_specs": describe_options(cls.Options),
        }


def with_exact_emission(frame: Frame) -> Frame:
    """`frame` with an `emission` layer of its exact pixels (`service.stages.exact`) when it has both halves,
    no `emission` of its own and some exact pixel; otherwise `frame` itself."""
    if "emission" in frame or "colorA" not in frame or "colorB" not in frame:
        return frame
    emission = exact_emission(frame["colorA"], frame["colorB"], frame["color"])
    return frame if emission is None else frame.replace(emission=emission)
