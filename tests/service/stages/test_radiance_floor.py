"""The step's radiance floor (service/stages/radiance_floor.py): nothing below min(0, the input's minimum)."""

import numpy as np
import pytest

from service.stages.radiance_floor import radiance_floor


def _frames(seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    out = (rng.standard_normal((9, 13, 3)) * 10).astype(np.float32)
    color = rng.random((9, 13, 3)).astype(np.float32)
    return out, color


def test_non_negative_input_clips_the_output_at_zero():
    out, color = _frames()
    clipped = radiance_floor(out, color)
    np.testing.assert_array_equal(clipped, np.maximum(out, 0))
    assert clipped is not out and (out < 0).any()  # the denoiser's array is left as it was


def test_negative_input_lowers_the_floor_to_its_minimum():
    out, color = _frames(1)
    color[4, 7, 1] = -2.5  # a negative light somewhere in the frame
    np.testing.assert_array_equal(radiance_floor(out, color), np.maximum(out, np.float32(-2.5)))


def test_non_finite_output_stays_for_the_steps_finite_check():
    out, color = _frames(2)
    out[0, 0, 0], out[3, 3, 2], out[5, 1, 0] = np.nan, -np.inf, np.inf
    clipped = radiance_floor(out, color)
    assert np.isnan(clipped[0, 0, 0]) and clipped[3, 3, 2] == -np.inf and clipped[5, 1, 0] == np.inf


def test_the_clip_can_only_lower_the_error_against_a_non_negative_reference():
    out, color = _frames(3)
    reference = np.abs(out[::-1]) + 0.01
    before, after = np.abs(out - reference), np.abs(radiance_floor(out, color) - reference)
    assert (after <= before).all() and (after < before).any()


def test_layouts_and_shapes():
    out, color = _frames(4)
    np.testing.assert_array_equal(radiance_floor(np.asfortranarray(out), color[:, ::-1][:, ::-1]),
                                  np.maximum(out, 0))
    with pytest.raises(ValueError, match="radiance floor"):
        radiance_floor(out, color[:-1])
