"""Pipeline `kpn`: the served composition (ONNX Runtime kernels, numba filter, numba warp of the previous
output) against its training twin (models/train/kpn.py) over a few frames; with the shipped weights: contract,
denoising, the history is used and reset per sequence, the motion option, constants, errors."""

import json

import numpy as np
import pytest

from models.data import SAMPLE_DIRS
from service import pipelines
from service.exr import read_sequence
from service.frame import Frame, FrameError
from service.metrics import TRIM_FRACTION, rel_l2
from service.pipelines.options import OptionError
from service.stages.background import FILTER_REACH
from service.stages.emission import subtract_emission
from tests.service.pipelines.sequence_errors import run_sequence, sequence_errors

SAMPLE = SAMPLE_DIRS[0]  # `shadows`, 120x120: not a multiple of the alignment (16), so the pipeline pads


@pytest.fixture(scope="module")
def frames() -> list[Frame]:
    return [frame for _path, frame in read_sequence(SAMPLE)]


def _inputs(frame: Frame, **replace: np.ndarray) -> Frame:
    return Frame({**{k: v for k, v in frame.buffers.items() if k != "reference"}, **replace}, {})




def test_contract():
    info = pipelines.get("kpn").describe()
    assert info["temporal"] and set(info["requires"]) == {"color", "albedo", "normal", "depth", "motion"}
    assert {"motionDual", "roughness", "emission", "colorA", "colorB"} <= set(info["optional"])
    assert info["option_specs"]["weights"]["enum"] == ["kpn"]
    assert info["option_specs"]["motion"]["enum"] == ["auto", "dual", "plain"]


@pytest.mark.parametrize("motion", ["dual", "plain"])
def test_served_pipeline_matches_the_training_twin(frames, tmp_path, monkeypatch, motion):
    """Three frames through the served pipeline (with its own state) and through models/train/kpn.py's
    `filter_window` (torch network, torch warp, torch filter) on the same planes (the served outlier clamp
    applied): the same filtered output."""
    torch = pytest.importorskip("torch")
    pytest.importorskip("onnx")
    from export.kpn import export_bytes
    from models.nets.kpn import KpnConfig, make_kpn
    from models.train.kpn import filter_window
    from service.runtime import WEIGHTS_DIR_ENV
    from service.stages.outliers import clamp_outliers
    from service.stages.rae_inputs import RADIANCE, rae_planes
    from service.stages.reprojection import surface_hit
    from tests.export.test_kpn_export import random_heads

    net = random_heads(make_kpn(KpnConfig(widths=(6, 8, 10, 12)), seed=4)).eval()
    (tmp_path / "tiny.onnx").write_bytes(export_bytes(net))
    monkeypatch.setenv(WEIGHTS_DIR_ENV, str(tmp_path))
    pipeline = pipelines.get("kpn", weights="tiny", motion=motion)
    state = pipeline.start(frames[0].height, frames[0].width)
    served, planes = [], []
    for frame in frames[:3]:
        # as Pipeline.step hands them over: the emission out of the radiance and its halves
        color, *halves = subtract_emission([frame[k] for k in ("color", "colorA", "colorB")], frame["emission"])
        _, state = pipeline.denoise(_inputs(frame, color=color, colorA=halves[0], colorB=halves[1]), state)
        served.append(state.previous)
        clamped = clamp_outliers(color, halves=tuple(halves), albedo=frame["albedo"])
        planes.append(rae_planes(clamped, frame["albedo"], frame["normal"],
                                 frame["depth"], frame.get("roughness"), background=~surface_hit(frame["normal"])))
    planes = torch.from_numpy(np.stack(planes))[None]
    moves = np.stack([f["motionDual" if motion == "dual" else "motion"].transpose(2, 0, 1) for f in frames[:3]])
    with torch.no_grad():
        ours = filter_window(net, torch.expm1(planes[:, :, RADIANCE]), planes[:, :, RADIANCE.stop:],
                             torch.from_numpy(moves)[None])[0]
    assert (moves[1:] != 0).any() and (served[2] != served[1]).any()
    for t in range(3):
        np.testing.assert_allclose(served[t], ours[t].numpy(), atol=2e-4, rtol=1e-4, err_msg=f"frame {t}")


def test_the_input_clamp_gets_the_halves_less_the_emission(frames, monkeypatch):
    """Pipeline.step hands kpn's input clamp the halves with the emission taken out, as the radiance it clamps
    (the halves are declared, so the emission split covers them), and the albedo."""
    import service.pipelines.kpn as module

    seen = []
    clamp = module.clamp_outliers
    monkeypatch.setattr(module, "clamp_outliers", lambda color, halves=None, albedo=None: (
        seen.append((color, halves, albedo)), clamp(color, halves=halves, albedo=albedo))[1])
    frame = _inputs(frames[0])
    assert float(frame["emission"].max()) > 0
    pipeline = pipelines.get("kpn")
    pipeline.step(frame, pipeline.start(frame.height, frame.width))
    (color, halves, albedo), = seen
    np.testing.assert_array_equal(albedo, frame["albedo"])  # judged on the demodulated radiance
    expected = subtract_emission([frame[k] for k in ("color", "colorA", "colorB")], frame["emission"])
    np.testing.assert_array_equal(color, expected[0])
    np.testing.assert_array_equal(halves[0], expected[1])
    np.testing.assert_array_equal(halves[1], expected[2])


def test_denoises_the_sample_and_history_lowers_the_temporal_error(frames):
    """The warped previous output the network reads (no output history)."""
    pipeline = pipelines.get("kpn", history=0)
    with_history, state = run_sequence(pipeline, frames)
    without, _ = run_sequence(pipeline, frames, fresh_each_frame=True)
    refs = [f["reference"] for f in frames]
    noisy = np.mean([rel_l2(f["color"], r, trim=TRIM_FRACTION) for f, r in zip(frames, refs, strict=True)])
    error = np.mean([rel_l2(o, r, trim=TRIM_FRACTION) for o, r in zip(with_history, refs, strict=True)])
    assert error < 0.5 * noisy
    assert state.frame_index == len(frames) and state.previous.shape == (3, 120, 120)
    assert sequence_errors(with_history, refs)[1] < sequence_errors(without, refs)[1]


def test_output_history_lowers_the_error_and_the_temporal_error(frames):
    """The clipped output history (step 6) on the sample: both errors fall; the network's own history, what
    step 2 warps, is its unblended output either way."""
    refs = [f["reference"] for f in frames]
    (plain, plain_state), (steadied, state) = run_sequence(pipelines.get("kpn", history=0), frames), \
        run_sequence(pipelines.get("kpn", history=0.2), frames)
    (error, temporal), (plain_error, plain_temporal) = (sequence_errors(outs, refs) for outs in (steadied, plain))
    assert temporal < 0.97 * plain_temporal and error < plain_error
    np.testing.assert_array_equal(steadied[0], plain[0])
    np.testing.assert_array_equal(state.previous, plain_state.previous)
    assert plain_state.history.previous is None and state.history.previous is not None


def test_frame_two_depends_on_frame_one_and_a_new_sequence_forgets_it(frames):
    pipeline = pipelines.get("kpn")
    (_, second), _ = run_sequence(pipeline, frames[:2])
    brighter = Frame({**frames[0].buffers, "color": frames[0]["color"] * 2}, {})
    (_, second_after_brighter), _ = run_sequence(pipeline, [brighter, frames[1]])
    assert np.abs(second_after_brighter - second).max() > 1e-2 * np.abs(second).max()
    (first,), _ = run_sequence(pipeline, frames[1:2])
    (_, again), _ = run_sequence(pipeline, [brighter, frames[1]], fresh_each_frame=True)
    np.testing.assert_array_equal(first, again)  # a sequence's first frame uses no history


def test_a_constant_image_stays_constant_and_the_background_passes_through(frames):
    """Kernels that sum to 1 and weights in (0, 1) on a constant radiance and albedo: that constant, every frame;
    where nothing was hit (zero normal: a sky of 7 in the first 6 columns) the input comes out unchanged beyond
    the pixel filter's reach of the surfaces (the pipeline step: service/stages/background.py)."""
    h, w = 37, 53  # odd sizes
    base = {k: frames[0][k][:h, :w].copy() for k in ("normal", "depth", "motion", "motionDual", "roughness")}
    base["normal"][:, :6] = 0.0
    color = np.full((h, w, 3), 0.3, np.float32)
    color[:, :6] = 7.0
    flat = Frame({**base, "color": color, "albedo": np.full((h, w, 3), 0.5, np.float32)}, {})
    hit = np.einsum("hwc,hwc->hw", base["normal"], base["normal"]) > 0.25
    assert hit[:, 6:].all() and not hit[:, :6].any()
    outs, _ = run_sequence(pipelines.get("kpn"), [flat, flat, flat])
    for out in outs:
        np.testing.assert_array_equal(out[:, : 6 - FILTER_REACH], color[:, : 6 - FILTER_REACH])
        np.testing.assert_allclose(out[:, 30:], 0.3, rtol=1e-4)  # away from the sky, whose radiance the network
        # does not see (zero there, as in `rae`; training windows show it: docs/training.md)


def test_motion_option(frames):
    """auto = dual where the frame has motionDual, plain otherwise; dual without motionDual is refused."""
    def third(**options):
        return run_sequence(pipelines.get("kpn", **options), frames[:3])[0][2]

    auto, dual, plain = third(), third(motion="dual"), third(motion="plain")
    np.testing.assert_array_equal(auto, dual)
    assert not np.array_equal(dual, plain)
    no_dual = [Frame({k: v for k, v in f.buffers.items() if k != "motionDual"}, {}) for f in frames[:3]]
    np.testing.assert_array_equal(run_sequence(pipelines.get("kpn"), no_dual)[0][2], plain)
    pipeline = pipelines.get("kpn", motion="dual")
    with pytest.raises(FrameError, match="missing layer 'motionDual' required by pipeline 'kpn' with motion 'dual'"):
        pipeline.step(no_dual[0], pipeline.start(120, 120))
    with pytest.raises(OptionError, match="motion"):
        pipelines.get("kpn", motion="sideways")


def test_missing_motion_and_a_frame_of_another_size_are_refused(frames):
    pipeline = pipelines.get("kpn")
    state = pipeline.start(120, 120)
    with pytest.raises(FrameError, match="missing layer 'motion' required by pipeline 'kpn'"):
        pipeline.step(Frame({k: v for k, v in frames[0].buffers.items() if k != "motion"}, {}), state)
    small = Frame({k: v[:50, :61] for k, v in frames[0].buffers.items()}, {})
    with pytest.raises(FrameError, match="sequence is 120x120"):
        pipeline.step(small, state)



def test_auto_motion_follows_what_the_weights_were_trained_with(frames, tmp_path, monkeypatch):
    """Weights whose metadata says they were trained with plain motion: `auto` warps by `motion`, as `plain`
    does, though the frames have `motionDual`."""
    pytest.importorskip("torch")
    pytest.importorskip("onnx")
    from export.kpn import export_bytes
    from models.nets.kpn import KpnConfig, make_kpn
    from service.runtime import WEIGHTS_DIR_ENV
    from tests.export.test_kpn_export import random_heads

    net = random_heads(make_kpn(KpnConfig(widths=(6, 8, 10, 12)), seed=4)).eval()
    (tmp_path / "plain.onnx").write_bytes(export_bytes(net, extra={"training": {"options": {"motion": "plain"}}}))
    (tmp_path / "dual.onnx").write_bytes(export_bytes(net))
    monkeypatch.setenv(WEIGHTS_DIR_ENV, str(tmp_path))

    def third(**options):
        return run_sequence(pipelines.get("kpn", **options), frames[:3])[0][2]

    np.testing.assert_array_equal(third(weights="plain"), third(weights="plain", motion="plain"))
    np.testing.assert_array_equal(third(weights="dual"), third(weights="dual", motion="dual"))
    assert not np.array_equal(third(weights="plain"), third(weights="plain", motion="dual"))


def test_weights_whose_coarse_outputs_are_not_at_scales_2_and_4_are_refused_at_the_start(tmp_path, monkeypatch):
    """The filter reads the coarse outputs by their `scale`: a file that lists others is refused when a sequence
    starts, naming the option, and not on a frame."""
    onnx = pytest.importorskip("onnx")
    from export.kpn import export_bytes
    from models.nets.kpn import KpnConfig, make_kpn
    from service.runtime import METADATA_KEY, WEIGHTS_DIR_ENV

    model = onnx.load_from_string(export_bytes(make_kpn(KpnConfig(widths=(6, 8, 10, 12)), seed=4).eval()))
    entry = next(p for p in model.metadata_props if p.key == METADATA_KEY)
    metadata = json.loads(entry.value)
    metadata["coarse"][1]["scale"] = 8
    entry.value = json.dumps(metadata)
    onnx.save(model, str(tmp_path / "odd.onnx"))
    monkeypatch.setenv(WEIGHTS_DIR_ENV, str(tmp_path))
    with pytest.raises(OptionError, match=r"weights 'odd' have coarse outputs at scales \[2, 8\]"):
        pipelines.get("kpn", weights="odd").start(120, 120)
