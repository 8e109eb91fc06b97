"""Pipeline `flnr`: the served composition (ONNX Runtime guides, then the numba FLR) against its training
twin (torch network, then models/train/flr.py), and with the shipped weights: contract, denoising, and the
paper's point that learned guides follow lighting the G-buffer does not show (against `flr`)."""

import numpy as np
import pytest

from models.data import SAMPLE_DIRS
from service import pipelines
from service.exr import read_sequence
from service.frame import Frame
from service.metrics import TRIM_FRACTION, rel_l2
from service.stages.albedo import remodulate
from service.stages.emission import subtract_emission
from service.stages.rae_inputs import demodulated
from tests.service.pipelines.sequence_errors import run_sequence, sequence_errors

SAMPLE = SAMPLE_DIRS[0]  # `shadows`: cast shadows that no G-buffer shows


@pytest.fixture(scope="module")
def frames() -> list[Frame]:
    return [frame for _path, frame in read_sequence(SAMPLE)]


def _inputs(frame: Frame) -> Frame:
    return Frame({k: v for k, v in frame.buffers.items() if k != "reference"}, {})


def test_contract():
    info = pipelines.get("flnr").describe()
    assert info["temporal"] and set(info["requires"]) == {"color", "albedo", "normal", "depth"}
    assert "motion" in info["optional"]  # the accumulated input's reprojection (module docstring)
    assert info["option_specs"]["weights"]["enum"] == ["flnr"]


def test_served_composition_matches_the_training_twin(frames, tmp_path, monkeypatch):
    """What the served pipeline regresses is what models/train/flnr.py trains: the same guides (the network in
    ONNX Runtime against torch, on the same planes) and the same regression (the numba FLR with its firefly
    clamp against the torch twin on the clamped, demodulated radiance, remodulated)."""
    torch = pytest.importorskip("torch")
    pytest.importorskip("onnx")
    from export.flnr import export_bytes
    from models.nets.flnr import FlnrConfig, make_flnr
    from models.train import flr as twin
    from models.train.flnr import FLR, clamped
    from service.layout import pad_planes
    from service.runtime import WEIGHTS_DIR_ENV
    from service.stages.flr import local_linear_regression
    from service.stages.rae_inputs import rae_planes
    from service.stages.reprojection import surface_hit
    from tests.tolerances import ORT_ATOL

    net = make_flnr(FlnrConfig(widths=(6, 8, 10, 12)), seed=2).eval()
    with torch.no_grad():  # a head that is not the untrained zero: guides that are not the G-buffer's
        net.head.weight.normal_(0.0, 0.05, generator=torch.Generator().manual_seed(0))
    (tmp_path / "tiny.onnx").write_bytes(export_bytes(net))
    monkeypatch.setenv(WEIGHTS_DIR_ENV, str(tmp_path))
    pipeline = pipelines.get("flnr", weights="tiny")
    frame = frames[2]
    color = subtract_emission([frame["color"]], frame["emission"])[0]  # as Pipeline.step hands it over
    albedo, h, w = frame["albedo"], frame.height, frame.width
    guides = pipeline.guides(Frame({**_inputs(frame).buffers, "color": color}, {}))

    roughness, background = frame.get("roughness"), ~surface_hit(frame["normal"])
    planes = rae_planes(color, albedo, frame["normal"], frame["depth"], roughness, background=background)
    with torch.no_grad():
        learned = net(torch.from_numpy(pad_planes(planes, net.alignment)[None]))[0, :, :h, :w]
    np.testing.assert_allclose(guides, learned.numpy(), atol=ORT_ATOL, rtol=1e-4)

    noisy = torch.from_numpy(demodulated(color, albedo).transpose(2, 0, 1).copy())[None]
    ours = twin.local_linear_regression(clamped(noisy), torch.from_numpy(guides)[None], FLR)[0]
    ours = remodulate(ours.numpy().transpose(1, 2, 0), albedo)
    served = local_linear_regression(np.maximum(color, 0), guides.transpose(1, 2, 0), FLR, albedo=albedo)
    np.testing.assert_allclose(served, ours, rtol=0, atol=2e-3 * float(np.abs(served).max()))


def test_shipped_weights_denoise_and_beat_flr_on_shadows(frames):
    """The sample is `shadows`: moving objects' cast shadows, which normal and depth do not show and which
    FLR on them blurs; the learned guides should show them (Salmi et al., "Enhancing Local Regression")."""
    refs = [f["reference"] for f in frames]

    def error(name: str) -> float:  # each frame alone: the guides, not flnr's accumulated input, against flr
        outs, _ = run_sequence(pipelines.get(name), frames, fresh_each_frame=True)
        return float(np.mean([rel_l2(o, r, trim=TRIM_FRACTION) for o, r in zip(outs, refs, strict=True)]))

    noisy = float(np.mean([rel_l2(f["color"], r, trim=TRIM_FRACTION) for f, r in zip(frames, refs, strict=True)]))
    flnr, flr = error("flnr"), error("flr")
    assert flnr < 0.5 * noisy
    assert flnr < flr


def test_the_accumulated_input_lowers_the_error_and_a_new_sequence_forgets_it(frames):
    """Temporal through the noise blend's accumulated input: over the sample's frames as one sequence both the
    error and the temporal error are lower than with each frame alone; a sequence's first frame is the same."""
    pipeline = pipelines.get("flnr")
    (together, _), (alone, _) = run_sequence(pipeline, frames), run_sequence(pipeline, frames, fresh_each_frame=True)
    np.testing.assert_array_equal(together[0], alone[0])
    refs = [f["reference"] for f in frames]
    error, temporal = sequence_errors(together, refs, trim=TRIM_FRACTION)
    alone_error, alone_temporal = sequence_errors(alone, refs, trim=TRIM_FRACTION)
    assert error < 0.97 * alone_error and temporal < 0.95 * alone_temporal
