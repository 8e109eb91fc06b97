"""bench.error_estimate: rank correlation, per-tile assembly, and the evaluation on a small sequence."""

from pathlib import Path

import numpy as np
import pytest

from bench.error_estimate import assemble, evaluate, one_half, spearman
from service.exr import list_sequence, read_frame


def test_spearman_is_one_for_any_increasing_map_and_minus_one_reversed():
    x = np.random.default_rng(0).random(50)
    assert spearman(x, np.exp(3 * x)) == pytest.approx(1.0)
    assert spearman(x, -x) == pytest.approx(-1.0)


def test_assemble_takes_each_tile_from_its_candidate_ragged_borders_too():
    outputs = np.stack([np.full((5, 7, 3), k, np.float32) for k in range(3)])
    choice = np.array([[2, 0], [1, 2]])
    frame = assemble(outputs, choice, 4)
    assert frame.shape == (5, 7, 3)
    assert (frame[:4, :4] == 2).all() and (frame[:4, 4:] == 0).all()
    assert (frame[4:, :4] == 1).all() and (frame[4:, 4:] == 2).all()


@pytest.mark.parametrize("name", ["colorA", "colorB"])
def test_one_half_serves_that_half_as_the_colour_without_the_halves(tiny_sequence_dir: Path, name):
    frame = read_frame(list_sequence(tiny_sequence_dir)[0])
    half = one_half(frame, name)
    assert "colorA" not in half and "colorB" not in half
    np.testing.assert_array_equal(half["color"], frame[name])
    np.testing.assert_array_equal(half["albedo"], frame["albedo"])


def test_evaluation_of_a_small_sequence(tiny_sequence_dir: Path):
    report = evaluate(tiny_sequence_dir, ["bilateral", "flr"], tile=8)
    assert report.candidates == ["bilateral", "flr"]
    assert len(report.one_way) == len(report.both_ways) == len(report.controlled) == len(report.per_candidate) == 2
    assert all(-1.0 <= v <= 1.0 for v in (*report.one_way, *report.both_ways, *report.controlled, *report.per_candidate,
                                          report.pooled, report.pooled_half))
    assert 0.0 <= report.best_match <= 1.0
    assert report.oracle <= report.best_single[1] + 1e-12  # the per-tile oracle is at least the best single one
    assert report.oracle <= report.chosen + 1e-12
