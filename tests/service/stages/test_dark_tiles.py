"""The dark pixels' test of the noise blend (service/stages/dark_tiles.py): its tail probability against
enumeration, the kernel against its numpy twin, and the analytic threshold on an all-dark half tile."""

import itertools
import math

import numpy as np
import pytest

from service.stages.dark_tiles import EVIDENCE, lower_tail, one_hit_values, refuted, refuted_reference


@pytest.mark.parametrize("lit", [0, 1, 3])
def test_lower_tail_matches_enumeration(lit):
    chances = np.random.default_rng(lit).random(7)
    total = 0.0
    for dark in itertools.product([True, False], repeat=7):
        if sum(not d for d in dark) <= lit:
            total += math.prod(p if d else 1 - p for p, d in zip(chances, dark, strict=True))
    assert lower_tail(chances, lit) == pytest.approx(total, rel=1e-12)


def _frame(rng, shape=(32, 48, 3)):
    """Lit left (1 +- 0.3 per half), dark right (both halves 0) from column 24, a few exact and noisy pixels
    in the dark part."""
    truth = np.zeros(shape, np.float32)
    truth[:, :24] = 1.0
    a = (truth + rng.normal(0, 0.3, shape) * truth).astype(np.float32)
    b = (truth + rng.normal(0, 0.3, shape) * truth).astype(np.float32)
    a[3, 30] = b[3, 30] = 0.5  # exact: takes no part
    a[20, 40] = 2.0  # a one-half hit in the dark
    return a, b, ((a + b) / 2).astype(np.float32)


@pytest.mark.parametrize("emission", [False, True])
def test_kernel_matches_the_numpy_twin(emission):
    rng = np.random.default_rng(4)
    a, b, color = _frame(rng)
    out = color.copy()
    out[:, 24:] += rng.random(out[:, 24:].shape).astype(np.float32) * 0.2
    e = None
    if emission:
        e = np.zeros_like(color)
        e[10:12, 26:30] = 0.7
        a, b, color, out = (x + e for x in (a, b, color, out))
    hit = np.full((4, 6), 0.05)
    hit[0, 5] = np.inf
    candidates = np.ones((4, 6), np.bool_)
    candidates[1, 4] = False
    got = refuted(out, a, b, e, hit, candidates, 8)
    np.testing.assert_array_equal(got, refuted_reference(out, a, b, e, hit, candidates, 8))
    assert got[:, 3:].any() and not got[:, :3].any()  # the lifted dark part, not the lit part


@pytest.mark.parametrize("factor, expected", [(1.2, True), (0.8, False)])
def test_an_all_dark_half_tile_is_refuted_beyond_the_evidence(factor, expected):
    """An all-dark 8x8 half tile with the output at o everywhere: its samples all missed with a chance of
    exp(-64 o / h); refuted exactly where 64 o / h exceeds EVIDENCE."""
    h = 0.05
    out = np.full((8, 8, 3), factor * EVIDENCE * h / 64, np.float32)
    zero = np.zeros_like(out)
    got = refuted(out, zero, zero, None, np.full((1, 1), h), np.ones((1, 1), np.bool_), 8)
    assert bool(got[0, 0]) is expected


def test_the_one_hit_value_is_the_least_qualifying_neighbours_ratio_or_the_tiles_own_if_larger():
    noisy = np.array([[64.0, 10.0, 0.0], [64.0, 64.0, 0.0]])
    lit = np.array([[64.0, 10.0, 0.0], [32.0, 64.0, 0.0]])
    variance = np.array([[3.2, 1.0, 0.0], [6.4, 12.8, 0.0]])  # ratios 0.05, 0.1 (10 noisy: no neighbour), 0.2
    pixels = np.full((2, 3), 64)
    got = one_hit_values(noisy, lit, variance, pixels, 0.25)
    np.testing.assert_allclose(got, [[0.05, 0.1, 0.2], [0.2, 0.2, 0.2]])


def test_halves_within_a_thousandth_of_one_hit_of_zero_are_dark():
    """A renderer's shadow holds 1e-15 here and there (float rounding of paths that carry nothing): such a
    pixel's halves differ, yet it is dark as far as the light is concerned. Refuted the same as exact zeros."""
    h = 0.05
    out = np.full((8, 8, 3), 2 * EVIDENCE * h / 64, np.float32)
    zero = np.zeros_like(out)
    tiny = zero.copy()
    tiny[::2, ::3] = 1e-15
    tiny[1, 1] = 0.999e-3 * h
    args = (np.full((1, 1), h), np.ones((1, 1), np.bool_), 8)
    assert refuted(out, tiny, zero, None, *args)[0, 0] and refuted_reference(out, tiny, zero, None, *args)[0, 0]
    tiny[1, 1] = 1.001e-3 * h  # a pixel beyond the level is noisy: one lit pixel of 64, still refuted
    assert refuted(out, tiny, zero, None, *args)[0, 0]
    tiny[::2] = 1.001e-3 * h  # half of them: the output's light explains them
    assert not refuted(out, tiny, zero, None, *args)[0, 0]


def test_a_neighbour_of_specks_is_no_measure_of_a_hit():
    """A shadow whose 64 pixels hold 1e-15 in one half (ratio 5e-16) beside a lit half tile of ratio 0.05: the
    specks do not qualify, so neither their own nor their neighbours' one-hit value falls to 5e-16."""
    noisy = np.array([[64.0, 64.0]])
    lit = np.array([[64 * 1e-15, 64.0]])
    variance = np.array([[64 * 5e-31, 3.2]])
    got = one_hit_values(noisy, lit, variance, np.full((1, 2), 64), 0.25)
    np.testing.assert_allclose(got, [[0.05, 0.05]])
