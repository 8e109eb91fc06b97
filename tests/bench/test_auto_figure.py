"""`python -m bench.auto_figure`: auto's blend, its `error` layer and the true error of one frame."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from bench.auto_figure import main, run_auto
from service import pipelines
from service.exr import list_sequence, read_frame, write_frame
from service.frame import FrameError
from service.metrics import rel_l2_map
from service.stages.error_estimate import tile_means


def test_the_frame_auto_served_with_its_blend_estimate_and_truth(tiny_sequence_dir: Path, tmp_path: Path) -> None:
    """What the figure shows is what `auto` serves: the same output, `error` layer and blend as a run of the
    pipeline itself, and the per-tile truth of that output."""
    result = run_auto(tiny_sequence_dir, 1)
    frames = [read_frame(p) for p in list_sequence(tiny_sequence_dir)[:2]]
    auto = pipelines.get("auto")
    state = auto.start(frames[0].height, frames[0].width)
    for frame in frames:
        served, state = auto.step(frame, state)
    np.testing.assert_array_equal(result["color"], served["color"])
    np.testing.assert_array_equal(result["error"], served["error"][..., 0])
    np.testing.assert_array_equal(result["blend"], state.blend)
    assert result["candidates"] == list(state.candidates) and result["evaluated"] == 1
    assert result["shares"] == state.shares() and sum(result["shares"].values()) == pytest.approx(1.0)
    np.testing.assert_array_equal(result["truth"], tile_means(rel_l2_map(served["color"], frames[1]["reference"]),
                                                              result["tile"]))
    out = tmp_path / "auto.png"
    assert main([str(tiny_sequence_dir), str(out)]) == 0
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_a_sequence_without_halves_or_a_frame_beyond_it_is_refused(tiny_sequence_dir: Path, tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="frame 9 is not in 0..2"):
        run_auto(tiny_sequence_dir, 9)
    plain = tmp_path / "plain"
    plain.mkdir()
    for path in list_sequence(tiny_sequence_dir):
        frame = read_frame(path)
        write_frame(plain / path.name, {k: v for k, v in frame.buffers.items() if k != "colorB"})
    with pytest.raises(FrameError, match="colorB"):
        run_auto(plain)
