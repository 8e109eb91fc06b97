"""The hidden-state warp: block-mean motion, each level's motion built from the level above, an integer
shift moves the state exactly, and parity with the torch twin that training runs through
(models/nets/warp.py)."""

import numpy as np
import pytest

from service.stages.hidden_warp import downsample_motion, level_motions, warp_states
from tests.tolerances import TWIN_ATOL

SCALES = (2, 4, 8, 16)  # the shipped network's levels (models.nets.rae.RaeConfig.scales)


def test_motion_is_averaged_per_block_and_scaled():
    motion = np.zeros((4, 4, 2), np.float32)
    motion[:2, :2, 0] = (4.0, 8.0)  # the first 2x2 block: columns of 4 and 8 px, mean 6 px
    level = downsample_motion(motion, 2)
    assert level.shape == (2, 2, 2)
    assert level[0, 0, 0] == pytest.approx(3.0)  # 6 px are 3 px of the half-resolution grid
    assert (level[1:, :] == 0).all() and (level[:, 1:] == 0).all()


@pytest.mark.parametrize("factor", [1, 2, 3, 4, 16])
def test_downsampling_is_the_block_mean_over_the_factor(factor):
    rng = np.random.default_rng(factor)
    motion = (rng.standard_normal((2 * factor, 3 * factor, 2)) * 5).astype(np.float32)
    blocks = motion.reshape(2, factor, 3, factor, 2)
    expected = blocks.mean(axis=(1, 3), dtype=np.float32) / np.float32(factor)
    np.testing.assert_array_equal(downsample_motion(motion, factor), expected)


def test_each_level_from_the_level_above_is_the_block_mean_of_the_frame():
    """The 2x2 mean of 2x2 means is the 4x4 mean: exactly where the sums are exact in float32 (quarter
    pixels), to float32 rounding otherwise."""
    rng = np.random.default_rng(0)
    quarters = (rng.integers(-64, 64, (64, 96, 2)) / 4).astype(np.float32)
    for level, scale in zip(level_motions(quarters, SCALES), SCALES, strict=True):
        np.testing.assert_array_equal(level, downsample_motion(quarters, scale))
    motion = (rng.standard_normal((64, 96, 2)) * 7).astype(np.float32)
    for level, scale in zip(level_motions(motion, SCALES), SCALES, strict=True):
        np.testing.assert_allclose(level, downsample_motion(motion, scale), rtol=1e-6, atol=1e-7)
    with pytest.raises(ValueError, match=r"scales must each divide the next, got \[2, 6, 9\]"):
        level_motions(np.zeros((36, 36, 2), np.float32), (2, 6, 9))


def test_an_integer_motion_moves_the_state_by_whole_pixels():
    rng = np.random.default_rng(0)
    state = rng.standard_normal((1, 3, 5, 6)).astype(np.float32)
    motion = np.zeros((10, 12, 2), np.float32)
    motion[..., 0] = 2.0  # every pixel was 2 px to the right: 1 px on the half-resolution grid
    (warped,) = warp_states([state], motion, [2])
    np.testing.assert_array_equal(warped[..., :-1], state[..., 1:])
    assert (warped[..., -1] == 0).all()  # came from outside the frame


@pytest.mark.parametrize(("size", "scales"), [((12, 20), (2,)), ((16, 8), (4,)), ((7, 9), (1,)),
                                              ((32, 48), (2, 4, 8, 16)), ((24, 40), (2, 4, 8))])
def test_torch_twin_agrees(size, scales):
    """Every level against models.nets.warp.warp_level, which pools the full-resolution motion directly."""
    torch = pytest.importorskip("torch")
    from models.nets.warp import warp_level

    (h, w), rng = size, np.random.default_rng(size[0])
    states = [rng.standard_normal((1, 4, h // s, w // s)).astype(np.float32) for s in scales]
    motion = (rng.standard_normal((h, w, 2)) * 3).astype(np.float32)
    ours = warp_states(states, motion, scales)
    torch_motion = torch.from_numpy(motion.transpose(2, 0, 1)[None].copy())
    for state, warped, scale in zip(states, ours, scales, strict=True):
        theirs = warp_level(torch.from_numpy(state), torch_motion, scale)
        np.testing.assert_allclose(warped, theirs.numpy(), atol=TWIN_ATOL)
