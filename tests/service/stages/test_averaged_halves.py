"""Each half averaged over the frames as the cross-regression's features (service/stages/averaged_halves.py):
the average by hand, restarts, the pilots' independence from the half they are fitted to, a shadow the
G-buffers do not show kept sharper, and crossreg's use of it."""

import numpy as np
import pytest

from bench.synthetic import synthetic_sequence
from service import pipelines
from service.frame import Frame
from service.layout import CROSSREG_INPUTS, channel_slices
from service.pipelines.crossreg import REPROJECTION, prepare_frame
from service.stages.averaged_halves import PLANES, average_halves, averaged_pilots
from service.stages.cross_regression import cross_regression, pilots_to_radiance
from service.stages.input_history import ALPHA_MIN
from service.stages.reprojection import reproject


def _static(height=24, width=32):
    normal = np.zeros((height, width, 3), np.float32)
    normal[..., 2] = 1.0
    depth = np.ones((height, width, 1), np.float32)
    albedo = np.full((height, width, 3), 0.6, np.float32)
    return np.zeros((height, width, 2), np.float32), depth, normal, albedo


def test_the_average_by_hand_and_a_restart_where_the_surface_changes():
    """Zero motion: a plain mean of the first 1 / ALPHA_MIN frames, then the exponential average; a pixel whose
    depth jumps starts again from its frame."""
    motion, depth, normal, _ = _static(8, 8)
    rng = np.random.default_rng(0)
    frames = [(rng.random((8, 8, 3), dtype=np.float32), rng.random((8, 8, 3), dtype=np.float32)) for _ in range(7)]
    planes = None
    for k, (a, b) in enumerate(frames):
        planes = average_halves(a, b, planes, motion, depth=depth, prev_depth=depth, normal=normal,
                                prev_normal=normal)
        assert planes.shape == (PLANES, 8, 8) and planes.dtype == np.float32
        np.testing.assert_array_equal(planes[6], k + 1)
    want_a = np.mean([a for a, _ in frames[:5]], axis=0)
    for a, _ in frames[5:]:
        want_a = (1 - ALPHA_MIN) * want_a + ALPHA_MIN * a
    np.testing.assert_allclose(planes[0:3].transpose(1, 2, 0), want_a, rtol=1e-5)
    moved = depth.copy()
    moved[2, 3] = 5.0
    a, b = frames[0]
    again = average_halves(a, b, planes, motion, depth=moved, prev_depth=depth, normal=normal, prev_normal=normal)
    assert again[6, 2, 3] == 1.0 and again[6, 0, 0] == 8.0
    np.testing.assert_array_equal(again[3:6, 2, 3], b[2, 3])
    start = average_halves(a, b, None, motion)
    np.testing.assert_array_equal(start[0:3].transpose(1, 2, 0), a)
    assert (start[6] == 1.0).all()


def test_each_pilot_reads_its_own_half_only_through_the_average():
    """Pilot A's features and weights come from averaged A, its targets from this frame's B: with the average
    held fixed, a change of this frame's A moves pilot B only (A is its target), a change of B pilot A only."""
    rng = np.random.default_rng(1)
    motion, depth, normal, albedo = _static()
    a, b = (rng.random((24, 32, 3), dtype=np.float32) for _ in range(2))
    planes = average_halves(a, b, None, motion)
    planes = average_halves(a * 0.9, b * 1.1, planes, motion, depth=depth, prev_depth=depth, normal=normal,
                            prev_normal=normal)
    pilot_a, pilot_b = averaged_pilots(a, b, planes, albedo, normal)
    other_a, other_b = averaged_pilots(a * 1.5, b, planes, albedo, normal)
    np.testing.assert_array_equal(other_a, pilot_a)
    assert not np.array_equal(other_b, pilot_b)
    other_a, other_b = averaged_pilots(a, b * 1.5, planes, albedo, normal)
    np.testing.assert_array_equal(other_b, pilot_b)
    assert not np.array_equal(other_a, pilot_a)
    first = average_halves(a, b, None, motion)
    for got, want in zip(averaged_pilots(a, b, first, albedo, normal), cross_regression(a, b, albedo, normal),
                         strict=True):
        np.testing.assert_array_equal(got, want)  # a start: one plain cross-regression


def test_a_shadow_no_g_buffer_shows_stays_sharper():
    """A static frame lit 1.0 on the left and 0.1 on the right (albedo and normal flat), one noisy sample a pixel
    per half: after 8 frames the pilots from averaged halves are closer to the truth than this frame's, and
    most of the gain is at the shadow's edge."""
    motion, depth, normal, albedo = _static()
    truth = np.where(np.arange(32) < 16, 1.0, 0.1)[None, :, None].repeat(24, 0).repeat(3, 2).astype(np.float32)
    rng = np.random.default_rng(2)
    planes = None
    for _ in range(8):
        a, b = _noisy_halves(truth, rng)
        planes = average_halves(a, b, planes, motion, depth=depth, prev_depth=depth, normal=normal,
                                prev_normal=normal)
    averaged = pilots_to_radiance(*averaged_pilots(a, b, planes, albedo, normal))
    plain = pilots_to_radiance(*cross_regression(a, b, albedo, normal))

    def error(image, columns=slice(None)):
        return float((((image - truth) / (truth + 0.1)) ** 2)[:, columns].mean())

    assert error(averaged) < 0.5 * error(plain), (error(averaged), error(plain))
    assert error(averaged, slice(12, 20)) < 0.5 * error(plain, slice(12, 20))


def _noisy_halves(truth, rng):
    """Two (H, W, 3) float32 halves of one exponentially distributed sample a pixel around `truth`."""
    return tuple((truth * rng.exponential(1.0, truth.shape[:2])[..., None]).astype(np.float32) for _ in range(2))


def test_the_average_starts_again_where_a_shadow_moved_in_and_not_at_a_firefly():
    """A floor lit 1.0 for 6 frames; then a shadow (0.05) covers columns 8-23, and half A of a lit pixel
    holds a firefly of 1000. The shadow's pixels start again from the frame (the history's lit floor would make
    features of 1 where the light is 0.05), so the pilots there are near the shadow's value; the firefly's pixel
    and the lit floor keep averaging."""
    motion, depth, normal, albedo = _static()
    lit = np.ones((24, 32, 3), np.float32)
    rng = np.random.default_rng(4)
    planes = None
    for _ in range(6):
        planes = average_halves(*_noisy_halves(lit, rng), planes, motion, depth=depth, prev_depth=depth,
                                normal=normal, prev_normal=normal)
    before = planes[6].copy()
    shadowed = lit.copy()
    shadowed[:, 8:24] = 0.05
    a, b = _noisy_halves(shadowed, rng)
    a[12, 4] = 1000.0
    planes = average_halves(a, b, planes, motion, depth=depth, prev_depth=depth, normal=normal, prev_normal=normal)
    inside = planes[6, 2:-2, 10:22]  # the shadow less the 3x3 window's reach over its edge (and the eroded border)
    assert (inside == 1.0).mean() > 0.95, (inside == 1.0).mean()
    assert planes[6, 12, 4] == before[12, 4] + 1.0
    kept = planes[6, 2:-2, 2:6] == before[2:-2, 2:6] + 1.0
    assert kept.mean() > 0.9, kept.mean()
    pilots = pilots_to_radiance(*averaged_pilots(a, b, planes, albedo, normal))
    assert np.median(pilots[2:-2, 10:22]) < 0.1, np.median(pilots[2:-2, 10:22])


def test_a_pixel_beside_a_failed_reprojection_keeps_averaging():
    """A noise-free lit floor whose depth jumps in a cross: the cross starts again, and the valid pixels around
    it keep averaging, those in its inner corners too (5 of their 9 neighbours failed: had the failed history's
    zeros entered their 3x3 means, those would have fallen to 4/9 of the frame's, a change)."""
    motion, depth, normal, _ = _static(16, 16)
    lit = np.ones((16, 16, 3), np.float32)
    planes = None
    for _ in range(3):
        planes = average_halves(lit, lit, planes, motion, depth=depth, prev_depth=depth, normal=normal,
                                prev_normal=normal, params=REPROJECTION)
    moved = depth.copy()
    moved[8:10, 2:14] = moved[2:14, 8:10] = 5.0
    planes = average_halves(lit, lit, planes, motion, depth=moved, prev_depth=depth, normal=normal,
                            prev_normal=normal, params=REPROJECTION)
    _, valid = reproject(planes.transpose(1, 2, 0), motion, depth=moved, prev_depth=depth, normal=normal,
                         prev_normal=normal, params=REPROJECTION)
    assert (planes[6][~valid] == 1.0).all() and (~valid).any()
    np.testing.assert_array_equal(planes[6][valid], 4.0)


@pytest.mark.parametrize("average", [True, False])
def test_crossreg_keeps_the_average_in_its_history_only_with_the_option(average):
    motion, depth, normal, albedo = _static(13, 17)
    rng = np.random.default_rng(3)
    pipeline = pipelines.get("crossreg", average_halves=average)
    state = pipeline.start(13, 17)
    for _ in range(3):
        a, b = (rng.random((13, 17, 3), dtype=np.float32) for _ in range(2))
        frame = Frame.from_buffers(dict(color=(a + b) / 2, colorA=a, colorB=b, albedo=albedo, normal=normal,
                                        depth=depth, motion=motion))
        _, state = pipeline.step(frame, state)
    if average:
        assert state.history.halves.shape == (PLANES, 13, 17)
        assert state.history.halves[6, 6, 8] == 3.0  # a pixel inside the eroded mask: every frame
    else:
        assert state.history.halves is None
    with pytest.raises(ValueError, match="average_halves"):
        pipelines.get("crossreg", average_halves="often")


def test_prepare_frame_averages_with_the_previous_frame_reprojected():
    """On a moving synthetic sequence, `prepare_frame(average=True)`'s pilots are `averaged_pilots` of the halves
    averaged with the previous frame's, reprojected by this frame's motion against the previous frame's depth and
    normal; the pipeline's state carries them, and with the option off the pilots are the paper's."""
    frames = [Frame.from_buffers(x) for x in synthetic_sequence(20, 28, 3, spp=4, seed=7)]
    assert np.abs(frames[1]["motion"]).max() > 0.5
    pipeline = pipelines.get("crossreg")
    state = pipeline.start(20, 28)
    _, state = pipeline.step(frames[0], state)
    history, frame = state.history, frames[1]
    assert history.halves is not None
    prepared = prepare_frame(frame, history, average=True)
    want_halves = average_halves(frame["colorA"], frame["colorB"], history.halves, frame["motion"],
                                 depth=frame["depth"], prev_depth=history.depth, normal=frame["normal"],
                                 prev_normal=history.normal, params=REPROJECTION)
    np.testing.assert_array_equal(prepared.halves, want_halves)
    assert (want_halves[6] == 2.0).any() and (want_halves[6] == 1.0).any()  # reprojected, and restarted
    s = channel_slices(CROSSREG_INPUTS)
    pilot_a, pilot_b = averaged_pilots(frame["colorA"], frame["colorB"], want_halves, frame["albedo"], frame["normal"])
    np.testing.assert_array_equal(prepared.planes[s["pilotA"]], pilot_a)
    np.testing.assert_array_equal(prepared.planes[s["pilotB"]], pilot_b)
    paper = prepare_frame(frame, history)
    plain = cross_regression(frame["colorA"], frame["colorB"], frame["albedo"], frame["normal"])
    np.testing.assert_array_equal(paper.planes[s["pilotA"]], plain[0])
    assert not np.array_equal(paper.planes[s["pilotA"]], pilot_a)
