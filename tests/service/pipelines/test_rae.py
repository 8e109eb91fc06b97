"""Pipeline `rae` with the shipped weights: contract, the recurrent state carries information (the output
depends on the history, and temporal error falls with it), the state resets per sequence, the warp
option."""

import numpy as np
import pytest

from models.data import SAMPLE_DIRS
from service import pipelines
from service.exr import read_sequence
from service.frame import Frame, FrameError
from service.metrics import rel_l2, temporal_rel_l2
from service.pipelines.rae import RaePipeline, trained_with_warp

SAMPLE = SAMPLE_DIRS[0]


@pytest.fixture(scope="module")
def frames() -> list[Frame]:
    return [frame for _path, frame in read_sequence(SAMPLE)]


def _run(pipeline, frames, *, fresh_each_frame=False):
    state, outs = None, []
    for frame in frames:
        if state is None or fresh_each_frame:
            state = pipeline.start(frame.height, frame.width)
        out, state = pipeline.step(Frame({k: v for k, v in frame.buffers.items() if k != "reference"}, {}), state)
        outs.append(out["color"])
    return outs, state


def test_contract():
    info = pipelines.get("rae").describe()
    assert info["temporal"] and set(info["requires"]) == {"color", "albedo", "normal", "depth"}
    assert {"roughness", "motion", "emission"} <= set(info["optional"])
    assert info["option_specs"]["weights"]["enum"] == ["rae"]


def test_denoises_the_sample_and_history_lowers_the_temporal_error(frames):
    pipeline = pipelines.get("rae")
    with_history, state = _run(pipeline, frames)
    without, _ = _run(pipeline, frames, fresh_each_frame=True)
    refs = [f["reference"] for f in frames]
    noisy = np.mean([rel_l2(f["color"], r) for f, r in zip(frames, refs, strict=True)])
    error = np.mean([rel_l2(o, r) for o, r in zip(with_history, refs, strict=True)])
    assert error < 0.5 * noisy
    assert state.frame_index == len(frames) and len(state.hidden) == 4

    def temporal(outs):
        return np.mean([temporal_rel_l2(outs[i - 1], outs[i], refs[i - 1], refs[i]) for i in range(1, len(outs))])

    assert not np.allclose(with_history[-1], without[-1])  # the state carries information
    assert temporal(with_history) < temporal(without)


def test_each_sequence_starts_from_a_zero_state(frames):
    pipeline = pipelines.get("rae")
    first, _ = _run(pipeline, frames[:1])
    again, _ = _run(pipeline, frames[3:4] + frames[:1], fresh_each_frame=True)
    np.testing.assert_array_equal(first[0], again[1])


def test_a_frame_of_another_size_is_refused_mid_sequence(frames):
    pipeline = pipelines.get("rae")
    state = pipeline.start(frames[0].height, frames[0].width)
    small = Frame({k: v[:50, :61] for k, v in frames[0].buffers.items()}, {})
    with pytest.raises(FrameError, match="sequence is 120x120"):
        pipeline.step(small, state)


def test_warp_option_moves_the_state_and_zero_motion_changes_nothing(frames):
    still = [Frame({**f.buffers, "motion": np.zeros_like(f["motion"])}, {}) for f in frames[:3]]
    plain, _ = _run(pipelines.get("rae", warp=False), still)
    warped, _ = _run(pipelines.get("rae", warp=True), still)
    for a, b in zip(plain, warped, strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6)
    moving, _ = _run(pipelines.get("rae", warp=True), frames[:3])
    plain_moving, _ = _run(pipelines.get("rae", warp=False), frames[:3])
    assert not np.allclose(moving[2], plain_moving[2])


def test_warp_defaults_to_how_the_weights_were_trained():
    pipeline = pipelines.get("rae")
    assert pipeline.warps == trained_with_warp(pipeline.model())
    assert RaePipeline(warp=True).warps and not RaePipeline(warp=False).warps
