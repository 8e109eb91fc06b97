"""The hard-case stability suite (bench/stability.py) on every registered pipeline, at small sizes.

Parametrised over `pipelines.names()`, so a new pipeline is tested as soon as it registers. A failure
here is the pipeline's bug (see the criterion in bench/stability.py), not the suite's.
"""

from __future__ import annotations

from functools import cache

import numpy as np
import pytest

from bench.methods import Method, anchor_method, pipeline_method
from bench.stability import (
    CASE_NAMES,
    CASES,
    case,
    check_output,
    copy_frames,
    radiance_bounds,
    run_case,
    run_suite,
)
from service import pipelines
from service.frame import Frame
from service.pipelines.base import Pipeline, SequenceState

HEIGHT, WIDTH = 32, 48  # size of the cases without a fixed size: small, the suite must stay fast
FRAMES = 3


@cache
def _frames(name: str) -> tuple[Frame, ...]:
    return tuple(case(name).frames(HEIGHT, WIDTH, FRAMES))


@cache
def _pipeline(name: str) -> tuple[Pipeline, Method]:
    return pipelines.get(name), pipeline_method(name)


@pytest.mark.parametrize("case_name", CASE_NAMES)
@pytest.mark.parametrize("pipeline_name", pipelines.names())
def test_pipeline_survives_hard_case(pipeline_name: str, case_name: str) -> None:
    pipeline, method = _pipeline(pipeline_name)
    frames = copy_frames(_frames(case_name))
    missing = method.missing(set(frames[0].buffers))
    if missing:
        pytest.skip(f"{pipeline_name} needs {missing}")
    result = run_case(pipeline, frames, temporal=method.temporal)
    assert result.passed, f"{pipeline_name} / {case_name}: {result.reason}"


def test_cases_are_what_they_say() -> None:
    assert len(set(CASE_NAMES)) == len(CASES)
    assert [f.height for f in _frames("size_7x13")] == [7] * FRAMES and _frames("size_7x13")[0].width == 13
    assert _frames("size_1x1")[0].width == 1
    black = _frames("black")[0]
    assert radiance_bounds(black) == (0.0, 0.0)
    assert float(_frames("firefly_1e8")[0]["colorA"].max()) >= 1e8 / 2 * 0.99  # one of two samples
    assert float(_frames("radiance_1e20")[0]["color"].max()) > 1e20
    assert float(_frames("negative_radiance")[0]["color"].min()) < 0.0
    assert (_frames("zero_samples")[0]["sampleCount"] == 0).any()
    assert not _frames("zero_normals")[0]["normal"].any()
    assert _frames("nan_inf")[0].nonfinite_total > 0 and _frames("half_source")[0].nonfinite.get("colorA", 0) > 0
    for frames in map(_frames, CASE_NAMES):
        assert all(np.isfinite(v).all() for f in frames for v in f.buffers.values())


def test_bounds_count_emission_once_on_top() -> None:
    color = np.full((1, 2, 3), 2.0, np.float32)
    emission = np.zeros((1, 2, 3), np.float32)
    emission[0, 0] = 8.0
    frame = Frame.from_buffers({"color": color + emission, "emission": emission})
    assert radiance_bounds(frame) == (0.0, 10.0)  # non-emitted 2 plus emission 8
    negative = Frame.from_buffers({"color": np.full((1, 1, 3), -3.0, np.float32)})
    assert radiance_bounds(negative) == (-3.0, 0.0)


class _Brightener(Pipeline):
    """A broken denoiser: adds light that is not in the input on frame 1."""

    name, summary, requires, temporal = "brightener", "test double", ("color",), False
    guards = False  # the noise clamp would take the added light out again: this double tests the criterion

    def denoise(self, frame: Frame, state: SequenceState):
        return {"color": frame["color"] + (1.0 if state.frame_index == 1 else 0.0)}, state


class _Raiser(_Brightener):
    def denoise(self, frame: Frame, state: SequenceState):
        raise ZeroDivisionError("oops")


def test_criterion_catches_energy_exceptions_and_bad_shapes() -> None:
    frames = case("black").frames(4, 5)
    bright = run_case(_Brightener(), frames, temporal=False)
    assert not bright.passed and bright.reason.startswith("frame 1: max output 1 > max explainable input 0")
    raised = run_case(_Raiser(), frames, temporal=False)
    assert not raised.passed and raised.reason == "frame 0: ZeroDivisionError: oops"
    assert "non-finite" in check_output(Frame({"color": np.full((2, 2, 3), np.nan, np.float32)}), 2, 2, 0, 1)
    assert "shape" in check_output(Frame({"color": np.zeros((2, 3, 3), np.float32)}), 2, 2, 0, 1)
    assert "min output" in check_output(Frame({"color": np.full((2, 2, 3), -1.0, np.float32)}), 2, 2, 0, 1)
    assert check_output(Frame({"color": np.full((2, 2, 3), 1.0005, np.float32)}), 2, 2, 0, 1) == ""  # rtol 1e-3


def test_suite_runs_the_noisy_anchor_clean() -> None:
    results = run_suite([anchor_method("noisy")], height=6, width=8, frames=2, progress=False)
    assert all(r.passed for r in results["noisy"].values())
    assert set(results["noisy"]) == set(CASE_NAMES)
