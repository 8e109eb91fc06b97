"""Pipeline `rae` with the shipped weights: contract, the recurrent state carries information (the output
depends on the history, and temporal error falls with it), the state resets per sequence, the warp
option, the clipped output history."""

import numpy as np
import pytest

from models.data import SAMPLE_DIRS
from service import pipelines
from service.exr import read_sequence
from service.frame import Frame, FrameError
from service.metrics import rel_l2
from service.pipelines.rae import RaePipeline
from tests.service.pipelines.sequence_errors import run_sequence, sequence_errors

SAMPLE = SAMPLE_DIRS[0]


@pytest.fixture(scope="module")
def frames() -> list[Frame]:
    return [frame for _path, frame in read_sequence(SAMPLE)]




def test_contract():
    info = pipelines.get("rae").describe()
    assert info["temporal"] and set(info["requires"]) == {"color", "albedo", "normal", "depth"}
    assert {"roughness", "motion", "emission"} <= set(info["optional"])
    assert info["option_specs"]["weights"]["enum"] == ["rae"]


def test_denoises_the_sample_and_history_lowers_the_temporal_error(frames):
    """The network's recurrent state alone (no output history)."""
    pipeline = pipelines.get("rae", history=0)
    with_history, state = run_sequence(pipeline, frames)
    without, _ = run_sequence(pipeline, frames, fresh_each_frame=True)
    refs = [f["reference"] for f in frames]
    noisy = np.mean([rel_l2(f["color"], r) for f, r in zip(frames, refs, strict=True)])
    (error, temporal), (_, temporal_without) = (sequence_errors(outs, refs) for outs in (with_history, without))
    assert error < 0.5 * noisy
    assert state.frame_index == len(frames) and len(state.hidden) == 4
    assert not np.allclose(with_history[-1], without[-1])  # the state carries information
    assert temporal < temporal_without


def test_each_sequence_starts_from_a_zero_state(frames):
    pipeline = pipelines.get("rae")
    first, _ = run_sequence(pipeline, frames[:1])
    again, _ = run_sequence(pipeline, frames[3:4] + frames[:1], fresh_each_frame=True)
    np.testing.assert_array_equal(first[0], again[1])


def test_a_frame_of_another_size_is_refused_mid_sequence(frames):
    pipeline = pipelines.get("rae")
    state = pipeline.start(frames[0].height, frames[0].width)
    small = Frame({k: v[:50, :61] for k, v in frames[0].buffers.items()}, {})
    with pytest.raises(FrameError, match="sequence is 120x120"):
        pipeline.step(small, state)


def test_warp_option_moves_the_state_and_zero_motion_changes_nothing(frames):
    still = [Frame({**f.buffers, "motion": np.zeros_like(f["motion"])}, {}) for f in frames[:3]]
    plain, _ = run_sequence(pipelines.get("rae", warp=False), still)
    warped, _ = run_sequence(pipelines.get("rae", warp=True), still)
    for a, b in zip(plain, warped, strict=True):
        np.testing.assert_array_equal(a, b)  # a zero shift samples every state exactly where it was
    moving, _ = run_sequence(pipelines.get("rae", warp=True), frames[:3])
    plain_moving, _ = run_sequence(pipelines.get("rae", warp=False), frames[:3])
    np.testing.assert_array_equal(moving[0], plain_moving[0])  # the first frame has no state to move
    assert not np.allclose(moving[2], plain_moving[2])


def test_warp_defaults_to_how_the_weights_were_trained(frames, tmp_path, monkeypatch):
    """The shipped weights were trained with the warp; a copy whose training metadata says otherwise is run
    without it, unless the option says so."""
    import json

    import onnx

    from service.runtime import METADATA_KEY, SHIPPED_WEIGHTS, WEIGHTS_DIR_ENV

    model = onnx.load(SHIPPED_WEIGHTS / "rae.onnx")
    entry = next(p for p in model.metadata_props if p.key == METADATA_KEY)
    meta = json.loads(entry.value)
    assert meta["training"]["options"]["warp"] is True
    meta["training"]["options"]["warp"] = False
    entry.value = json.dumps(meta)
    onnx.save(model, tmp_path / "rae_still.onnx")
    monkeypatch.setenv(WEIGHTS_DIR_ENV, str(tmp_path))

    def third_output(**options):
        return run_sequence(RaePipeline(**options), frames[:3])[0][2]

    shipped, plain = third_output(), third_output(warp=False)
    np.testing.assert_array_equal(shipped, third_output(warp=True))
    np.testing.assert_array_equal(third_output(weights="rae_still"), plain)
    assert not np.allclose(shipped, plain)
    assert RaePipeline(weights="rae_still", warp=True).warps and not RaePipeline(weights="rae_still").warps


def test_output_history_lowers_the_temporal_error_for_little_error(frames):
    """The default history on `shadows`: temporal error 3% lower, relL2 at most 1.5% higher (0.9% measured: the
    noise blend's accumulated input already steadies much of what the history did; module docstring)."""
    refs = [f["reference"] for f in frames]
    plain, _ = run_sequence(pipelines.get("rae", history=0), frames)
    steadied, _ = run_sequence(pipelines.get("rae"), frames)  # the default history
    (error, temporal), (plain_error, plain_temporal) = (sequence_errors(outs, refs) for outs in (steadied, plain))
    assert temporal < 0.98 * plain_temporal and error < 1.015 * plain_error
    np.testing.assert_array_equal(steadied[0], plain[0])  # nothing to blend at the first frame


def test_a_frame_without_motion_is_not_blended_and_restarts_the_output_history(frames):
    gap = [frames[0], Frame({k: v for k, v in frames[1].buffers.items() if k != "motion"}, {}), frames[2]]
    plain, _ = run_sequence(pipelines.get("rae", history=0, warp=False), gap)
    steadied, _ = run_sequence(pipelines.get("rae", history=0.5, warp=False), gap)
    for a, b in zip(plain, steadied, strict=True):
        np.testing.assert_array_equal(a, b)


def test_a_frame_without_motion_starts_the_warped_recurrence_again(frames):
    """`motion` is optional: with the warp, a frame without it is denoised as a sequence's first frame (zero
    hidden states; the output history restarts too), and the frames after it carry on from it."""
    pipeline = pipelines.get("rae", warp=True)
    gap = [frames[0], Frame({k: v for k, v in frames[1].buffers.items() if k != "motion"}, {}), frames[2]]
    outs, _ = run_sequence(pipeline, gap)
    first, _ = run_sequence(pipeline, gap[1:2])
    np.testing.assert_array_equal(outs[1], first[0])
    after, _ = run_sequence(pipeline, gap[1:])
    np.testing.assert_array_equal(outs[2], after[1])


@pytest.mark.parametrize("level", [0, 3])
def test_a_non_finite_hidden_state_fails_the_next_frame_which_resets_it(frames, monkeypatch, level):
    """Only the radiance is checked. A NaN left in a hidden state with a finite radiance (the worst case:
    the network itself does not produce one, see the next test) fails the next frame, which resets."""
    pipeline = pipelines.get("rae")  # the shipped weights warp the state: the NaN is carried to its next place
    state = pipeline.start(120, 120)
    model = pipeline.model()
    real, spec = model.run, model.info.state[level]

    def nan_in_state(feeds):
        outputs = real(feeds)
        outputs[spec.output] = outputs[spec.output].copy()
        outputs[spec.output][0, 0, 2, 2] = np.nan
        return outputs

    monkeypatch.setattr(model, "run", nan_in_state)
    out, state = pipeline.step(frames[0], state)
    assert np.isfinite(out["color"]).all() and not np.isfinite(state.hidden[level]).all()
    monkeypatch.setattr(model, "run", real)
    with pytest.raises(FloatingPointError, match="recurrent state was reset"):
        pipeline.step(frames[1], state)
    assert state.hidden == []
    out, state = pipeline.step(frames[2], state)
    assert np.isfinite(out["color"]).all() and all(np.isfinite(h).all() for h in state.hidden)


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_a_non_finite_value_in_any_hidden_state_makes_the_radiance_non_finite(bad):
    """The shipped network: one non-finite value fed in any level's state reaches the radiance."""
    model = pipelines.get("rae").model()
    info = model.info
    planes = np.random.default_rng(0).standard_normal((1, 8, 64, 64)).astype(np.float32)
    for level in range(len(info.state)):
        hidden = [np.zeros(spec.shape(64, 64), np.float32) for spec in info.state]
        hidden[level][0, 0, 1, 2] = bad
        outputs = model.run({info.input_name: planes, **{s.input: h for s, h in zip(info.state, hidden, strict=True)}})
        assert not np.isfinite(outputs[info.output_name]).all(), level


def test_a_firefly_in_one_half_does_not_enter_the_network(frames):
    """The input clamp (as kpn's): a firefly of 1e4 in one half at one pixel of the sample's first frame (radiance
    ~0.5) moves no other pixel by more than 0.1 and all of them by 15 in sum (without the clamp: 0.25 and 63,
    spread by the network); the clamp is told the halves, which the pipeline declares."""
    frame = Frame({k: v for k, v in frames[0].buffers.items() if k != "reference"}, {})
    pipeline = pipelines.get("rae")
    clean, _ = pipeline.step(frame, pipeline.start(frame.height, frame.width))
    buffers = dict(frame.buffers)
    buffers["colorB"] = buffers["colorB"].copy()
    buffers["colorB"][60, 60] = 1e4
    buffers["color"] = (0.5 * (buffers["colorA"] + buffers["colorB"])).astype(np.float32)
    spiked = Frame(buffers, {})
    out, _ = pipeline.step(spiked, pipeline.start(frame.height, frame.width))
    moved = np.abs(out["color"] - clean["color"]).max(axis=-1)
    moved[60, 60] = 0.0  # the firefly's own pixel, clipped to its neighbourhood's range
    assert float(moved.max()) < 0.1 and float(moved.sum()) < 15.0
    assert pipelines.get("rae").describe()["optional"][-2:] == ["colorA", "colorB"]
