"""The `statistical` and `svgf` pipelines end to end on the synthetic sequence and through the CLI."""

import numpy as np
import pytest

from service import pipelines
from service.cli import main
from service.frame import Frame
from service.metrics import rel_l2


@pytest.mark.parametrize("name, options", [("statistical", {}), ("statistical", {"radius": 6, "symmetric": False}),
                                           ("svgf", {}), ("svgf", {"clamp_spread": None})])
def test_pipeline_lowers_error_well_below_the_input(name, options, tiny_layers):
    pipeline = pipelines.get(name, **options)
    state = pipeline.start(24, 40)
    noisy, out_err = [], []
    for layers in tiny_layers:
        out, state = pipeline.step(Frame.from_buffers(layers), state)
        noisy.append(rel_l2(layers["color"], layers["reference"]))
        out_err.append(rel_l2(out["color"], layers["reference"]))
    assert np.mean(out_err) < 0.7 * np.mean(noisy)


@pytest.mark.parametrize("name", ["statistical", "svgf"])
def test_constant_frame_is_unchanged(name):
    h, w = 11, 13
    layers = {
        "color": np.full((h, w, 3), 0.42, np.float32),
        "albedo": np.full((h, w, 3), 0.5, np.float32),
        "normal": np.tile(np.float32([0, 0, 1]), (h, w, 1)),
        "depth": np.full((h, w, 1), 3.0, np.float32),
        "motion": np.zeros((h, w, 2), np.float32),
        "sampleCount": np.full((h, w, 1), 8.0, np.float32),
        "bcMean": np.full((h, w, 3), 0.1, np.float32),
        "bcM2": np.full((h, w, 3), 0.05, np.float32),
        "bcM3": np.zeros((h, w, 3), np.float32),
    }
    pipeline = pipelines.get(name)
    state = pipeline.start(h, w)
    for _ in range(3):
        out, state = pipeline.step(Frame.from_buffers(layers), state)
        np.testing.assert_allclose(out["color"], 0.42, rtol=1e-5)


@pytest.mark.parametrize("name", ["statistical", "svgf"])
def test_cli_denoises_a_sequence(name, tiny_sequence_dir, tmp_path, capsys):
    assert main(["denoise", "--pipeline", name, "-o", "iterations=2" if name == "svgf" else "radius=6",
                 str(tiny_sequence_dir), str(tmp_path / "out")]) == 0
    assert len(list((tmp_path / "out").glob("*.exr"))) == 3
    assert f"{name}: 3 frames" in capsys.readouterr().out


def test_svgf_history_survives_radiance_scale_jumps(tiny_layers):
    """Frames at 1, 1e20 and 1 times the radiance: the history is rescaled, nothing overflows."""
    pipeline = pipelines.get("svgf")
    state = pipeline.start(24, 40)
    for layers, gain in zip(tiny_layers, (1.0, 1e20, 1.0), strict=True):
        scaled = {k: (v * gain if k in ("color", "colorA", "colorB", "emission") else v) for k, v in layers.items()}
        out, state = pipeline.step(Frame.from_buffers(scaled), state)
        assert np.isfinite(out["color"]).all()
        assert np.isfinite(state.history).all()  # the output clamp would hide an overflowed history
        assert out["color"].max() <= scaled["color"].max() * 1.01  # the 1e20 history does not leak back
