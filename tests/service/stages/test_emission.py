import numpy as np
import pytest

from service.stages.emission import add_emission


def _layers(rng, shape):
    return [rng.standard_normal(shape).astype(np.float32) * 10 for _ in range(2)]


@pytest.mark.parametrize("shape", [(1, 1, 3), (151, 203, 3)])
def test_add_matches_numpy(shape):
    color, emission = _layers(np.random.default_rng(0), shape)
    total, finite = add_emission(color, emission)
    assert finite and total.dtype == np.float32
    np.testing.assert_array_equal(total, color + emission)


@pytest.mark.parametrize("bad", [np.inf, -np.inf, np.nan])
def test_add_reports_a_non_finite_value_anywhere(bad):
    color, emission = _layers(np.random.default_rng(1), (151, 203, 3))
    color[150, 202, 2] = bad  # the last value
    assert add_emission(color, emission)[1] is False
    color[150, 202, 2] = 3.4e38  # finite, but the sum overflows
    emission[150, 202, 2] = 3.4e38
    assert add_emission(color, emission)[1] is False


def test_other_layouts_are_converted_and_mismatched_shapes_refused():
    color, emission = _layers(np.random.default_rng(2), (6, 5, 3))
    transposed = np.ascontiguousarray(color.transpose(1, 0, 2)).transpose(1, 0, 2)  # not C-contiguous
    np.testing.assert_array_equal(add_emission(transposed, emission.astype(np.float64))[0], color + emission)
    with pytest.raises(ValueError, match="emission: the colour"):
        add_emission(color[:5], emission)
