"""Which pixels and frames each benchmark score sees (bench/scoring.py)."""

from __future__ import annotations

import numpy as np
import pytest

from bench import scoring
from bench.hard_cases import TILE_FLOOR, TILE_SLACK
from bench.scoring import SequenceScore, disoccluded_mask, score_frame
from service.frame import Frame
from service.metrics import rel_l2_map


def test_disoccluded_error_is_untrimmed_mean_over_the_mask() -> None:
    rng = np.random.default_rng(0)
    reference = rng.uniform(0.5, 1.0, (6, 7, 3)).astype(np.float32)
    image = reference + rng.normal(0, 0.1, reference.shape).astype(np.float32)
    mask = np.zeros((6, 7), bool)
    mask[2:4, 1:5] = True
    score = score_frame(image, reference, (reference, reference), mask, flip=False)
    expected = rel_l2_map(image, reference)[mask].mean()
    assert score.as_dict()["disoccluded_rel_l2"] == pytest.approx(expected)
    assert score.disoccluded_pixels == 8 and score.temporal is not None and score.flip is None
    first = score_frame(image, reference, None, None, flip=False)
    assert first.temporal is None and first.as_dict()["disoccluded_rel_l2"] is None


def test_sequence_summary_pools_disoccluded_pixels_and_takes_median_time() -> None:
    frames = [scoring.FrameScore(0.1, 0.2, None, None, None, 0), scoring.FrameScore(0.3, 0.4, None, 0.5, 2.0, 4),
              scoring.FrameScore(0.2, 0.3, None, 0.7, 0.0, 0)]
    summary = SequenceScore(frames, [5.0, 1.0, 3.0]).summary(megapixels=0.5)
    assert summary["ms_per_frame"] == 3.0 and summary["ms_per_megapixel"] == 6.0
    assert summary["rel_l2"] == pytest.approx(0.2) and summary["temporal"] == pytest.approx(0.6)
    assert summary["disoccluded_rel_l2"] == pytest.approx(0.5)  # 2.0 over 4 pixels, pooled
    assert summary["flip"] is None


def test_worst_tile_is_the_hard_cases_criterion_and_the_summary_names_where() -> None:
    rng = np.random.default_rng(1)
    reference = rng.uniform(0.5, 1.0, (40, 33, 3)).astype(np.float32)
    noisy = (reference * rng.lognormal(0.0, 0.3, reference.shape)).astype(np.float32)
    image = reference.copy()
    image[34:38, 20:24] = 0.0  # a black patch in the ragged tile (32, 16)
    score = score_frame(image, reference, None, None, flip=False, noisy=noisy)
    out_map, noisy_map = rel_l2_map(image, reference), rel_l2_map(noisy, reference)
    expected = (out_map[32:, 16:32].mean() + TILE_FLOOR) / (noisy_map[32:, 16:32].mean() + TILE_FLOOR)
    assert score.worst_tile == (32, 16) and score.worst_tile_ratio == pytest.approx(expected)
    assert score.worst_tile_ratio > 1.0 + TILE_SLACK and score.failing_tiles == 1
    assert score.as_dict()["worst_tile"] == [32, 16]
    clean = score_frame(reference, reference, None, None, flip=False, noisy=noisy)
    assert clean.failing_tiles == 0 and clean.worst_tile_ratio < 1.0
    assert score_frame(image, reference, None, None, flip=False).worst_tile_ratio is None  # no noisy input
    summary = SequenceScore([clean, score, clean], [1.0, 1.0, 1.0]).summary(megapixels=1.0)
    assert summary["worst_tile"] == score.worst_tile_ratio and summary["worst_tile_at"] == "frame 1 (32, 16)"
    assert summary["failing_tiles"] == 1
    assert SequenceScore([score_frame(image, reference, None, None, flip=False)], [1.0]).tiles()["worst_tile"] is None


def test_static_camera_has_no_disocclusion(tiny_layers) -> None:
    prev, frame = Frame.from_buffers(tiny_layers[0]), Frame.from_buffers(tiny_layers[1])
    still = np.zeros_like(frame["motion"])
    static = frame.replace(motion=still, motionDual=still, depth=prev["depth"], normal=prev["normal"])
    mask = disoccluded_mask(static, prev)
    assert mask is not None and mask.shape == (frame.height, frame.width) and not mask.any()
    dual = still.copy()
    dual[1, 2] = (0.3, -0.3)  # 0.42 px apart: not occluded
    dual[3, 4] = (0.0, 0.6)  # 0.6 px: occluded in the previous frame
    mask = disoccluded_mask(static.replace(motionDual=dual), prev)
    assert mask.sum() == 1 and mask[3, 4]
    plain = Frame({k: v for k, v in static.replace(motionDual=dual).buffers.items() if k != "motionDual"}, {})
    assert not disoccluded_mask(plain, prev).any()  # without motionDual, only the reprojection decides
    assert disoccluded_mask(Frame.from_buffers({"color": frame["color"]}), prev) is None  # no motion layer
