"""`auto`: the per-tile choice by the reference-free error estimate, its blend, its fallback and its error layer."""

import copy

import numpy as np
import pytest

from bench.synthetic import synthetic_sequence
from service import pipelines
from service.frame import Frame
from service.pipelines import tiled
from service.pipelines.tiled import CANDIDATES, choose, one_half, run_half, tile_weights
from service.stages.error_estimate import interpolate_tiles


@pytest.fixture(scope="module")
def frames():
    return [Frame.from_buffers(x) for x in synthetic_sequence(40, 72, 5, spp=8, seed=11)]


def _run(pipeline, frames):
    state = pipeline.start(frames[0].height, frames[0].width)
    outs = []
    for frame in frames:
        out, state = pipeline.step(frame, state)
        outs.append(out)
    return outs, state


def test_choice_is_the_cheapest_candidate_within_the_tolerance_of_the_best():
    estimate = np.array([[[1.04, 2.0]], [[1.00, 1.0]], [[1.50, 1.2]]])  # (K=3, 1, 2), cheapest first
    np.testing.assert_array_equal(choose(estimate, 0.05), [[0, 1]])  # 1.04 is within 5% of 1.00
    np.testing.assert_array_equal(choose(estimate, 0.0), [[1, 1]])
    np.testing.assert_array_equal(choose(estimate, 0.5), [[0, 1]])
    np.testing.assert_array_equal(choose(estimate, 1.0), [[0, 0]])
    negative = np.array([[[0.02]], [[-0.01]]])  # a noisy estimate below zero: only the best is eligible
    np.testing.assert_array_equal(choose(negative, 0.05), [[1]])


def test_blend_weights_sum_to_one_without_seams_and_are_pure_inside_uniform_regions():
    choice = np.array([[0, 0, 1, 1], [0, 0, 1, 1], [2, 2, 2, 2]])
    weights = tile_weights(choice, 3, 8, 21, 30)  # ragged last row and column of tiles
    assert weights.shape == (3, 21, 30) and (weights >= 0).all()
    np.testing.assert_allclose(weights.sum(axis=0), 1.0, atol=1e-6)
    assert weights[0, 0, 0] == 1.0 and weights[1, 0, 29] == 1.0 and weights[2, 20, 15] == 1.0
    assert np.abs(np.diff(weights, axis=2)).max() <= 1.0 / 8 + 1e-6  # at most one tile-width ramp: no seam
    np.testing.assert_allclose(interpolate_tiles(np.full((3, 4), 2.5), 8, 21, 30), 2.5)


def test_without_halves_it_is_the_layers_choice_exactly(frames):
    plain = [Frame({k: v for k, v in f.buffers.items() if k not in ("colorA", "colorB")}) for f in frames]
    outs, state = _run(pipelines.get("auto"), plain)
    name = pipelines.auto(set(plain[0].buffers))
    expected, _ = _run(pipelines.get(name), plain)
    assert state.fallback is not None and state.fallback.name == name
    for out, ref in zip(outs, expected, strict=True):
        np.testing.assert_array_equal(out["color"], ref["color"])
        assert "error" not in out


def test_with_halves_it_chooses_per_tile_reevaluates_every_k_frames_and_outputs_its_estimate(frames, monkeypatch):
    calls = []
    evaluate = tiled.AutoPipeline._evaluate
    monkeypatch.setattr(tiled.AutoPipeline, "_evaluate", lambda self, f, s: (calls.append(s.frame_index),
                                                                                evaluate(self, f, s)))
    outs, state = _run(pipelines.get("auto", tile=16, every=2), frames)
    assert calls == [0, 2, 4]
    assert list(state.candidates) == list(CANDIDATES) and state.choice.shape == (3, 5)
    for out in outs:
        assert out["color"].shape == (40, 72, 3) and np.isfinite(out["color"]).all()
        assert out["error"].shape == (40, 72, 1) and out["error"].dtype == np.float32
    np.testing.assert_array_equal(outs[3]["error"], outs[2]["error"])  # frame 3 keeps frame 2's evaluation
    chosen = np.take_along_axis(state.estimate, state.choice[None], axis=0)[0]
    np.testing.assert_allclose(outs[-1]["error"][0, 0, 0], max(chosen[0, 0], 0.0), rtol=1e-6)  # before the 1st centre
    # each frame is the weighted blend of the chosen candidates, each stepped on the frame from its own state
    chosen = sorted(set(state.choice.ravel().tolist()))
    assert set(state.states) == {CANDIDATES[i] for i in chosen}


def test_a_candidate_alone_is_served_exactly_when_every_tile_chooses_it(frames, monkeypatch):
    monkeypatch.setattr(tiled, "choose", lambda estimate, tolerance: np.zeros(estimate.shape[1:], np.int64))
    outs, _ = _run(pipelines.get("auto"), frames)
    expected, _ = _run(pipelines.get(CANDIDATES[0]), frames)
    for out, ref in zip(outs, expected, strict=True):
        np.testing.assert_allclose(out["color"], ref["color"], rtol=1e-6, atol=1e-7)


def test_a_frame_without_halves_after_the_choice_started_is_refused_naming_the_layer(frames):
    from service.frame import FrameError

    pipeline = pipelines.get("auto", every=2)
    state = pipeline.start(40, 72)
    _, state = pipeline.step(frames[0], state)
    plain = Frame({k: v for k, v in frames[1].buffers.items() if k != "colorB"})
    with pytest.raises(FrameError, match="pipeline 'auto' .* no layer 'colorB'"):
        pipeline.step(plain, state)
    out, state = pipeline.step(frames[1], state)  # the session goes on with the next good frame
    assert state.frame_index == 2 and np.isfinite(out["color"]).all()


def test_an_error_pass_in_an_input_file_is_ignored(tmp_path, frames):
    from service.exr import read_frame, write_frame

    path = tmp_path / "f.exr"
    write_frame(path, {"color": frames[0]["color"]})
    import OpenEXR

    with OpenEXR.File(str(path)) as exr:
        channels = dict(exr.channels())
    channels["error"] = OpenEXR.Channel(np.ones((40, 72, 3), np.float32))  # a renderer's own RGB 'error' AOV
    OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}, channels).write(str(path))
    assert set(read_frame(path).buffers) == {"color"}


def test_two_chosen_candidates_are_blended_by_their_tile_weights(frames, monkeypatch):
    """Left tiles to the first candidate, the rest to the second: every frame is their outputs (each run
    alone from the sequence's start) weighted by `tile_weights`."""

    def split(estimate, tolerance):
        choice = np.ones(estimate.shape[1:], np.int64)
        choice[:, :2] = 0
        return choice

    monkeypatch.setattr(tiled, "choose", split)
    outs, state = _run(pipelines.get("auto", tile=16), frames)
    weights = tile_weights(state.choice, len(CANDIDATES), 16, 40, 72)
    alone = [_run(pipelines.get(name), frames)[0] for name in CANDIDATES[:2]]
    for index, out in enumerate(outs):
        expected = sum(weights[k][..., None] * alone[k][index]["color"] for k in range(2))
        np.testing.assert_allclose(out["color"], expected, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("both_halves", [True, False])
def test_each_evaluation_averages_with_the_previous_estimate(frames, monkeypatch, both_halves):
    from service.stages.error_estimate import TileError

    calls = []

    def fake(*args, **kwargs):
        calls.append(len(calls))
        value = np.full((3, 5), float(len(calls)))  # 1, 2, 3, ... per candidate call
        return TileError(value, np.zeros_like(value), 16)

    monkeypatch.setattr(tiled, "cross_tile_error" if both_halves else "tile_error", fake)
    _, state = _run(pipelines.get("auto", tile=16, every=2, both_halves=both_halves), frames[:3])  # frames 0, 2
    k = len(CANDIDATES)
    first = np.arange(1, k + 1, dtype=float)
    second = np.arange(k + 1, 2 * k + 1, dtype=float)
    np.testing.assert_allclose(state.estimate[:, 0, 0], 0.5 * (first + second))


def test_the_estimate_both_ways_compares_each_candidate_on_half_a_and_on_half_b(frames, monkeypatch):
    """At the first frame each candidate's f(A) and f(B) (from fresh states) go to `cross_tile_error` with the
    halves, and the estimate is what it returns."""
    from service.stages.error_estimate import cross_tile_error

    seen = []

    def spy(out_a, out_b, color_a, color_b, scale, tile, cap=None):
        seen.append((out_a, out_b))
        return cross_tile_error(out_a, out_b, color_a, color_b, scale, tile, cap=cap)

    monkeypatch.setattr(tiled, "cross_tile_error", spy)
    _, state = _run(pipelines.get("auto", tile=16, every=8), frames[:1])
    frame = frames[0]
    outputs = {h: [_run(pipelines.get(n), [one_half(frame, h)])[0][0]["color"] for n in CANDIDATES]
               for h in ("colorA", "colorB")}
    assert len(seen) == len(CANDIDATES)
    scale = np.median(outputs["colorA"] + outputs["colorB"], axis=0)
    for k, (out_a, out_b) in enumerate(seen):
        np.testing.assert_array_equal(out_a, outputs["colorA"][k])
        np.testing.assert_array_equal(out_b, outputs["colorB"][k])
        expected = cross_tile_error(out_a, out_b, frame["colorA"], frame["colorB"], scale, 16,
                                    cap=tiled.FIREFLY_CAP).mean
        np.testing.assert_array_equal(state.estimate[k], expected)


def test_a_running_candidate_is_judged_from_a_copy_of_its_state(frames, monkeypatch):
    """At a later evaluation a chosen temporal candidate (svgf) denoises each half from a copy of its running
    state, with its history: what that state gives, not what a fresh state gives, and the running state
    itself is left as it was."""
    monkeypatch.setattr(tiled, "choose", lambda estimate, tolerance: np.full(estimate.shape[1:], 2, np.int64))
    assert CANDIDATES[2] == "svgf"
    seen = []

    def spy(pipeline, frame, running):
        before = copy.deepcopy(running)
        out = run_half(pipeline, frame, running)
        if pipeline.name == "svgf":
            seen.append((frame, before, out))
            if running is not None:  # untouched by the evaluation
                assert running.frame_index == before.frame_index
                np.testing.assert_array_equal(running.history, before.history)
        return out

    monkeypatch.setattr(tiled, "run_half", spy)
    _run(pipelines.get("auto", tile=16, every=2), frames[:3])  # evaluations at frames 0 and 2
    assert [running is None for _, running, _ in seen] == [True, True, False, False]
    svgf = pipelines.get("svgf")
    for frame, running, out in seen[2:]:
        assert running.frame_index == 2
        np.testing.assert_array_equal(out, svgf.step(frame, copy.deepcopy(running))[0]["color"])
        assert not np.allclose(out, run_half(svgf, frame, None))  # the history is used


@pytest.mark.parametrize("name", CANDIDATES)
def test_every_candidates_running_state_can_be_copied_for_its_evaluation(frames, name):
    """`run_half` deep-copies a running candidate's state: it must hold arrays and numbers only (no ONNX
    session, no online worker), and the copy must not share an array with the running state."""
    pipeline = pipelines.get(name)
    _, state = pipeline.step(frames[0], pipeline.start(frames[0].height, frames[0].width))
    forked = copy.deepcopy(state)
    for key, value in vars(state).items():
        if isinstance(value, np.ndarray):
            assert not np.shares_memory(value, getattr(forked, key)), key
        else:
            assert value is None or isinstance(value, int | float | str | bool | list), (key, type(value))
