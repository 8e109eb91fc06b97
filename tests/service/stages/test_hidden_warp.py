"""The hidden-state warp: block-mean motion, an integer shift moves the state exactly, and parity with the
torch twin that training runs through (models/nets/warp.py)."""

import numpy as np
import pytest

from service.stages.hidden_warp import downsample_motion, warp_state
from tests.tolerances import TWIN_ATOL


def test_motion_is_averaged_per_block_and_scaled():
    motion = np.zeros((4, 4, 2), np.float32)
    motion[:2, :2, 0] = (4.0, 8.0)  # the first 2x2 block: columns of 4 and 8 px, mean 6 px
    level = downsample_motion(motion, 2)
    assert level.shape == (2, 2, 2)
    assert level[0, 0, 0] == pytest.approx(3.0)  # 6 px are 3 px of the half-resolution grid
    assert (level[1:, :] == 0).all() and (level[:, 1:] == 0).all()


def test_an_integer_motion_moves_the_state_by_whole_pixels():
    rng = np.random.default_rng(0)
    state = rng.standard_normal((1, 3, 5, 6)).astype(np.float32)
    motion = np.zeros((10, 12, 2), np.float32)
    motion[..., 0] = 2.0  # every pixel was 2 px to the right: 1 px on the half-resolution grid
    warped = warp_state(state, motion, 2)
    np.testing.assert_array_equal(warped[..., :-1], state[..., 1:])
    assert (warped[..., -1] == 0).all()  # came from outside the frame


@pytest.mark.parametrize("shape", [(12, 20, 2), (16, 8, 4), (7, 9, 1)])
def test_torch_twin_agrees(shape):
    torch = pytest.importorskip("torch")
    from models.nets.warp import warp_level

    h, w, scale = shape
    rng = np.random.default_rng(h)
    state = rng.standard_normal((1, 4, h // scale, w // scale)).astype(np.float32)
    motion = (rng.standard_normal((h // scale * scale, w // scale * scale, 2)) * 3).astype(np.float32)
    ours = warp_state(state, motion, scale)
    theirs = warp_level(torch.from_numpy(state), torch.from_numpy(motion.transpose(2, 0, 1)[None].copy()), scale)
    np.testing.assert_allclose(ours, theirs.numpy(), atol=TWIN_ATOL)
