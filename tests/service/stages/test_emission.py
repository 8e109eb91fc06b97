import numpy as np
import pytest

from service.stages.emission import add_emission, subtract_emission


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


@pytest.mark.parametrize("count", [1, 2, 3])
@pytest.mark.parametrize("shape", [(1, 1, 3), (151, 203, 3)])
def test_subtract_matches_numpy_for_each_layer(count, shape):
    rng = np.random.default_rng(3)
    *layers, emission = [rng.standard_normal(shape).astype(np.float32) * 10 for _ in range(count + 1)]
    split = subtract_emission(layers, emission)
    assert len(split) == count
    for layer, less in zip(layers, split, strict=True):
        assert less.dtype == np.float32 and less.flags.c_contiguous
        np.testing.assert_array_equal(less, layer - emission)


def test_subtract_refuses_mismatched_shapes_and_layer_counts():
    color, emission = _layers(np.random.default_rng(4), (6, 5, 3))
    with pytest.raises(ValueError, match=r"emission: a radiance layer \(5, 5, 3\) does not match the emission"):
        subtract_emission([color, color[:5]], emission)
    with pytest.raises(ValueError, match="emission: takes 1 to 3 layers, got 4"):
        subtract_emission([color] * 4, emission)
