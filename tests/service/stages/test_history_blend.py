"""service/stages/history_blend.py: analytic cases and the local-range invariant."""

import numpy as np

from service.stages.history_blend import blend_history
from service.stages.range_clamp import local_range_reference

H, W = 24, 31


def _geometry():
    depth = np.full((H, W, 1), 2.0, np.float32)
    normal = np.zeros((H, W, 3), np.float32)
    normal[..., 2] = 1.0
    return depth, normal


def test_a_still_constant_frame_stays_constant():
    depth, normal = _geometry()
    flat = np.full((H, W, 3), 0.7, np.float32)
    out = blend_history(flat, flat.copy(), np.zeros((H, W, 2), np.float32), depth, depth, normal, normal, 0.5, 1)
    assert out.dtype == np.float32
    np.testing.assert_array_equal(out, flat)


def test_the_blend_is_the_weighted_mean_where_the_history_is_in_range():
    """A still camera and a history within the current range (a smooth ramp, shifted by less than a pixel's
    step): out = (1 - w) current + w previous exactly."""
    depth, normal = _geometry()
    ramp = np.broadcast_to(np.linspace(1.0, 2.0, W, dtype=np.float32)[None, :, None], (H, W, 3)).copy()
    previous = ramp + np.float32(0.01)
    out = blend_history(ramp, previous, np.zeros((H, W, 2), np.float32), depth, depth, normal, normal, 0.25, 1)
    inner = (slice(None), slice(None, -1))  # at the ramp's bright end previous is above the range: clipped
    np.testing.assert_allclose(out[inner], (0.75 * ramp + 0.25 * previous)[inner], rtol=1e-6)


def test_the_result_stays_within_the_local_range_of_the_current_frame_and_follows_motion():
    """Random frames, motion of a few pixels: every output within the current frame's 3x3 (radius 1) or 5x5
    range; a history shifted by the motion is found where the motion says (a moving ramp)."""
    rng = np.random.default_rng(2)
    depth, normal = _geometry()
    current = rng.uniform(0, 5, (H, W, 3)).astype(np.float32)
    previous = rng.uniform(0, 5, (H, W, 3)).astype(np.float32)
    motion = rng.uniform(-3, 3, (H, W, 2)).astype(np.float32)
    for radius in (1, 2):
        out = blend_history(current, previous, motion, depth, depth, normal, normal, 0.9, radius)
        lo, hi = local_range_reference(current, radius)
        assert (out >= lo).all() and (out <= hi).all()
        assert not np.allclose(out, current)
    ramp = np.broadcast_to(np.arange(W, dtype=np.float32)[None, :, None], (H, W, 3)).copy()
    shifted = np.full((H, W, 2), 0.0, np.float32)
    shifted[..., 0] = 2.0  # each pixel was 2 px to the right: previous(x + 2)
    out = blend_history(ramp, ramp - 2.0, shifted, depth, depth, normal, normal, 0.5, 1)
    np.testing.assert_allclose(out[:, 1:-3], ramp[:, 1:-3], atol=1e-5)  # ramp - 2 moved by 2 is the ramp again


def test_where_reprojection_fails_the_current_frame_is_kept():
    rng = np.random.default_rng(3)
    depth, normal = _geometry()
    current = rng.uniform(0, 1, (H, W, 3)).astype(np.float32)
    previous = rng.uniform(0, 1, (H, W, 3)).astype(np.float32)
    far = depth * np.float32(3.0)  # every tap's depth changed by 200%: no consistent history
    out = blend_history(current, previous, np.zeros((H, W, 2), np.float32), depth, far, normal, normal, 0.5, 1)
    np.testing.assert_array_equal(out, current)
