"""Hard-case stability suite: every pipeline over generated frames that break naive denoisers.

Each case is a short sequence (default 3 frames, so temporal pipelines run with history) built from
the analytic scene of bench.synthetic: the G-buffers and reference come from `synthetic_sequence`,
and the radiance layers (`color`, `colorA`, `colorB`, `sampleCount`, `bcMean`, `bcM2`, `bcM3`) are
re-derived from per-pixel samples so that every case keeps them consistent with each other. Frames
enter through `Frame.from_buffers`, the one door every interface uses, so NaN/Inf repair is part of
what is tested.

A case passes for a method when, on every frame:
1. `pipeline.step` raises nothing;
2. the output `color` has shape (H, W, 3) and every output buffer is finite;
3. the output holds no energy the input cannot explain:
       lo * (1 + ENERGY_RTOL) - ENERGY_ATOL <= output color <= hi * (1 + ENERGY_RTOL) + ENERGY_ATOL
   with, over the input frames the output may depend on (the current frame for a non-temporal
   method; all frames so far for a temporal one), and over the radiance layers L in
   {color, colorA, colorB} after NaN/Inf repair, E the `emission` layer (zero when absent):
       hi = max(0, max(L - E)) + max(0, max E)
       lo = min(0, min(L - E)) + min(0, min E)
   That is: the brightest non-emitted radiance any input estimate shows, plus the brightest emission
   (a pipeline denoises L - E and adds E back, so a pixel may legitimately get both), and the same
   for the darkest (negative radiance is legal input, FRAME_FORMAT.md). Nothing brighter than the
   input, nothing darker than it, nothing from an all-black input.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from bench.synthetic import lognormal_samples, synthetic_sequence
from service.exr import encode_frame, read_frame
from service.frame import RADIANCE_LAYERS, Frame
from service.pipelines.base import Pipeline
from service.stages.sample_statistics import statistics_from_samples

ENERGY_RTOL = 1e-3  # relative slack of the energy bound (float32 rounding of sums of many terms)
ENERGY_ATOL = 1e-4  # absolute slack of the energy bound, radiance units
SPP = 4  # samples per pixel of every generated frame (two per half buffer)
FIREFLY_FRACTION = 0.005  # fraction of pixels (at least one) that get one firefly sample
HALF_MAX = 65504.0  # largest finite float16 (IEEE 754 binary16)

Layers = dict[str, np.ndarray]


# ----------------------------------------------------------------------------------------------- generation


def _samples(layers: Layers, rng: np.random.Generator) -> np.ndarray:
    """(SPP, H, W, 3) float32 samples of the frame: reference radiance times a log-normal factor of
    mean 1 (as bench.synthetic), plus the noise-free emission."""
    return lognormal_samples(layers["reference"] - layers["emission"], layers["emission"], SPP, rng)


def _with_samples(layers: Layers, samples: np.ndarray) -> Layers:
    """`layers` with every radiance and sample-statistics layer recomputed from `samples`."""
    half = samples.shape[0] // 2
    with np.errstate(over="ignore", invalid="ignore"):
        return {
            **layers,
            "color": samples.mean(axis=0),
            "colorA": samples[:half].mean(axis=0),
            "colorB": samples[half:].mean(axis=0),
            **statistics_from_samples(samples),
        }


def _pixels(rng: np.random.Generator, height: int, width: int, fraction: float) -> tuple[np.ndarray, np.ndarray]:
    """Row and column indices of round(fraction * H * W) random distinct pixels (at least one)."""
    count = max(1, int(round(fraction * height * width)))
    flat = rng.choice(height * width, size=min(count, height * width), replace=False)
    return np.unravel_index(flat, (height, width))


def _fireflies(value: float) -> Callable[[Layers, np.random.Generator], Layers]:
    def edit(layers: Layers, rng: np.random.Generator) -> Layers:
        samples = _samples(layers, rng)
        ys, xs = _pixels(rng, *samples.shape[1:3], FIREFLY_FRACTION)
        samples[0, ys, xs, :] = value  # one sample of the pixel hit a tiny bright light
        return _with_samples(layers, samples)

    return edit


def _black(layers: Layers, rng: np.random.Generator) -> Layers:
    zero = np.zeros_like(layers["reference"])
    samples = np.zeros((SPP, *zero.shape), np.float32)
    return _with_samples({**layers, "reference": zero, "emission": zero.copy()}, samples)


def _constant_gbuffers(layers: Layers, rng: np.random.Generator) -> Layers:
    def const(name: str, value: list[float]) -> np.ndarray:
        return np.broadcast_to(np.asarray(value, np.float32), layers[name].shape).copy()

    return _with_samples({
        **layers,
        "albedo": const("albedo", [0.5, 0.5, 0.5]),
        "normal": const("normal", [0.0, 0.0, 1.0]),
        "depth": const("depth", [5.0]),
        "motion": const("motion", [0.0, 0.0]),
        "motionDual": const("motionDual", [0.0, 0.0]),
        "roughness": const("roughness", [0.5]),
        "ao": const("ao", [1.0]),
    }, _samples(layers, rng))


def _nan_inf(layers: Layers, rng: np.random.Generator) -> Layers:
    out = {}
    for name, value in _with_samples(layers, _samples(layers, rng)).items():
        value = value.copy()
        pick = rng.random(value.shape)
        value[pick < 0.02] = np.nan
        value[(pick >= 0.02) & (pick < 0.03)] = np.inf
        value[(pick >= 0.03) & (pick < 0.04)] = -np.inf
        out[name] = value
    return out


def _scaled(scale: float) -> Callable[[Layers, np.random.Generator], Layers]:
    def edit(layers: Layers, rng: np.random.Generator) -> Layers:
        with np.errstate(over="ignore"):
            scaled = {**layers, "reference": layers["reference"] * np.float32(scale),
                      "emission": layers["emission"] * np.float32(scale)}
            return _with_samples(scaled, _samples(layers, rng) * np.float32(scale))

    return edit


def _negative(layers: Layers, rng: np.random.Generator) -> Layers:
    """Zero-mean Gaussian noise of 1.5x the radiance added to each sample: unbiased, often negative."""
    samples = _samples(layers, rng)
    radiance = (layers["reference"] - layers["emission"])[None]
    samples = samples + 1.5 * radiance * rng.standard_normal(samples.shape[:3] + (1,)).astype(np.float32)
    return _with_samples(layers, samples)


def _zero_samples(layers: Layers, rng: np.random.Generator) -> Layers:
    """20% of pixels got no sample: sampleCount 0, radiance and statistics 0 there."""
    out = _with_samples(layers, _samples(layers, rng))
    ys, xs = _pixels(rng, *layers["color"].shape[:2], 0.2)
    for name in (*RADIANCE_LAYERS, "sampleCount", "bcMean", "bcM2", "bcM3"):
        out[name] = out[name].copy()
        out[name][ys, xs] = 0.0
    return out


def _zero_normals(layers: Layers, rng: np.random.Generator) -> Layers:
    return _with_samples({**layers, "normal": np.zeros_like(layers["normal"])}, _samples(layers, rng))


def _plain(layers: Layers, rng: np.random.Generator) -> Layers:
    return _with_samples(layers, _samples(layers, rng))


@dataclass(frozen=True)
class Case:
    """One hard case: how to edit each frame of the synthetic scene, at what size."""

    name: str
    description: str
    edit: Callable[[Layers, np.random.Generator], Layers]
    size: tuple[int, int] | None = None  # (height, width) of this case; None: the suite's size
    half: bool = False  # whether the frame goes through a half-float EXR before the pipeline sees it

    def frames(self, height: int, width: int, count: int = 3, seed: int = 0) -> list[Frame]:
        """The case's `count` frames as validated Frames (NaN/Inf repaired), deterministic in `seed`."""
        height, width = self.size or (height, width)
        rng = np.random.default_rng(seed)
        frames = []
        for layers in synthetic_sequence(height, width, count, spp=2, seed=seed):
            edited = self.edit(layers, rng)
            if self.half:
                frames.append(read_frame(encode_frame(edited, half=True)))
            else:
                frames.append(Frame.from_buffers(edited))
        return frames


def _half_source(layers: Layers, rng: np.random.Generator) -> Layers:
    """Fireflies above the float16 range (they become Inf in the file, then repaired) and a
    half-precision file: every value rounded to 11 significant bits."""
    return _fireflies(4.0 * HALF_MAX)(layers, rng)


CASES: tuple[Case, ...] = (
    *(Case(f"firefly_1e{e}", f"0.5% of pixels have one sample of radiance 1e{e}", _fireflies(10.0**e))
      for e in range(3, 9)),
    Case("black", "all radiance, emission and reference zero", _black),
    Case("constant_gbuffers", "albedo, normal, depth, motion, roughness, ao constant over the frame",
         _constant_gbuffers),
    Case("nan_inf", "2% NaN, 1% +Inf, 1% -Inf values in every layer (repaired at the frame door)", _nan_inf),
    Case("size_1x1", "a 1x1 frame", _plain, size=(1, 1)),
    Case("size_2x2", "a 2x2 frame", _plain, size=(2, 2)),
    Case("size_7x13", "a 7x13 (H x W) frame", _plain, size=(7, 13)),
    Case("radiance_1e20", "radiance, emission and reference scaled by 1e20 (squares overflow float32)",
         _scaled(1e20)),
    Case("negative_radiance", "zero-mean Gaussian sample noise of 1.5x the radiance: many negative pixels",
         _negative),
    Case("zero_samples", "20% of pixels with sampleCount 0 and zero radiance/statistics", _zero_samples),
    Case("half_source", "every layer read from a half-float EXR; fireflies above 65504 arrive as Inf",
         _half_source, half=True),
    Case("zero_normals", "normal layer all zero", _zero_normals),
)
CASE_NAMES = tuple(c.name for c in CASES)


def case(name: str) -> Case:
    for c in CASES:
        if c.name == name:
            return c
    raise KeyError(f"unknown stability case '{name}'; cases: {', '.join(CASE_NAMES)}")


# ----------------------------------------------------------------------------------------------- checking


def radiance_bounds(frame: Frame) -> tuple[float, float]:
    """(lo, hi): the darkest and brightest output radiance `frame` can explain (module docstring)."""
    emission = frame.get("emission")
    e = np.zeros((1, 1, 3)) if emission is None else emission.astype(np.float64)
    hi, lo = 0.0, 0.0
    for name in RADIANCE_LAYERS:
        if name in frame:
            diff = frame[name].astype(np.float64) - e
            hi, lo = max(hi, float(diff.max())), min(lo, float(diff.min()))
    return lo + min(0.0, float(e.min())), hi + max(0.0, float(e.max()))


@dataclass(frozen=True)
class CaseResult:
    passed: bool
    reason: str  # empty when passed; what failed first, with the frame index; why it was skipped
    skipped: bool = False  # the method needs a layer the case does not have

    @property
    def label(self) -> str:
        return "skip" if self.skipped else "pass" if self.passed else "FAIL"

    def as_dict(self) -> dict[str, Any]:
        return {"passed": self.passed, "skipped": self.skipped, "reason": self.reason}


def check_output(out: Frame, height: int, width: int, lo: float, hi: float) -> str:
    """Empty string when `out` is a valid output within [lo, hi] (with the tolerances), else the reason."""
    color = out.get("color")
    if color is None or color.shape != (height, width, 3):
        return f"output color has shape {None if color is None else color.shape}, expected ({height}, {width}, 3)"
    for name, value in out.buffers.items():
        bad = int((~np.isfinite(value)).sum())
        if bad:
            return f"output '{name}' has {bad} non-finite value(s)"
    top, bottom = float(color.max()), float(color.min())
    upper = hi * (1.0 + ENERGY_RTOL) + ENERGY_ATOL
    lower = lo * (1.0 + ENERGY_RTOL) - ENERGY_ATOL
    if top > upper:
        return f"max output {top:.4g} > max explainable input {hi:.4g}"
    if bottom < lower:
        return f"min output {bottom:.4g} < min explainable input {lo:.4g}"
    return ""


def copy_frames(frames: list[Frame] | tuple[Frame, ...]) -> list[Frame]:
    """Deep copies, so a pipeline that writes into its input cannot change what the next one gets."""
    return [Frame({k: v.copy() for k, v in f.buffers.items()}, dict(f.nonfinite)) for f in frames]


def run_case(pipeline: Pipeline, frames: list[Frame], *, temporal: bool) -> CaseResult:
    """Run `frames` through a fresh sequence state of `pipeline` and check every output."""
    height, width = frames[0].height, frames[0].width
    lo, hi = 0.0, 0.0
    index = 0
    try:
        state = pipeline.start(height, width)
        for index, frame in enumerate(frames):
            f_lo, f_hi = radiance_bounds(frame)
            lo, hi = (min(lo, f_lo), max(hi, f_hi)) if temporal else (f_lo, f_hi)
            out, state = pipeline.step(frame, state)
            reason = check_output(out, height, width, lo, hi)
            if reason:
                return CaseResult(False, f"frame {index}: {reason}")
    except Exception as err:  # any exception is a failure of the case, reported with its text
        return CaseResult(False, f"frame {index}: {type(err).__name__}: {err}")
    return CaseResult(True, "")


def run_suite(
    methods: list[Any], *, height: int = 48, width: int = 64, frames: int = 3, cases: tuple[Case, ...] = CASES,
    progress: bool = True,
) -> dict[str, dict[str, CaseResult]]:
    """Every method (bench.methods.Method) on every case: method -> case -> result."""
    from tqdm import tqdm

    built = {c.name: c.frames(height, width, frames) for c in cases}
    results: dict[str, dict[str, CaseResult]] = {}
    with tqdm(total=len(methods) * len(cases), desc="stability", unit="case", disable=not progress) as bar:
        for method in methods:
            pipeline = method.make()
            row = results[method.name] = {}
            for c in cases:
                bar.set_postfix_str(f"{method.name} / {c.name}")
                missing = method.missing(set(built[c.name][0].buffers))
                if missing:
                    row[c.name] = CaseResult(True, f"needs {', '.join(missing)}", skipped=True)
                else:
                    row[c.name] = run_case(pipeline, copy_frames(built[c.name]), temporal=method.temporal)
                bar.update(1)
    return results


def matrix(results: dict[str, dict[str, CaseResult]]) -> str:
    """Pass/fail matrix, cases as rows and methods as columns, then the reasons of the failures."""
    methods = list(results)
    cases = list(next(iter(results.values()))) if results else []
    width = max([len(c) for c in cases] + [4])
    cols = [max(len(m), 4) for m in methods]
    lines = [" " * width + " | " + " | ".join(m.rjust(w) for m, w in zip(methods, cols, strict=True))]
    lines.append("-" * len(lines[0]))
    for c in cases:
        cells = [results[m][c].label for m in methods]
        lines.append(c.ljust(width) + " | " + " | ".join(s.rjust(w) for s, w in zip(cells, cols, strict=True)))
    failures = [(m, c, r.reason) for m in methods for c, r in results[m].items() if not r.passed]
    if failures:
        lines += ["", "failures:"] + [f"  {m} / {c}: {reason}" for m, c, reason in failures]
    return "\n".join(lines)
