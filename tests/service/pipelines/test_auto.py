"""`auto`: the per-tile choice by the reference-free error estimate, its blend, its fallback and its error layer."""

import copy
import dataclasses

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


COSTS = np.array([1.0, 1.1, 4.0, 7.0])  # flr, bmfr, svgf, kpn (tiled.COSTS' ratios, rounded)


def test_the_main_candidate_is_the_cheapest_near_the_lowest_total_and_others_take_tiles_by_a_margin():
    # (K=4, 1, 3): totals 3.3, 3.12, 3.6, 3.0; near the lowest (3.0) within 5%: kpn and bmfr (3.12) -> bmfr
    estimate = np.array([[[1.1, 1.1, 1.1]], [[1.04, 1.04, 1.04]], [[1.2, 1.2, 1.2]], [[1.0, 1.0, 1.0]]])
    choice, main = choose(estimate, COSTS, 0.05, 100.0)
    assert main == 1
    np.testing.assert_array_equal(choice, [[1, 1, 1]])  # kpn is lower, but not by more than 5% of 1.04
    choice, main = choose(estimate, COSTS, 0.0, 100.0)
    assert main == 3
    np.testing.assert_array_equal(choice, [[3, 3, 3]])
    # one tile where svgf is much better: it takes it, the lowest of those that beat the main one there
    estimate[2] = [[1.6, 1.6, 0.5]]
    choice, main = choose(estimate, COSTS, 0.05, 100.0)
    assert main == 1
    np.testing.assert_array_equal(choice, [[1, 1, 2]])
    negative = np.array([[[0.02]], [[-0.01]]])  # a noisy estimate below zero: only the best is near it
    assert choose(negative, COSTS[:2], 0.05, 100.0)[1] == 1


def test_where_several_beat_the_main_one_the_lowest_takes_the_tile_and_a_main_with_no_tile_gives_way():
    estimate = np.array([[[1.0, 1.0, 1.0]], [[0.8, 1.0, 1.0]], [[0.6, 1.0, 1.0]], [[0.9, 0.5, 1.0]]])
    estimate[0, 0, 2] = -1.0  # flr's total is the lowest: it is main
    choice, main = choose(estimate, COSTS, 0.05, 100.0)
    assert main == 0
    np.testing.assert_array_equal(choice, [[2, 3, 0]])  # svgf (0.6) over bmfr (0.8) and kpn (0.9)
    below = np.array([[[-1.0, -1.0]], [[-1.3, -1.3]]])  # bmfr beats flr by more than 5% everywhere
    choice, main = choose(below, COSTS[:2], 0.2, 100.0, previous=0)  # flr stays near (within 20%) ...
    np.testing.assert_array_equal(choice, [[1, 1]])
    assert main == 1  # ... but serves no tile: bmfr is main


def test_the_budget_keeps_the_others_that_gain_most_while_their_cost_fits():
    # main flr (cost 1); bmfr gains a little on tile 0, svgf and kpn a lot on tiles 1 and 2
    estimate = np.array([[[1.0, 1.0, 1.0, 1.0]], [[0.8, 1.0, 1.0, 1.0]], [[1.0, 0.3, 1.0, 1.0]],
                         [[1.0, 1.0, 0.2, 1.0]]])
    estimate[0, 0, 3] = -2.0  # flr's total is the lowest
    everything, main = choose(estimate, COSTS, 0.05, 100.0)
    assert main == 0
    np.testing.assert_array_equal(everything, [[1, 2, 3, 0]])
    np.testing.assert_array_equal(choose(estimate, COSTS, 0.05, 1.0)[0], [[0, 0, 0, 0]])  # the main one alone
    np.testing.assert_array_equal(choose(estimate, COSTS, 0.05, 2.1)[0], [[1, 0, 0, 0]])  # bmfr fits, svgf not
    np.testing.assert_array_equal(choose(estimate, COSTS, 0.05, 8.0)[0], [[0, 0, 3, 0]])  # kpn gains most, fits
    np.testing.assert_array_equal(choose(estimate, COSTS, 0.05, 12.1)[0], [[0, 2, 3, 0]])  # then svgf
    for budget in (1.0, 2.1, 8.0, 12.1, 100.0):
        chosen = np.unique(choose(estimate, COSTS, 0.05, budget)[0])
        assert COSTS[chosen].sum() <= budget * COSTS[main]


def test_the_last_main_candidate_stays_while_it_is_near_the_lowest():
    estimate = np.array([[[1.04]], [[1.0]], [[1.2]]])  # flr within 5% of bmfr
    assert choose(estimate, COSTS[:3], 0.05, 1.0)[1] == 0
    assert choose(estimate, COSTS[:3], 0.05, 1.0, previous=1)[1] == 1  # bmfr ran: it stays
    assert choose(estimate, COSTS[:3], 0.05, 1.0, previous=2)[1] == 0  # svgf is not near: the cheapest near one


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
    assert calls == [0, 1, 2, 4]
    assert list(state.candidates) == list(CANDIDATES) and state.choice.shape == (3, 5)
    for out in outs:
        assert out["color"].shape == (40, 72, 3) and np.isfinite(out["color"]).all()
        assert out["error"].shape == (40, 72, 1) and out["error"].dtype == np.float32
    np.testing.assert_array_equal(outs[3]["error"], outs[2]["error"])  # frame 3 keeps frame 2's evaluation
    chosen, spread = (np.take_along_axis(x, state.choice[None], axis=0)[0] for x in (state.estimate, state.variance))
    floored = max(chosen[0, 0], np.sqrt(spread[0, 0]))  # an estimate at least its standard error
    np.testing.assert_allclose(outs[-1]["error"][0, 0, 0], floored, rtol=1e-6)  # before the first tile centre
    # each frame is the weighted blend of the chosen candidates, each stepped on the frame from its own state
    chosen = sorted(set(state.choice.ravel().tolist()))
    assert set(state.states) == {CANDIDATES[i] for i in chosen}


def test_a_candidate_alone_is_served_exactly_when_every_tile_chooses_it(frames, monkeypatch):
    monkeypatch.setattr(tiled, "choose", lambda estimate, *args: (np.zeros(estimate.shape[1:], np.int64), 0))
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

    def split(estimate, *args):
        choice = np.ones(estimate.shape[1:], np.int64)
        choice[:, :2] = 0
        return choice, 1

    monkeypatch.setattr(tiled, "choose", split)
    outs, state = _run(pipelines.get("auto", tile=16), frames)
    weights = tile_weights(state.choice, len(CANDIDATES), 16, 40, 72)
    alone = [_run(pipelines.get(name), frames)[0] for name in CANDIDATES[:2]]
    for index, out in enumerate(outs):
        expected = sum(weights[k][..., None] * alone[k][index]["color"] for k in range(2))
        np.testing.assert_allclose(out["color"], expected, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("both_halves", [True, False])
def test_each_evaluation_averages_with_the_previous_one_but_the_first(frames, monkeypatch, both_halves):
    from service.stages.error_estimate import TileError

    calls = []

    def fake(*args, **kwargs):
        calls.append(len(calls))
        value = np.full((3, 5), float(len(calls)))  # 1, 2, 3, ... per candidate call
        return TileError(value, 2 * value, 16)

    monkeypatch.setattr(tiled, "cross_tile_error" if both_halves else "tile_error", fake)
    pipeline = pipelines.get("auto", tile=16, every=2, both_halves=both_halves)
    state = pipeline.start(40, 72)
    k = len(CANDIDATES)
    for index, frame in enumerate(frames[:3]):  # evaluations at frames 0, 1 and 2
        _, state = pipeline.step(frame, state)
        calls_so_far = np.arange(index * k + 1, (index + 1) * k + 1, dtype=float)
        if index < 2:  # the first frame's, made without history, is not averaged into the second's
            np.testing.assert_allclose(state.estimate[:, 0, 0], calls_so_far)
    np.testing.assert_allclose(state.estimate[:, 0, 0], 0.5 * (calls_so_far - k + calls_so_far))
    np.testing.assert_allclose(state.variance[:, 0, 0], 0.25 * 2 * (calls_so_far - k + calls_so_far))


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
    monkeypatch.setattr(tiled, "choose", lambda estimate, *args: (np.full(estimate.shape[1:], 2, np.int64), 2))
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
    _run(pipelines.get("auto", tile=16, every=2), frames[:3])  # evaluations at frames 0, 1 and 2
    assert [running is None for _, running, _ in seen] == [True, True, False, False, False, False]
    svgf = pipelines.get("svgf")
    for (frame, running, out), index in zip(seen[2:], (1, 1, 2, 2), strict=True):
        assert running.frame_index == index
        np.testing.assert_array_equal(out, svgf.step(frame, copy.deepcopy(running))[0]["color"])
        assert not np.allclose(out, run_half(svgf, frame, None))  # the history is used


def test_a_temporal_candidate_not_running_is_judged_with_a_history_through_the_previous_frame(frames, monkeypatch):
    """flr alone is chosen, so svgf never runs; at the second frame's evaluation svgf denoises each half from a
    state stepped through the first frame, bmfr from a fresh one (it keeps no history; flr runs: its own state)."""
    monkeypatch.setattr(tiled, "choose", lambda estimate, *args: (np.zeros(estimate.shape[1:], np.int64), 0))
    seen = []

    def spy(pipeline, frame, running):
        seen.append((pipeline.name, frame, None if running is None else copy.deepcopy(running)))
        return run_half(pipeline, frame, running)

    monkeypatch.setattr(tiled, "run_half", spy)
    _, state = _run(pipelines.get("auto", tile=16, every=4), frames[:2])
    assert list(state.states) == ["flr"]
    second = seen[2 * len(CANDIDATES):]
    svgf = pipelines.get("svgf")
    _, history = svgf.step(frames[0], svgf.start(40, 72))
    assert {name for name, _, running in second if running is None} == {"bmfr"}  # not temporal, not running
    for name, _, running in second:
        if name == "svgf":
            assert running.frame_index == 1
            np.testing.assert_array_equal(running.history, history.history)


@pytest.mark.parametrize("name", CANDIDATES)
def test_every_candidates_running_state_can_be_copied_for_its_evaluation(frames, name):
    """`run_half` deep-copies a running candidate's state: it must hold arrays, numbers and dataclasses of them
    only (no ONNX session, no online worker), and the copy must not share an array with the running state."""
    pipeline = pipelines.get(name)
    _, state = pipeline.step(frames[0], pipeline.start(frames[0].height, frames[0].width))
    _, state = pipeline.step(frames[1], state)

    def check(original, forked, path):
        for key, value in vars(original).items():
            if isinstance(value, np.ndarray):
                assert not np.shares_memory(value, getattr(forked, key)), path + key
            elif dataclasses.is_dataclass(value):
                check(value, getattr(forked, key), f"{path}{key}.")
            else:
                assert value is None or isinstance(value, int | float | str | bool | list), (path + key, type(value))

    check(state, copy.deepcopy(state), "")


def test_the_main_candidate_is_handed_to_the_next_evaluation(frames, monkeypatch):
    """choose gets the last main candidate as `previous` (none at the first evaluation); the previous frame is kept
    only where an evaluation comes next."""
    seen = []

    def spy(estimate, costs, tolerance, budget, previous=None):
        seen.append(previous)
        return np.full(estimate.shape[1:], 2, np.int64), 2

    monkeypatch.setattr(tiled, "choose", spy)
    pipeline = pipelines.get("auto", tile=16, every=3)
    state = pipeline.start(40, 72)
    kept = []
    for frame in frames[:4]:  # evaluations at frames 0, 1 and 3
        _, state = pipeline.step(frame, state)
        kept.append(state.previous is frame)
    assert seen == [None, 2, 2]
    assert kept == [True, False, True, False]  # after frames 0 and 2: frames 1 and 3 evaluate
    state.close()
    assert state.previous is None


def test_the_error_layer_is_at_least_the_estimates_standard_error(frames, monkeypatch):
    """A tile whose estimate fell below zero by chance reads as its standard error, not as error-free; one
    above it reads as itself."""
    from service.stages.error_estimate import TileError

    def fake(*args, **kwargs):
        mean = np.full((3, 5), -1.0)
        mean[:, 3:] = 5.0
        return TileError(mean, np.full((3, 5), 4.0), 16)

    monkeypatch.setattr(tiled, "cross_tile_error", fake)
    outs, _ = _run(pipelines.get("auto", tile=16), frames[:1])
    error = outs[0]["error"][..., 0]
    np.testing.assert_allclose(error[:, :16], 2.0, rtol=1e-6)  # sqrt(4), interpolated between equal tiles
    np.testing.assert_allclose(error[:, 60:], 5.0, rtol=1e-6)
