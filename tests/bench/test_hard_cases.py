"""The rendered hard cases (bench/hard_cases.py) on every registered pipeline, judged per tile.

Parametrised over `pipelines.names()`, so a new pipeline is held to the criterion as soon as it
registers: half the noisy relL2 or better, no 16x16 tile more than 10% worse than the noisy input's,
exact pixels unchanged. The frames are committed (models/data/samples/hard); no renderer runs here.
Pairs that still fail are listed in KNOWN_FAILURES with their worst tile ratio, held to it.
"""

from __future__ import annotations

from functools import cache

import numpy as np
import pytest

from bench import hard_cases
from bench.hard_cases import CASE_NAMES, EXACT_RTOL, TILE_FLOOR, TILE_SLACK, score, tile_means
from service import pipelines
from service.frame import Frame

# Where a pipeline still fails the criterion, with its worst tile ratio as measured (`python -m bench.hard_cases
# table`). A listed pair may not get worse than recorded (test below), and one that passes must leave the list;
# those within 20% of the limit may pass or fail (another CPU's rounding). Since the noise blend's half tiles
# hold their weight over their own pixels (service/stages/noise_blend.py) every pair passes here; bmfr on bulb
# (was 1.16x) passes by far, crossregression on glints (was 1.13x) at 1.07x since its window is 15.
KNOWN_FAILURES: dict[tuple[str, str], float] = {}


def _params() -> list:
    return [pytest.param(p, c, id=f"{p}-{c}") for p in pipelines.names() for c in CASE_NAMES]


@cache
def _layers(name: str) -> frozenset[str]:
    return frozenset(hard_cases.frames(name)[0].buffers)


def test_known_failures_name_real_pairs() -> None:
    assert {p for p, _ in KNOWN_FAILURES} <= set(pipelines.names())
    assert {c for _, c in KNOWN_FAILURES} <= set(CASE_NAMES)


@pytest.mark.parametrize(("pipeline_name", "case_name"), _params())
def test_pipeline_passes_hard_case(pipeline_name: str, case_name: str) -> None:
    """A pair passes the criterion; a known failure may not get worse: its worst tile stays within 20% of the
    recorded ratio, exact pixels stay unchanged and the frame's relL2 stays below the noisy input's. A known
    failure that now passes (and was recorded more than 20% beyond the limit) must leave the ledger."""
    pipeline = pipelines.get(pipeline_name)
    missing = set(pipeline.requires) - _layers(case_name)
    if missing:
        pytest.skip(f"{pipeline_name} needs {sorted(missing)}")
    scores = hard_cases.run(pipeline, case_name)
    recorded = KNOWN_FAILURES.get((pipeline_name, case_name))
    if recorded is None:
        for index, result in enumerate(scores):
            assert not result.failures(), f"{pipeline_name} / {case_name}, frame {index}: {result.failures()}"
        return
    worst = max(s.worst_tile_ratio for s in scores)
    assert worst <= 1.2 * recorded, f"worst tile {worst:.3g}x, recorded {recorded}x"
    for index, result in enumerate(scores):
        assert result.exact_error <= EXACT_RTOL, f"frame {index}: {result.failures()}"
        assert result.rel_l2 < result.noisy_rel_l2, f"frame {index}: {result.failures()}"
    fixed = not any(s.failures() for s in scores)
    assert not (fixed and recorded > 1.2 * (1 + TILE_SLACK)), "passes now: remove it from KNOWN_FAILURES"


def test_cases_are_what_they_say() -> None:
    for name in CASE_NAMES:
        frames = hard_cases.frames(name)
        assert len(frames) >= 2 and all("reference" in f for f in frames)
        assert ("emission" in frames[0]) == hard_cases.case(name).emission
    bulb = hard_cases.frames("bulb")[0]
    assert float(bulb["color"].max()) > 1e3  # the light is seen directly
    window = hard_cases.frames("window")[0]
    assert float(window["reference"].max()) >= 1e3  # the sky through the window
    dark = hard_cases.frames("dark")[0]
    assert float(np.median(dark["reference"])) < 0.1


def _frame(noisy: np.ndarray, reference: np.ndarray) -> Frame:
    return Frame({"color": noisy, "colorA": noisy, "colorB": noisy + 0.5, "reference": reference})


def test_tile_check_catches_a_black_ring_that_the_mean_hides() -> None:
    rng = np.random.default_rng(0)
    reference = np.ones((64, 64, 3), np.float32)
    noisy = (reference * rng.lognormal(-0.02, 0.2, reference.shape)).astype(np.float32)
    out = reference.copy()
    out[20:24, 20:24] = 0.0  # a black patch inside one tile, 16 of 4096 pixels
    result = score(out, _frame(noisy, reference))
    assert result.rel_l2 < 0.5 * result.noisy_rel_l2  # the mean passes
    assert result.worst_tile == (16, 16) and result.worst_tile_ratio > 1.1
    assert any("tile at (16, 16)" in reason for reason in result.failures())
    assert not score(reference.copy(), _frame(noisy, reference)).failures()


def test_exact_pixels_must_come_out_unchanged() -> None:
    reference = np.ones((16, 16, 3), np.float32)
    noisy = reference * 1.3
    frame = Frame({"color": noisy, "colorA": noisy, "colorB": noisy.copy(), "reference": reference})
    frame.buffers["colorB"][1:] += 0.5  # only row 0 is exact (both halves agree)
    out = reference.copy()  # denoised everywhere, so the exact row changed by 1/1.3
    assert score(out, frame).exact_error == pytest.approx(0.3 / 1.3, rel=1e-5)
    out[0] = noisy[0]
    assert score(out, frame).exact_error == 0.0


def test_tile_means_cover_ragged_borders() -> None:
    errors = np.arange(20 * 35, dtype=np.float64).reshape(20, 35)
    means = tile_means(errors, 16)
    assert means.shape == (2, 3)
    assert means[1, 2] == pytest.approx(errors[16:, 32:].mean())
    assert means[0, 0] == pytest.approx(errors[:16, :16].mean())


def test_floor_lets_noise_free_tiles_compare() -> None:
    reference = np.ones((16, 16, 3), np.float32)
    result = score(reference + 1e-4, _frame(reference.copy(), reference))
    assert result.worst_tile_ratio == pytest.approx((1e-8 / 1.01 + TILE_FLOOR) / TILE_FLOOR, rel=1e-6)
    assert result.worst_tile_ratio < 1.0 + TILE_SLACK  # within the floor: not a tile failure
