"""`python -m bench.auto_figure`: auto's choice, its `error` layer and the true error of one frame."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from bench.auto_figure import main, run_auto
from service.exr import list_sequence, read_frame, write_frame
from service.frame import FrameError
from service.metrics import rel_l2_map
from service.pipelines.tiled import CANDIDATES
from service.stages.error_estimate import tile_means


def test_the_frame_auto_served_with_its_choice_estimate_and_truth(tiny_sequence_dir: Path, tmp_path: Path) -> None:
    result = run_auto(tiny_sequence_dir, 1)
    frame = read_frame(list_sequence(tiny_sequence_dir)[1])
    assert result["frame"] == 1 and result["color"].shape == frame["color"].shape
    assert result["error"].shape == frame["color"].shape[:2] and (result["error"] >= 0).all()
    np.testing.assert_array_equal(result["truth"], tile_means(rel_l2_map(result["color"], frame["reference"]),
                                                              result["tile"]))
    assert result["choice"].shape == result["truth"].shape
    assert set(result["candidates"]) <= set(CANDIDATES) and result["choice"].max() < len(result["candidates"])
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
