"""`auto`: the per-tile blend by the reference-free error estimate, its members, its fallback and its error layer."""

import copy
import dataclasses

import numpy as np
import pytest

from bench.synthetic import synthetic_sequence
from service import pipelines
from service.frame import Frame, FrameError
from service.pipelines import tiled
from service.pipelines.tiled import CANDIDATES, one_half, run_half
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


def _alone(index: int):
    """A `choose` that runs candidate `index` alone on every tile."""

    def choose(covariance, *args):
        weights = np.zeros(covariance.shape[1:])
        weights[index] = 1.0
        return weights, (index,)

    return choose


def test_blend_weights_sum_to_one_without_seams_and_are_pure_inside_uniform_regions():
    choice = np.array([[0, 0, 1, 1], [0, 0, 1, 1], [2, 2, 2, 2]])
    blend = np.stack([(choice == k).astype(float) for k in range(3)])
    blend[:, 0, 0] = [0.25, 0.0, 0.75]  # a tile blended from two
    weights = interpolate_tiles(blend, 8, 21, 30)  # ragged last row and column of tiles
    assert weights.shape == (3, 21, 30) and (weights >= 0).all()
    np.testing.assert_allclose(weights.sum(axis=0), 1.0, atol=1e-6)
    assert weights[1, 0, 29] == 1.0 and weights[2, 20, 15] == 1.0
    np.testing.assert_allclose(weights[:, 0, 0], [0.25, 0.0, 0.75])
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


def test_with_halves_it_blends_per_tile_reevaluates_every_k_frames_and_outputs_its_estimate(frames, monkeypatch):
    calls = []
    evaluate = tiled.AutoPipeline._evaluate
    monkeypatch.setattr(tiled.AutoPipeline, "_evaluate", lambda self, f, s: (calls.append(s.frame_index),
                                                                                evaluate(self, f, s))[1])
    outs, state = _run(pipelines.get("auto", tile=16, every=2), frames)
    assert calls == [0, 1, 2, 4]
    assert list(state.candidates) == list(CANDIDATES) and state.blend.shape == (len(CANDIDATES), 3, 5)
    for out in outs:
        assert out["color"].shape == (40, 72, 3) and np.isfinite(out["color"]).all()
        assert out["error"].shape == (40, 72, 1) and out["error"].dtype == np.float32
    np.testing.assert_array_equal(outs[3]["error"], outs[2]["error"])  # frame 3 keeps frame 2's evaluation
    assert (outs[-1]["error"][..., 0] >= interpolate_tiles(state.error_tiles, 16, 40, 72) * (1 - 1e-6)).all()
    # each frame is the weighted blend of the members, each stepped on the frame from its own state
    assert set(state.states) == {CANDIDATES[i] for i in state.members}
    assert set(np.flatnonzero(state.blend.reshape(len(CANDIDATES), -1).sum(axis=1))) == set(state.members)


def test_a_candidate_alone_is_served_exactly_when_every_tile_chooses_it(frames, monkeypatch):
    monkeypatch.setattr(tiled, "choose", _alone(0))
    outs, _ = _run(pipelines.get("auto"), frames)
    expected, _ = _run(pipelines.get(CANDIDATES[0]), frames)
    for out, ref in zip(outs, expected, strict=True):
        np.testing.assert_allclose(out["color"], ref["color"], rtol=1e-6, atol=1e-7)


def test_a_frame_without_halves_after_the_blend_started_is_refused_naming_the_layer(frames):
    pipeline = pipelines.get("auto", every=2)
    state = pipeline.start(40, 72)
    _, state = pipeline.step(frames[0], state)
    plain = Frame({k: v for k, v in frames[1].buffers.items() if k != "colorB"})
    with pytest.raises(FrameError, match="pipeline 'auto' .* no layer 'colorB'"):
        pipeline.step(plain, state)
    out, state = pipeline.step(frames[1], state)  # the session goes on with the next good frame, as a new start
    assert state.frame_index == 2 and state.begun == 1 and np.isfinite(out["color"]).all()
    fresh, _ = pipeline.step(frames[1], pipeline.start(40, 72))
    np.testing.assert_array_equal(out["color"], fresh["color"])


def test_after_a_refused_frame_a_frame_without_halves_starts_a_sequence_of_the_fallback(frames):
    """A refused frame starts the sequence again with what the next frame has: without halves, the fallback,
    as a fresh sequence would take it; the frame index goes on counting."""
    pipeline = pipelines.get("auto")
    state = pipeline.start(40, 72)
    _, state = pipeline.step(frames[0], state)
    with pytest.raises(FrameError):
        pipeline.step(Frame({k: v for k, v in frames[1].buffers.items() if k != "normal"}), state)
    plain = Frame({k: v for k, v in frames[2].buffers.items() if k not in ("colorA", "colorB")})
    out, state = pipeline.step(plain, state)
    fresh, fresh_state = pipeline.step(plain, pipeline.start(40, 72))
    assert state.fallback is not None and state.fallback.name == fresh_state.fallback.name
    assert state.frame_index == 2
    np.testing.assert_array_equal(out["color"], fresh["color"])


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
    """Left tiles to the first candidate, the rest to a 30/70 blend of both: every frame is their outputs (each
    run alone from the sequence's start) weighted by the tiles' weights interpolated between their centres."""

    def split(covariance, *args):
        weights = np.zeros(covariance.shape[1:])
        weights[0], weights[1] = 0.3, 0.7
        weights[0, :, :2], weights[1, :, :2] = 1.0, 0.0
        return weights, (0, 1)

    monkeypatch.setattr(tiled, "choose", split)
    outs, state = _run(pipelines.get("auto", tile=16), frames)
    weights = interpolate_tiles(state.blend, 16, 40, 72)
    alone = [_run(pipelines.get(name), frames)[0] for name in CANDIDATES[:2]]
    for index, out in enumerate(outs):
        expected = sum(weights[k][..., None] * alone[k][index]["color"] for k in range(2))
        np.testing.assert_allclose(out["color"], expected, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("both_halves", [True, False])
def test_each_evaluation_averages_with_the_previous_one_but_the_first(frames, monkeypatch, both_halves):
    calls = []

    def fake(outs_a, color_a, color_b, scale, tile, cap=None, outs_b=None):
        calls.append(outs_b is not None)
        return np.full((len(outs_a), len(outs_a), 3, 5), float(len(calls)))  # 1, 2, 3: one call per evaluation

    monkeypatch.setattr(tiled, "tile_covariance", fake)
    pipeline = pipelines.get("auto", tile=16, every=2, both_halves=both_halves)
    state = pipeline.start(40, 72)
    for index, frame in enumerate(frames[:3]):  # evaluations at frames 0, 1 and 2
        _, state = pipeline.step(frame, state)
        if index < 2:  # the first frame's, made without history, is not averaged into the second's
            np.testing.assert_allclose(state.covariance, index + 1.0)
    np.testing.assert_allclose(state.covariance, 0.5 * (2.0 + 3.0))
    assert calls == [both_halves] * 3


def test_tiles_whose_content_moved_since_the_last_evaluation_are_not_averaged(frames, monkeypatch):
    """Where the frames' `motion` since the last evaluation, summed, moves a tile's content by more than MOVED
    pixels on average, the last evaluation's estimates (of other content) are averaged neither into the
    covariance nor into the error layer; elsewhere they are. Two frames of half MOVED each move it beyond."""
    from service.stages.error_estimate import TileError

    calls = []

    def fake(outs_a, *args, **kwargs):
        calls.append(1)
        return np.full((len(outs_a), len(outs_a), 3, 5), float(len(calls)))

    def estimate(*args, **kwargs):
        return TileError(np.full((3, 5), float(len(calls))), np.zeros((3, 5)), 16)

    monkeypatch.setattr(tiled, "tile_covariance", fake)
    monkeypatch.setattr(tiled, "cross_tile_error", estimate)
    monkeypatch.setattr(tiled, "choose", _alone(0))  # the same blend at every evaluation
    moving = []
    for frame in frames[:4]:
        motion = np.zeros((40, 72, 2), np.float32)
        motion[:, 48:, 0] = 0.6 * tiled.MOVED  # the last two columns of 16x16 tiles move, the rest stays
        moving.append(frame.replace(motion=motion))
    _, state = _run(pipelines.get("auto", tile=16, every=3), moving)  # evaluations at frames 0, 1 and 3
    np.testing.assert_allclose(state.covariance[..., :3], 0.5 * (2.0 + 3.0))
    np.testing.assert_allclose(state.covariance[..., 3:], 3.0)
    np.testing.assert_allclose(state.error_tiles[:, :3], 0.5 * (2.0 + 3.0))
    np.testing.assert_allclose(state.error_tiles[:, 3:], 3.0)
    assert np.all(state.variance_factor[:, :3] == 0.5) and np.all(state.variance_factor[:, 3:] == 1.0)


def test_a_choice_that_fails_leaves_the_members_as_they_were(frames, monkeypatch):
    """An evaluation whose choice raises (the session answers 4xx and goes on) has stepped no member through
    the frame: the members stay in step with auto's frame count."""
    pipeline = pipelines.get("auto", tile=16, every=2)
    state = pipeline.start(40, 72)
    for frame in frames[:2]:
        _, state = pipeline.step(frame, state)
    counts = {name: s.frame_index for name, s in state.states.items()}

    def fail(*args, **kwargs):
        raise ValueError("no blend")

    monkeypatch.setattr(tiled, "choose", fail)
    with pytest.raises(ValueError, match="no blend"):
        pipeline.step(frames[2], state)
    assert {name: s.frame_index for name, s in state.states.items()} == counts


def test_the_estimate_both_ways_compares_each_candidate_on_half_a_and_on_half_b(frames):
    """At the first frame each candidate's f(A) and f(B) (from fresh states) give the error covariance both ways,
    whose diagonal is each candidate's `cross_tile_error`; the `error` layer is the blend's estimate."""
    from service.stages.error_estimate import cross_tile_error

    _, state = _run(pipelines.get("auto", tile=16, every=8), frames[:1])
    frame = frames[0]
    outputs = {h: [_run(pipelines.get(n), [one_half(frame, h)])[0][0]["color"] for n in CANDIDATES]
               for h in ("colorA", "colorB")}
    scale = np.median(outputs["colorA"] + outputs["colorB"], axis=0)
    a, b = frame["colorA"], frame["colorB"]
    for k in range(len(CANDIDATES)):
        expected = cross_tile_error(outputs["colorA"][k], outputs["colorB"][k], a, b, scale, 16,
                                    cap=tiled.FIREFLY_CAP).mean
        np.testing.assert_allclose(state.covariance[k, k], expected, rtol=1e-9, atol=1e-15)
    np.testing.assert_array_equal(state.covariance, state.covariance.transpose(1, 0, 2, 3))
    # the error layer: the blended halves' estimate against the candidates' median on the whole frame (scale and
    # control variate), at least its sd
    blend = state.blend
    per_pixel = np.repeat(np.repeat(blend, 16, axis=1), 16, axis=2)[:, :40, :72, None]
    blended = [sum(w * o for w, o in zip(per_pixel, outputs[h], strict=True)) for h in ("colorA", "colorB")]
    consensus = np.median([_run(pipelines.get(n), [frame])[0][0]["color"] for n in CANDIDATES], axis=0)
    estimate = cross_tile_error(*blended, a, b, consensus, 16, cap=tiled.FIREFLY_CAP, control=consensus)
    floored = np.maximum(estimate.mean, np.sqrt(estimate.variance))
    np.testing.assert_allclose(state.error[..., 0], interpolate_tiles(floored, 16, 40, 72), rtol=1e-5)


def test_a_running_candidate_is_judged_from_a_copy_of_its_state(frames, monkeypatch):
    """At a later evaluation a chosen temporal candidate (svgf) denoises each half from a copy of its running
    state, with its history: what that state gives, not what a fresh state gives, and the running state
    itself is left as it was."""
    monkeypatch.setattr(tiled, "choose", _alone(2))
    assert CANDIDATES[2] == "svgf"
    seen = []

    def spy(pipeline, frame, running):
        before = copy.deepcopy(running)
        out = run_half(pipeline, frame, running)
        if pipeline.name == "svgf" and "colorA" not in frame:  # a half (the whole frame: the error layer's median)
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
    monkeypatch.setattr(tiled, "choose", _alone(0))
    seen = []

    def spy(pipeline, frame, running):
        if "colorA" not in frame:  # a half (the whole frame: the error layer's median)
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


def test_the_members_are_handed_to_the_next_evaluation(frames, monkeypatch):
    """choose gets the last evaluation's members as `previous` (none at the first); the previous frame is kept
    only where an evaluation comes next."""
    seen = []

    def spy(covariance, costs, tolerance, budget, previous=None):
        seen.append(previous)
        return _alone(2)(covariance)

    monkeypatch.setattr(tiled, "choose", spy)
    pipeline = pipelines.get("auto", tile=16, every=3)
    state = pipeline.start(40, 72)
    kept = []
    for frame in frames[:4]:  # evaluations at frames 0, 1 and 3
        _, state = pipeline.step(frame, state)
        kept.append(state.previous is frame)
    assert seen == [None, (2,), (2,)]
    assert kept == [True, False, True, False]  # after frames 0 and 2: frames 1 and 3 evaluate
    state.close()
    assert state.previous is None


def test_the_error_layer_is_at_least_the_estimates_standard_error(frames, monkeypatch):
    """A tile whose blend's estimate fell below zero by chance reads as its standard error, not as error-free;
    one above it reads as itself. The sd is that of the running average: one evaluation's at frames 0 and 1
    (the first is not averaged into the second), then scaled by 1/2, 3/8, ... as averages are taken."""
    from service.stages.error_estimate import TileError

    mean = np.full((3, 5), -1.0)
    mean[:, 3:] = 5.0
    monkeypatch.setattr(tiled, "cross_tile_error", lambda *args, **kwargs: TileError(mean, np.full((3, 5), 4.0), 16))
    monkeypatch.setattr(tiled, "choose", _alone(0))  # one blend throughout: its estimates are averaged
    outs, _ = _run(pipelines.get("auto", tile=16, every=2), frames)  # evaluations at frames 0, 1, 2 and 4
    for out, factor in zip(outs, (1.0, 1.0, 0.5, 0.5, 0.375), strict=True):
        error = out["error"][..., 0]
        np.testing.assert_allclose(error[:, :16], np.sqrt(4.0 * factor), rtol=1e-6)  # interpolated between equal tiles
        np.testing.assert_allclose(error[:, 60:], 5.0, rtol=1e-6)
