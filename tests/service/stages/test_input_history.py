"""The accumulated input (service/stages/input_history.py) and the noise blend that takes it back: parity with
the numpy twins over sequences, the average and its error estimate (analytic and statistical cases), and that
the blend takes it only where it is better."""

import numpy as np
import pytest

from service.metrics import rel_l2_map
from service.stages import input_history
from service.stages import noise_blend as noise_blend_module
from service.stages.input_history import InputHistory, accumulate
from service.stages.noise_blend import (
    TILE,
    TILE_MEMORY,
    noise_blend,
    noise_blend_reference,
    remembered_sums,
    takes_accumulated,
)
from tests.service.stages.test_noise_blend import _halves


def _sequence(shape, frames, seed=0):
    """A moving (fractional motion) noisy sequence with depth, normals, a disocclusion edge and some emission."""
    rng = np.random.default_rng(seed)
    height, width = shape
    y, x = np.mgrid[:height, :width]
    out = []
    for k in range(frames):
        truth = (1.0 + np.sin((x - 0.7 * k) / 3.0) * np.cos(y / 4.0))[..., None].repeat(3, -1).astype(np.float32)
        a, b, color = _halves(rng, truth, 0.3)
        a[k % height, (2 * k) % width] += 500.0  # a firefly
        color = ((a + b) / 2).astype(np.float32)
        motion = np.zeros((height, width, 2), np.float32)
        motion[..., 0] = -0.7 if width > 2 else -0.3  # fractional; on screen for a column or a pixel too
        depth = np.where(x < width // 3, 1.0, 2.0)[..., None].astype(np.float32)
        depth[: height // 2, : width // 3] = 1.0 + (k % 2)  # depth that changes: a disocclusion
        normal = np.zeros((height, width, 3), np.float32)
        normal[..., 2] = 1.0
        emission = np.zeros_like(truth)
        emission[height // 2, width // 2] = 40.0
        out.append(dict(truth=truth, a=a + emission, b=b + emission, color=color + emission, motion=motion,
                        depth=depth, normal=normal, emission=emission))
    return out


@pytest.mark.parametrize("lit", [True, False])
@pytest.mark.parametrize("shape", [(1, 1), (5, 2), (17, 33), (40, 29)])
def test_accumulate_matches_the_numpy_twin(shape, lit):
    histories = InputHistory(), InputHistory()
    valid = 0
    for f in _sequence(shape, 4):
        emission = f["emission"] if lit else None
        clipped = (f["color"] - f["emission"]).astype(np.float32)
        got = [accumulate(h, clipped, f["color"], emission, f["a"], f["b"], f["motion"], f["depth"], f["normal"],
                          reference=ref) for h, ref in zip(histories, (False, True), strict=True)]
        if got[0] is None:
            assert got[1] is None
            continue
        for kernel, twin in zip(*got, strict=True):  # accumulated input, error, floor
            np.testing.assert_allclose(kernel, twin, rtol=1e-4, atol=1e-5)
        np.testing.assert_allclose(histories[0].buffer, histories[1].buffer, rtol=1e-5, atol=1e-5)
        valid += int((histories[0].buffer[..., -1] > 1).sum())
    assert valid > 0  # the reprojection held somewhere: the history's path was compared


def test_a_static_frame_is_averaged_and_the_history_is_clamped():
    """Zero motion: the second frame's accumulated input is the mean of the two (n = 2, a = 1/2), the history
    clamped to the frame's 3x3 range; the frame count goes 1, 2, ...; a pixel whose history is off screen or
    fails the depth test starts again (a = 1, its error the frame's own variance)."""
    shape = (6, 8, 3)
    first = np.full(shape, 1.0, np.float32)
    second = np.full(shape, 2.0, np.float32)
    second[:, :3] = 0.5  # a step from 0.5 to 2 over a column of 0.9: the history (1) clamped to the 3x3 range
    second[:, 3] = 0.9
    motion = np.zeros(shape[:2] + (2,), np.float32)
    depth = np.ones(shape[:2] + (1,), np.float32)
    history = InputHistory()
    assert accumulate(history, first, first, None, first, first, motion, depth) is None
    later_depth = depth.copy()
    later_depth[0, 0] = 5.0  # another surface: no consistent tap
    halves = second - np.float32(0.2), second + np.float32(0.2)  # v = 0.04
    accumulated, error, floor = accumulate(history, second, second, None, *halves, motion, later_depth)
    # per column: clamp(1, 3x3 range) and the frame, averaged
    expected = np.array([0.5, 0.5, (0.9 + 0.5) / 2, (1 + 0.9) / 2, (1 + 2) / 2, 2, 2, 2])[None, :, None]
    expected = np.broadcast_to(expected, shape).copy()
    expected[0, 0] = second[0, 0]
    np.testing.assert_allclose(accumulated, expected, rtol=1e-6)
    np.testing.assert_allclose(history.buffer[..., 3], np.where(later_depth[..., 0] == 1.0, 2.0, 1.0))
    # the error of the unclamped average: (1/2)^2 ((h - c)^2 - v) + (1/2)^2 v = (h - c)^2 / 4
    unclamped = (1.0 - second) ** 2 / 4
    unclamped[0, 0] = 0.04
    np.testing.assert_allclose(error, unclamped.mean(axis=-1), rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(floor, np.where(later_depth[..., 0] == 1.0, 0.04 / 4, 0.04), rtol=1e-5)
    # a frame without motion starts the history again from itself
    assert accumulate(history, first, first, None, first, first, None, depth) is None
    np.testing.assert_array_equal(history.buffer[..., 3], 1.0)


def test_lights_are_left_out_of_the_clamp():
    """Beside a light whose colour less emission is 100 (its emission pass took other samples), the history (1)
    is clamped to the range of the frame's other pixels (0.5), not widened to the light's remainder."""
    shape = (5, 5, 3)
    first = np.ones(shape, np.float32)
    second = np.full(shape, 0.5, np.float32)
    emission = np.zeros(shape, np.float32)
    emission[2, 2] = 50.0
    color = second + emission
    color[2, 2] += 100.0
    clipped = color - emission
    motion = np.zeros((5, 5, 2), np.float32)
    for reference in (False, True):
        history = InputHistory()
        accumulate(history, first, first, None, first, first, motion, reference=reference)
        accumulated, _, _ = accumulate(history, clipped, color, emission, color, color, motion, reference=reference)
        np.testing.assert_allclose(accumulated[1, 1], 0.5)  # (clamp(1, [0.5, 0.5]) + 0.5) / 2


def test_the_error_estimate_is_unbiased(monkeypatch):
    """A constant truth under noise, 12 static frames: the estimate's mean matches the accumulated input's true
    squared error (the twin, with the clamp widened to the whole frame so that it does not act)."""
    monkeypatch.setattr(input_history, "CLAMP_RADIUS", 200)
    rng = np.random.default_rng(1)
    truth = np.full((64, 64, 3), 2.0, np.float32)
    motion = np.zeros((64, 64, 2), np.float32)
    history = InputHistory()
    for _ in range(12):
        a, b, color = _halves(rng, truth, 0.5)
        result = accumulate(history, color, color, None, a, b, motion, reference=True)
    accumulated, error, floor = result
    true = ((accumulated.astype(np.float64) - truth) ** 2).mean()
    assert true < 0.25 * (0.5**2 / 2)  # an average of ~9 frames' worth (a = 0.2) beats one frame's variance
    assert abs(error.mean() - true) < 0.1 * true, (error.mean(), true)
    assert floor.mean() < true  # a^2 v: a lower bound


@pytest.mark.parametrize("chance", [0.05, 0.3])
def test_the_estimate_holds_with_the_clamp_at_one_sample_per_half(chance):
    """A 0/1 signal (one sample per half hits light with probability `chance`), 12 static frames, the 3x3 clamp
    on: the estimate is within 25% of the accumulated input's true squared error (measured: 11% low at 0.05, 14%
    high at 0.3), and both are far below the frame's own."""
    rng = np.random.default_rng(0)
    motion = np.zeros((64, 64, 2), np.float32)
    history = InputHistory()
    for _ in range(12):
        a, b = ((rng.random((64, 64, 1)) < chance).astype(np.float32).repeat(3, -1) for _ in range(2))
        color = ((a + b) / 2).astype(np.float32)
        result = accumulate(history, color, color, None, a, b, motion)
    accumulated, error, _ = result
    true = float(((accumulated - chance) ** 2).mean())
    assert abs(error.mean() - true) < 0.25 * true, (error.mean(), true)
    assert true < 0.2 * float(((color - chance) ** 2).mean())


def test_takes_accumulated_needs_two_standard_errors():
    count = 100.0
    rows = []
    for mean, sd in ((-1.0, 1.0), (-0.1, 1.0), (0.5, 0.1)):  # per-pixel d: mean and spread of a tile
        rows.append((mean * count, (sd * sd + mean * mean) * count, count))
    stats = np.array(rows, np.float64).T[:, None, :]
    # standard error sd / 10: -1 + 0.2 < 0 takes it; -0.1 + 0.2 > 0 does not; a positive mean never
    assert takes_accumulated(stats).tolist() == [[True, False, False]]


@pytest.mark.parametrize("tile", [16, 7, 1])
@pytest.mark.parametrize("shape", [(1, 1), (17, 33), (40, 29)])
def test_blend_with_history_matches_the_numpy_twin(shape, tile):
    histories = InputHistory(), InputHistory()
    rng = np.random.default_rng(2)
    for f in _sequence(shape, 5, seed=3):
        out = (f["truth"] * 0.9 + rng.normal(0, 0.02, f["truth"].shape) + f["emission"]).astype(np.float32)
        out[: shape[0] // 2] += 0.5  # a region the denoiser got wrong
        args = out, f["color"], f["a"], f["b"], f["emission"], tile
        layers = dict(motion=f["motion"], depth=f["depth"], normal=f["normal"])
        got = noise_blend(*args, history=histories[0], **layers)
        want = noise_blend_reference(*args, history=histories[1], **layers)
        np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-4)


def _tiles(errors):
    h, w = (s // TILE * TILE for s in errors.shape)
    return errors[:h, :w].reshape(h // TILE, TILE, w // TILE, TILE).mean(axis=(1, 3))


def test_a_biased_output_takes_the_accumulated_input_back():
    """A static noisy scene and a denoiser 10% too dark: after 8 frames the blend with the history is better
    than the blend with the frame alone in every tile, and far better overall."""
    rng = np.random.default_rng(4)
    y, x = np.mgrid[:64, :64]
    truth = (0.3 + (np.sin(x / 5.0) * np.cos(y / 7.0)) ** 2)[..., None].repeat(3, -1).astype(np.float32)
    motion = np.zeros((64, 64, 2), np.float32)
    history = InputHistory()
    for _ in range(8):
        a, b, color = _halves(rng, truth, 0.15)
        out = (truth * 0.9).astype(np.float32)
        with_history = noise_blend(out, color, a, b, history=history, motion=motion)
        plain = noise_blend(out, color, a, b)
    better, alone = (rel_l2_map(v, truth) for v in (with_history, plain))
    assert (_tiles(better) < _tiles(alone)).all()
    assert better.mean() < 0.6 * alone.mean(), (better.mean(), alone.mean())


def test_a_stale_history_is_not_taken_and_no_motion_forgets_it():
    """Five frames of one level, then the light changes (every pixel x3): the history is worse than the frame, and
    the blend is the plain one (the tile sums' average forgotten before that frame, so that only the accumulated
    input can make a difference). A frame without motion starts the history again."""
    rng = np.random.default_rng(5)
    truth = np.full((32, 48, 3), 0.5, np.float32)
    motion = np.zeros((32, 48, 2), np.float32)
    history = InputHistory()
    for k in range(6):
        level = truth * (3.0 if k == 5 else 1.0)
        a, b, color = _halves(rng, level, 0.1)
        out = (level * 0.8).astype(np.float32)
        if k == 5:
            history.tile_sums = None
        blended = noise_blend(out, color, a, b, history=history, motion=motion)
    np.testing.assert_array_equal(blended, noise_blend(out, color, a, b))
    assert history.buffer[..., 3].max() == 6.0
    noise_blend(out, color, a, b, history=history)
    assert history.buffer[..., 3].max() == 1.0


def test_remembered_sums_average_while_the_history_continues():
    """TILE_MEMORY of the previous frames' sums, the rest this frame's; a (half) tile whose halves all agree in this
    frame (row 2, its noisy pixels, 0), a restart or another size takes this frame's alone; without a history the
    sums are returned as given; `clear` forgets them."""
    history = InputHistory()
    ones_fine, ones = np.ones((4, 4, 6)), np.ones((4, 2, 3))

    def quiet(x):  # sums of 0 but for the noisy pixels' count
        z = np.zeros_like(x)
        z[2] = 1.0
        return z

    fine, coarse = remembered_sums(history, ones_fine, ones, continued=True)  # nothing before: this frame's
    assert fine is ones_fine and coarse is ones
    fine, coarse = remembered_sums(history, quiet(ones_fine), quiet(ones), continued=True)
    np.testing.assert_allclose(fine[[0, 1, 3]], TILE_MEMORY)
    np.testing.assert_allclose(coarse[[0, 1, 3]], TILE_MEMORY)
    fine, coarse = remembered_sums(history, quiet(ones_fine), quiet(ones), continued=True)
    np.testing.assert_allclose(coarse[0], TILE_MEMORY**2)
    exact = np.ones_like(ones_fine)
    exact[2, 0, 0] = 0.0  # a half tile none of whose pixels has halves that differ: this frame's sums alone
    fine, _ = remembered_sums(history, exact, ones, continued=True)
    assert fine[0, 0, 0] == 1.0 and fine[0, 0, 1] == pytest.approx(TILE_MEMORY**3 + 1 - TILE_MEMORY)
    fine, _ = remembered_sums(history, ones_fine, ones, continued=False)
    np.testing.assert_array_equal(fine, ones_fine)
    fine, _ = remembered_sums(history, quiet(np.ones((4, 5, 6))), quiet(np.ones((4, 3, 3))), continued=True)
    np.testing.assert_array_equal(fine[0], 0.0)  # another size
    assert remembered_sums(None, ones_fine, ones, continued=True)[0] is ones_fine
    history.clear()
    assert history.half_tile_sums is None and history.tile_sums is None


def test_the_tile_memory_steadies_a_temporal_blend(monkeypatch):
    """A static noisy scene whose output is 30% too bright in one corner: the blend's weights there move with each
    frame's noise. Averaged over the frames they move less: the blended output changes less from frame to frame
    (and its error is no higher)."""
    y, x = np.mgrid[:64, :64]
    truth = (0.4 + 0.3 * np.sin(x / 6.0) * np.cos(y / 9.0))[..., None].repeat(3, -1).astype(np.float32)
    out = truth.copy()
    out[:24, :24] *= 1.3
    motion = np.zeros((64, 64, 2), np.float32)

    def run(memory):
        monkeypatch.setattr(noise_blend_module, "TILE_MEMORY", memory)
        rng, history, outputs = np.random.default_rng(8), InputHistory(), []
        for _ in range(12):
            a, b, color = _halves(rng, truth, 0.25)
            outputs.append(noise_blend(out, color, a, b, history=history, motion=motion).astype(np.float64))
        flicker = np.mean([((u - v) ** 2).mean() for u, v in zip(outputs[4:], outputs[5:], strict=False)])
        error = np.mean([rel_l2_map(o.astype(np.float32), truth).mean() for o in outputs[4:]])
        return flicker, error

    (flicker, error), (flicker_alone, error_alone) = run(TILE_MEMORY), run(0.0)
    assert flicker < 0.9 * flicker_alone, (flicker, flicker_alone)
    assert error <= 1.02 * error_alone, (error, error_alone)


def test_a_frame_whose_halves_agree_comes_back_as_it_came_after_a_history():
    """Noisy frames, then one whose halves agree everywhere (its input is exact): the blend returns its input, the
    tile sums of the frames before notwithstanding."""
    rng = np.random.default_rng(9)
    truth = np.full((32, 32, 3), 0.5, np.float32)
    motion = np.zeros((32, 32, 2), np.float32)
    history = InputHistory()
    out = (truth * 0.8).astype(np.float32)
    for _ in range(3):
        a, b, color = _halves(rng, truth, 0.1)
        noise_blend(out, color, a, b, history=history, motion=motion)
    assert history.tile_sums is not None
    np.testing.assert_array_equal(noise_blend(out, truth, truth, truth, history=history, motion=motion), truth)
