"""Exact pixels from the halves (service/stages/exact.py): the numba pass against its numpy reference, and
what counts as exact."""

import numpy as np
import pytest

from service.stages.exact import EXACT_RTOL, exact_emission, exact_mask


def _halves(rng, shape):
    a = rng.lognormal(0.0, 1.0, shape).astype(np.float32)
    b = rng.lognormal(0.0, 1.0, shape).astype(np.float32)
    return a, b


def test_a_light_whose_halves_agree_is_exact_and_noise_is_not():
    a, b = _halves(np.random.default_rng(0), (9, 11, 3))
    a[4, 5] = b[4, 5] = (3000.0, 2700.0, 2300.0)  # every sample saw the emitter
    a[0, 0] = b[0, 0] = 0.0  # no light found in either half: noise, not exact
    a[1, 1], b[1, 1] = 0.5, 0.5 * (1 + 10 * EXACT_RTOL)  # close, but beyond the tolerance
    mask = exact_mask(a, b)
    assert mask[4, 5] and mask.sum() == 1
    emission = exact_emission(a, b, (a + b) / 2)
    assert emission is not None
    np.testing.assert_array_equal(emission[4, 5], [3000.0, 2700.0, 2300.0])
    assert np.count_nonzero(emission) == 3


@pytest.mark.parametrize("shape", [(1, 1, 3), (37, 53, 3)])
def test_numba_pass_matches_the_mask(shape):
    rng = np.random.default_rng(1)
    a, b = _halves(rng, shape)
    same = rng.random(shape[:2]) < 0.3
    b[same] = a[same]
    color = (a + b) / 2
    emission = exact_emission(a, b, color)
    expected = np.where(exact_mask(a, b)[..., None], color, 0.0)
    np.testing.assert_array_equal(emission if emission is not None else np.zeros_like(color), expected)


def test_none_when_no_pixel_is_exact():
    a, b = _halves(np.random.default_rng(2), (16, 16, 3))
    assert exact_emission(a, b, a) is None
    zeros = np.zeros((4, 4, 3), np.float32)
    assert exact_emission(zeros, zeros, zeros) is None  # black everywhere: nothing to keep


def test_an_emission_layer_that_disagrees_rejects_an_agreeing_pixel():
    a, b = _halves(np.random.default_rng(3), (5, 5, 3))
    a[2, 2] = b[2, 2] = 3000.0  # every sample hit the light's edge...
    emission = np.zeros_like(a)
    emission[2, 2] = 900.0  # ...but the converged emission covers only part of the pixel
    color = (a + b) / 2
    assert exact_mask(a, b)[2, 2] and not exact_mask(a, b, color, emission)[2, 2]
    emission[2, 2] = 3000.0
    assert exact_mask(a, b, color, emission)[2, 2]
