"""The background stage (service/stages/background.py): where nothing was hit, the input as it came."""

import numpy as np
import pytest

from service.stages.background import FILTER_REACH, pass_background


def _frame(seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    out = rng.random((16, 20, 3), dtype=np.float32)
    color = rng.random((16, 20, 3), dtype=np.float32) * 1e3
    normal = np.zeros((16, 20, 3), np.float32)
    normal[..., 2] = 1.0
    return out, color, normal


def test_pixels_beyond_the_filters_reach_of_any_hit_take_the_input_and_the_rest_keep_the_output():
    out, color, normal = _frame()
    normal[:8] = 0.0  # a sky over the top half, the frame's edge beyond it
    normal[3, 10] = (0.3, 0.3, 0.0)  # |n|^2 = 0.18: below NORMAL_HIT, a pixel that mostly missed
    normal[5, 3] = (0.0, 1.0, 0.0)  # one surface pixel in the sky (a wire)
    sky = np.zeros((16, 20), bool)
    sky[: 8 - FILTER_REACH] = True  # the rows within reach of the surface below stay the denoiser's
    sky[5 - FILTER_REACH: 5 + FILTER_REACH + 1, 3 - FILTER_REACH: 3 + FILTER_REACH + 1] = False  # and the wire's
    got = pass_background(out, color, normal)
    assert got.dtype == np.float32
    np.testing.assert_array_equal(got[sky], color[sky])
    np.testing.assert_array_equal(got[~sky], out[~sky])
    assert sky[3, 10] and sky[0, 0]


def test_a_frame_that_hit_everywhere_or_nowhere_far_from_a_hit_is_returned_itself():
    out, color, normal = _frame(1)
    assert pass_background(out, color, normal) is out
    normal[::3] = 0.0  # misses in every third row: each within reach of a hit
    assert pass_background(out, color, normal) is out


def test_a_sky_the_emission_layer_holds_keeps_the_output():
    """Where the renderer's emission is non-zero the emission split has the pixel; elsewhere in the sky (an
    emission layer of the emitters alone) the input passes."""
    out, color, normal = _frame(3)
    normal[:8] = 0.0
    emission = np.zeros_like(color)
    emission[0] = color[0]  # row 0: the environment in the emission layer; row 1: not
    got = pass_background(out, color, normal, emission)
    np.testing.assert_array_equal(got[0], out[0])
    np.testing.assert_array_equal(got[1], color[1])
    np.testing.assert_array_equal(got[8 - FILTER_REACH:], out[8 - FILTER_REACH:])


def test_mismatched_shapes_are_refused():
    out, color, normal = _frame(2)
    with pytest.raises(ValueError, match="share one"):
        pass_background(out, color[:, :5], normal)
    with pytest.raises(ValueError, match="share one"):
        pass_background(out, color, normal, emission=color[:4])
