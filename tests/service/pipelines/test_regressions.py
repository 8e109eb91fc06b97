"""The three regression pipelines end to end: the command line on a synthetic sequence, and error
against the reference well below the noisy input's."""

import subprocess
import sys

import numpy as np
import pytest

from service import pipelines
from service.exr import read_frame
from service.frame import Frame
from service.metrics import rel_l2

REGRESSIONS = ("crossregression", "bmfr", "flr")
# relL2 of the output over the noisy input's on the 64x80 synthetic sequence; measured 0.05-0.25.
MAX_ERROR_RATIO = 0.35


@pytest.mark.parametrize("name", REGRESSIONS)
def test_denoises_the_synthetic_sequence_well_below_the_noise(name):
    from bench.synthetic import synthetic_sequence

    pipeline = pipelines.get(name)
    state = pipeline.start(64, 80)
    noisy, denoised = [], []
    for layers in synthetic_sequence(64, 80, 2, seed=5):
        out, state = pipeline.step(Frame.from_buffers(layers), state)
        noisy.append(rel_l2(layers["color"], layers["reference"]))
        denoised.append(rel_l2(out["color"], layers["reference"]))
    assert np.mean(denoised) < MAX_ERROR_RATIO * np.mean(noisy)


def test_crossregression_needs_both_half_buffers():
    info = pipelines.pipeline_class("crossregression").describe()
    assert {"colorA", "colorB", "albedo", "normal"} <= set(info["requires"])
    assert info["options"]["window"] == 15 and info["options"]["sparsity"] == 4


def test_flr_reads_ao_only_with_its_option():
    """The `ao` layer is one more FLR guide with `ao=True`, and ignored by default (flr's docstring)."""
    from bench.synthetic import synthetic_frame

    layers = synthetic_frame(48, 64, 1, rng=np.random.default_rng(2))
    other = dict(layers, ao=np.random.default_rng(3).random(layers["ao"].shape, np.float32))  # the frame's is 1

    def out(options, buffers):
        pipeline = pipelines.get("flr", **options)
        return pipeline.step(Frame.from_buffers(buffers), pipeline.start(48, 64))[0]["color"]

    np.testing.assert_array_equal(out({}, layers), out({}, other))
    assert not np.array_equal(out({"ao": True}, layers), out({"ao": True}, other))


@pytest.mark.parametrize("name", REGRESSIONS)
def test_command_line_denoise(name, tiny_sequence_dir, tmp_path):
    out = tmp_path / "out"
    run = subprocess.run(
        [sys.executable, "-m", "service", "denoise", str(tiny_sequence_dir), str(out), "--pipeline", name],
        capture_output=True,
        text=True,
        check=False,
    )
    assert run.returncode == 0, run.stderr
    frame = read_frame(out / "frame_0002.exr")
    assert frame["color"].shape == (24, 40, 3) and np.isfinite(frame["color"]).all()
