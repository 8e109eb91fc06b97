"""The crossreg pipeline: explicit state, odd sizes, the network contract, weight refusal, the online
worker end to end (training, swap, crash), and the CLI's --online."""

import os
import re
import signal
import time

import numpy as np
import pytest

from bench.synthetic import synthetic_sequence
from service import pipelines
from service.cli import main as cli_main
from service.frame import Frame
from service.layout import CROSSREG_INPUTS, CROSSREG_SAMPLE, channel_slices, total_channels
from service.metrics import rel_l2
from service.online import trainer as trainer_module
from service.pipelines.crossreg import HISTORY_REPROJECTION, CrossregState, prepare_frame
from service.pipelines.options import OptionError
from service.stages.cross_regression import cross_regression, pilots_to_radiance
from service.stages.reprojection import reproject

WORKER_START_S = 90  # spawning a process that imports torch, on 2 busy cores


@pytest.fixture(scope="module")
def odd_frames():
    return [Frame.from_buffers(x) for x in synthetic_sequence(13, 17, 3, spp=8, seed=5)]


def _run(pipeline, frames, state=None):
    state = state or pipeline.start(frames[0].height, frames[0].width)
    outs = []
    for frame in frames:
        out, state = pipeline.step(frame, state)
        outs.append(out["color"])
    return outs, state


def test_contract_and_options():
    info = pipelines.get("crossreg").describe()
    assert info["temporal"] is True
    assert {"colorA", "colorB", "albedo", "normal", "motion"} == set(info["requires"])
    assert {"online", "publish_every", "crop", "random_init"} <= set(info["options"])
    assert info["options"]["online"] is False


@pytest.mark.parametrize("min_alpha, bandwidth", [(0.0, 0.0), (0.3, 32.0), (1.0, 1e4)])
def test_the_floors_reach_the_filter_with_the_network_output_untouched(odd_frames, monkeypatch, min_alpha, bandwidth):
    from service.pipelines import crossreg

    seen, filter_frame = [], crossreg.filter_frame

    def spy(prepared, params, floor, pilot_bandwidth):
        before = params.copy()
        out = filter_frame(prepared, params, floor, pilot_bandwidth)
        seen.append((floor, pilot_bandwidth, np.array_equal(params, before)))
        return out

    monkeypatch.setattr(crossreg, "filter_frame", spy)
    _run(pipelines.get("crossreg", min_alpha=min_alpha, pilot_bandwidth=bandwidth), odd_frames)
    assert seen and all(x == (min_alpha, bandwidth, True) for x in seen)


def test_pilot_bandwidth_defaults_to_32_and_is_range_checked():
    assert pipelines.get("crossreg").options.pilot_bandwidth == 32.0
    for bad in (-1.0, 2e4):
        with pytest.raises(OptionError, match="pilot_bandwidth"):
            pipelines.get("crossreg", pilot_bandwidth=bad)


def test_odd_size_sequence_keeps_explicit_history(odd_frames):
    pipeline = pipelines.get("crossreg")
    outs, state = _run(pipeline, odd_frames)
    assert isinstance(state, CrossregState) and state.frame_index == 3
    assert all(o.shape == (13, 17, 3) and np.isfinite(o).all() and (o >= 0).all() for o in outs)
    assert state.history.colors.shape == (9, 13, 17)
    status = state.online_status
    assert status["state"] == "off" and status["weights_version"] == 0 and status["init"] == "warm start"


def test_network_input_follows_the_layout_and_history_is_used(odd_frames):
    frame = odd_frames[0]
    prepared = prepare_frame(frame, None)
    s = channel_slices(CROSSREG_INPUTS)
    pilot_a, pilot_b = cross_regression(frame["colorA"], frame["colorB"], frame["albedo"], frame["normal"])
    np.testing.assert_array_equal(prepared.planes[s["pilotA"]], pilot_a)
    np.testing.assert_array_equal(prepared.planes[s["pilotB"]], pilot_b)
    np.testing.assert_array_equal(prepared.planes[s["normal"]], frame["normal"].transpose(2, 0, 1))
    assert not prepared.valid.any()  # no history on the first frame: the filter ignores `previous`
    pipeline = pipelines.get("crossreg")
    _, state = _run(pipeline, odd_frames[:1])
    second = prepare_frame(odd_frames[1], state.history)
    assert second.valid.any()  # static floor reprojects
    assert second.sample().shape == (13, 17, 22)


def test_depth_that_comes_and_goes_starts_the_history_again(odd_frames):
    """`depth` is optional: a frame without it after frames with it (or the reverse) denoises as a new start,
    and the frames after it with the same layers use the history again."""
    without = [Frame({k: v for k, v in f.buffers.items() if k != "depth"}, {}) for f in odd_frames]
    pipeline = pipelines.get("crossreg")
    for sequence in ([odd_frames[0], without[1], without[2]], [without[0], odd_frames[1], odd_frames[2]]):
        outs, state = _run(pipeline, sequence)
        fresh, _ = _run(pipeline, sequence[1:2])
        np.testing.assert_array_equal(outs[1], fresh[0])
        np.testing.assert_array_equal(outs[2], _run(pipeline, sequence[1:])[0][1])  # frame 1's history, used


def test_cached_pilots_give_the_same_network_input(odd_frames):
    """Offline training passes (3, H, W) pilot planes it computed once; the result equals computing them here."""
    pipeline = pipelines.get("crossreg")
    _, state = _run(pipeline, odd_frames[:1])
    frame = odd_frames[1]
    cached = cross_regression(frame["colorA"], frame["colorB"], frame["albedo"], frame["normal"])
    fresh, reused = prepare_frame(frame, state.history), prepare_frame(frame, state.history, pilots=cached)
    np.testing.assert_array_equal(fresh.planes, reused.planes)
    np.testing.assert_array_equal(fresh.valid, reused.valid)
    np.testing.assert_array_equal(fresh.previous_pilots, reused.previous_pilots)


@pytest.mark.parametrize("screen", [True, False])
def test_previous_is_the_screened_history_or_the_pilots_mean(odd_frames, screen):
    _, state = _run(pipelines.get("crossreg"), odd_frames[:1])
    prepared = prepare_frame(odd_frames[1], state.history, screen=screen)
    frame, history = odd_frames[1], state.history
    warped, reprojected = reproject(
        history.colors.transpose(1, 2, 0), frame["motion"], depth=frame["depth"], prev_depth=history.depth,
        normal=frame["normal"], prev_normal=history.normal, params=HISTORY_REPROJECTION,
    )  # fmt: skip
    valid = prepared.valid
    assert valid.any() and not valid.all() and not (valid & ~reprojected).any()
    if not screen:
        np.testing.assert_array_equal(valid, reprojected)
    previous = prepared.plane_group("previous").transpose(1, 2, 0)
    np.testing.assert_array_equal(previous[valid], warped[valid][:, 6:9])
    pilot_a, pilot_b = (prepared.plane_group(name).transpose(1, 2, 0) for name in ("pilotA", "pilotB"))
    mean = 0.5 * (pilot_a + pilot_b)
    np.testing.assert_allclose(previous[~valid], mean[~valid], rtol=1e-6)
    sample = prepared.sample()
    s = channel_slices(CROSSREG_SAMPLE)
    np.testing.assert_array_equal(sample[..., s["valid"]][..., 0], valid.astype(np.float32))
    np.testing.assert_array_equal(sample[..., : total_channels(CROSSREG_INPUTS)], prepared.planes.transpose(1, 2, 0))
    for name, current, planes in (("previousPilotA", pilot_a, slice(0, 3)), ("previousPilotB", pilot_b, slice(3, 6))):
        label = sample[..., s[name]]
        kept = (label == warped[..., planes]).all(-1) & reprojected
        assert np.all(kept | (label == current).all(-1))  # each pixel: its reprojected or its current pilot


def test_warm_start_denoises_better_than_the_pilots_alone():
    layers = synthetic_sequence(32, 48, 4, spp=8, seed=11)
    frames = [Frame.from_buffers(x) for x in layers]
    outs, _ = _run(pipelines.get("crossreg"), frames)
    for frame, out, x in zip(frames[1:], outs[1:], layers[1:], strict=True):
        pilots = pilots_to_radiance(*cross_regression(frame["colorA"], frame["colorB"], frame["albedo"],
                                                      frame["normal"])) + x["emission"]  # fmt: skip
        assert rel_l2(out, x["reference"]) < rel_l2(pilots, x["reference"])


class _FakeTrainer:
    """Stand-in for OnlineTrainer (test only): publishes whatever weights the test gives it."""

    def __init__(self, weights):
        self.weights, self.submitted = weights, 0

    def poll(self):
        weights, self.weights = self.weights, None
        return None if weights is None else (1, weights)

    def submit(self, sample, frame_index, *, wait=0.0):
        self.submitted += 1
        return True

    def status(self):
        return {"state": "running", "running": True, "crashed": False, "lagging": False, "last_error": None}

    def close(self):
        pass


def test_non_finite_worker_weights_are_refused_and_reported(odd_frames):
    pipeline = pipelines.get("crossreg")
    state = pipeline.start(13, 17)
    state.model = state.model.copy()
    reference, _ = _run(pipeline, odd_frames[:2])
    shapes = state.model.info.weight_shapes
    bad = {name: np.full(shape, np.nan, np.float32) for name, shape in shapes.items()}
    state.trainer = _FakeTrainer(bad)
    outs, state = _run(pipeline, odd_frames[:2], state)
    status = state.online_status
    assert status["weights_version"] == 0 and status["weights_refused"] == 1
    assert "non-finite" in status["last_error"] and state.trainer.submitted == 2
    np.testing.assert_allclose(outs[1], reference[1], rtol=1e-5, atol=1e-6)  # still the last good weights


def test_random_init_starts_from_fresh_weights(odd_frames):
    outs, state = _run(pipelines.get("crossreg", random_init=True, seed=3), odd_frames[:2])
    assert state.online_status["init"] == "random" and state.model.version == 1
    assert all(np.isfinite(o).all() for o in outs)


def test_online_without_torch_is_a_clear_error(monkeypatch):
    real = trainer_module.importlib.util.find_spec
    monkeypatch.setattr(
        trainer_module.importlib.util, "find_spec", lambda name, *a: None if name == "torch" else real(name, *a)
    )
    with pytest.raises(ValueError, match="online training needs torch, which is not installed"):
        pipelines.get("crossreg", online=True)


def test_online_session_trains_swaps_weights_and_survives_a_worker_crash(odd_frames):
    pytest.importorskip("torch")
    pipeline = pipelines.get("crossreg", online=True, publish_every=1, crop=8)
    state = pipeline.start(13, 17)
    try:
        deadline = time.monotonic() + WORKER_START_S
        frames = odd_frames * 20
        i = 0
        while state.online_status["weights_version"] < 1:  # inference never waits; we wait for the test
            assert time.monotonic() < deadline, state.online_status
            _, state = pipeline.step(frames[i % len(frames)], state)
            i += 1
            time.sleep(0.1)
        status = state.online_status
        assert status["frames_trained"] >= 1 and status["running"] and not status["crashed"]
        os.kill(state.trainer.pid, signal.SIGKILL)
        state.trainer._process.join(10)
        outs, state = _run(pipeline, odd_frames, state)
        assert all(np.isfinite(o).all() for o in outs)
        status = state.online_status
        assert status["crashed"] and status["state"] == "crashed" and "exited" in status["last_error"]
        assert status["weights_version"] >= 1  # running on the last good weights
    finally:
        state.close()


def test_lockstep_trains_on_every_frame_and_swaps_weights_on_schedule(odd_frames):
    pytest.importorskip("torch")
    frames = odd_frames + odd_frames[:2]  # 5 frames
    warm, _ = _run(pipelines.get("crossreg"), frames)
    pipeline = pipelines.get("crossreg", online=True, lockstep=True, publish_every=2, crop=8)
    state = pipeline.start(13, 17)
    try:
        outs = []
        for index, frame in enumerate(frames):
            out, state = pipeline.step(frame, state)
            outs.append(out["color"])
            status = state.online_status
            assert status["frames_trained"] == index + 1 and status["frames_dropped"] == 0, status
        # weights published after frames 2 and 4 (1-based), swapped in at the start of frames 3 and 5
        assert status["weights_published"] == 2 and status["weights_version"] == 2, status
        for index in range(2):
            np.testing.assert_array_equal(outs[index], warm[index])
        assert not np.array_equal(outs[2], warm[2])
    finally:
        state.close()


def test_cli_online_flag(tiny_sequence_dir, tmp_path, capsys):
    assert cli_main(["denoise", "--pipeline", "bilateral", "--online", str(tiny_sequence_dir), str(tmp_path)]) == 2
    assert "pipeline 'bilateral' has no option 'online'" in capsys.readouterr().err
    pytest.importorskip("torch")
    code = cli_main(["denoise", "--pipeline", "crossreg", "--online", "-o", "crop=8", str(tiny_sequence_dir),
                     str(tmp_path / "out")])  # fmt: skip
    assert code == 0 and len(list((tmp_path / "out").glob("*.exr"))) == 3
    out = capsys.readouterr().out
    assert "crossreg: 3 frames" in out
    assert re.search(r"online training: (starting|running|lagging), \d+ frames trained, \d+ dropped", out)


def test_lockstep_without_online_is_refused_naming_the_option():
    with pytest.raises(ValueError, match="option 'lockstep' needs online=true"):
        pipelines.get("crossreg", lockstep=True)
