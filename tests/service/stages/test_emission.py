import numpy as np
import pytest

from service.stages.emission import add_emission, subtract_emission, subtract_emission_reference


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
    """Emission at every pixel: no pixel has a neighbour without emission, so nothing is clipped."""
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
    with pytest.raises(ValueError, match=r"emission: expected \(H, W, 3\) layers, got \(6, 5, 1\)"):
        subtract_emission([color[..., :1]], emission[..., :1])
    transposed = np.ascontiguousarray(color.transpose(1, 0, 2)).transpose(1, 0, 2)  # not C-contiguous
    np.testing.assert_array_equal(subtract_emission([transposed], emission.astype(np.float64))[0], color - emission)


@pytest.mark.parametrize("count", [1, 2, 3])
@pytest.mark.parametrize("shape", [(1, 1, 3), (1, 7, 3), (9, 1, 3), (2, 2, 3), (37, 53, 3)])
@pytest.mark.parametrize("share", [0.3, 0.9])  # 0.9: most pixels amid emitters, the kernel's shortcut taken
def test_subtract_with_scattered_emitters_matches_the_numpy_twin(count, shape, share):
    rng = np.random.default_rng(5)
    layers = [rng.standard_normal(shape).astype(np.float32) * 10 for _ in range(count)]
    emission = np.where(rng.random((*shape[:2], 1)) < share, rng.uniform(0, 50, shape), 0).astype(np.float32)
    emission[rng.random(shape[:2]) < 0.05, 1] = 0  # pixels with emission in some channels only
    for fast, slow in zip(subtract_emission(layers, emission), subtract_emission_reference(layers, emission),
                          strict=True):
        np.testing.assert_array_equal(fast, slow)


def _light_edge():
    """A 5x5 frame of radiance 2 with a light of 1000 covering (2, 2) whole and (2, 3) and (1, 2) in part: the
    colour's few samples missed the light at (2, 3) (colour 1.1 < emission 300) and hit it too often at (1, 2)
    (colour 900 > emission 200 + 2)."""
    color = np.full((5, 5, 3), 2.0, np.float32)
    color[0, 1] = 3.0  # (1, 2)'s neighbours range over [2, 3]
    emission = np.zeros_like(color)
    emission[2, 2], emission[2, 3], emission[1, 2] = 1000.0, 300.0, 200.0
    color[2, 2], color[2, 3], color[1, 2] = 1000.0, 1.1, 900.0
    return color, emission


def test_the_remainder_at_an_emitters_edge_stays_within_its_neighbours_range():
    color, emission = _light_edge()
    less = subtract_emission([color], emission)[0]
    np.testing.assert_array_equal(less[2, 3], 0.0)  # -298.9: clipped up to min(0, 2)
    np.testing.assert_array_equal(less[1, 2], 3.0)  # +700: clipped down to its neighbours' highest, (0, 1)'s 3
    np.testing.assert_array_equal(less[2, 2], 0.0)  # the light seen whole: its remainder 0 is in range
    away = np.ones((5, 5), bool)
    away[1:3, 2:4] = False
    np.testing.assert_array_equal(less[away], color[away])  # no emission: the colour as it is
    np.testing.assert_array_equal(less, subtract_emission_reference([color], emission)[0])


def test_a_pixel_amid_emitters_keeps_its_remainder_and_negative_neighbours_widen_the_range():
    color, emission = _light_edge()
    emission[:] = np.maximum(emission, 1.0)  # a sky behind everything: no pixel lacks emission
    np.testing.assert_array_equal(subtract_emission([color], emission)[0], color - emission)
    color, emission = _light_edge()
    color[1:4, 1:5] = -5.0  # negative radiance around the edge pixel (legal input)
    color[2, 3] = -400.0
    assert subtract_emission([color], emission)[0][2, 3, 0] == -5.0  # the range [min(0, -5), -5]
