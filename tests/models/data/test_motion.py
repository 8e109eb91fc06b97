"""Motion and dual motion vectors on analytic G-buffers (no renderer): planes seen by a pinhole camera."""

import numpy as np
import pytest

from models.data import transforms as T
from models.data.camera import Camera, pixel_directions
from models.data.motion import DEPTH_MISS, GBuffer, View, compute_motion, silhouette

H, W = 24, 40
FOV = 50.0


def _camera(x: float) -> Camera:
    return Camera((x, 0.0, 3.0), (x, 0.0, 0.0), (0.0, 1.0, 0.0), FOV)


def _frame(camera: Camera, card_x: float) -> tuple[GBuffer, View]:
    """Background plane z = -2 (shape 0) and a card in the plane z = 0, |x - card_x| < 0.4, |y| < 0.5 (shape 1)."""
    d = pixel_directions(camera, H, W)
    o = np.asarray(camera.origin)
    t_card = (0.0 - o[2]) / d[..., 2]
    p_card = o + t_card[..., None] * d
    on_card = (np.abs(p_card[..., 0] - card_x) < 0.4) & (np.abs(p_card[..., 1]) < 0.5)
    t_back = (-2.0 - o[2]) / d[..., 2]
    p_back = o + t_back[..., None] * d
    shape = np.where(on_card, 1, 0).astype(np.int32)
    position = np.where(on_card[..., None], p_card, p_back)
    depth = np.linalg.norm(position - o, axis=-1).astype(np.float32)
    transforms = np.stack([T.identity(), T.translate([card_x, 0.0, 0.0])])
    view = View(camera.world_to_pixel(W, H), o, d, transforms)
    return GBuffer(position, shape, depth), view


def _focal_px() -> float:
    return 0.5 * W / np.tan(np.radians(FOV) / 2)


def test_camera_translation_gives_uniform_parallax_per_depth():
    delta = 0.1
    prev = _frame(_camera(-delta), 0.0)
    cur = _frame(_camera(0.0), 0.0)
    m = compute_motion(*cur, *prev)
    card = cur[0].shape == 1
    # A world point seen now at x was seen delta * f / depth pixels further right by the camera on the left.
    np.testing.assert_allclose(m.motion[card, 0], delta * _focal_px() / 3.0, rtol=1e-6)
    np.testing.assert_allclose(m.motion[~card, 0], delta * _focal_px() / 5.0, rtol=1e-6)
    np.testing.assert_allclose(m.motion[..., 1], 0.0, atol=1e-6)


def test_moving_card_motion_and_dual_motion_by_hand():
    shift = 0.25  # card moves right by this many world units per frame, at depth 3
    prev = _frame(_camera(0.0), 0.0)
    cur = _frame(_camera(0.0), shift)
    m = compute_motion(*cur, *prev)
    v = shift * _focal_px() / 3.0  # card speed, pixels per frame
    card_now, card_before = cur[0].shape == 1, prev[0].shape == 1
    np.testing.assert_allclose(m.motion[card_now, 0], -v, rtol=1e-6)
    np.testing.assert_allclose(m.motion[~card_now], 0.0, atol=1e-6)
    uncovered = ~card_now & card_before  # background the card uncovered (static camera: same pixel)
    assert uncovered.sum() > 10
    np.testing.assert_array_equal(m.occluded, uncovered)
    # Zeng eq. 2 for a rigidly translating occluder: the background is fetched at x - v.
    np.testing.assert_allclose(m.dual[uncovered, 0], -v, rtol=1e-6)
    np.testing.assert_array_equal(m.dual[~uncovered], m.motion[~uncovered])


def test_environment_pixels_follow_the_camera_rotation_only():
    before = Camera((0.0, 0.0, 3.0), (0.0, 0.0, 0.0), (0.0, 1.0, 0.0), FOV)
    after = Camera((5.0, 0.0, 3.0), (5.2, 0.0, 0.0), (0.0, 1.0, 0.0), FOV)  # moved far and turned
    empty = GBuffer(np.zeros((H, W, 3)), np.full((H, W), -1, np.int32), np.full((H, W), DEPTH_MISS, np.float32))

    def view(cam):
        return View(cam.world_to_pixel(W, H), np.asarray(cam.origin), pixel_directions(cam, H, W), np.eye(4)[None])

    m = compute_motion(empty, view(after), empty, view(before))
    turn = np.degrees(np.arctan2(0.2, 3.0))
    centre = m.motion[H // 2, W // 2, 0]
    # The centre direction is turned by `turn` degrees: a shift of about f * tan(turn) pixels (to the right).
    assert abs(centre - _focal_px() * np.tan(np.radians(turn))) < 0.05
    assert not m.occluded.any()


def test_silhouette_marks_both_sides_of_a_shape_edge():
    shape = np.zeros((5, 6), np.int32)
    shape[:, 3:] = 1
    edge = silhouette(shape)
    assert edge[:, 2:4].all() and not edge[:, [0, 1, 4, 5]].any()


def test_warp_errors_by_hand():
    from models.data.evaluate import warp_errors

    prev = np.zeros((4, 8, 3), np.float32)
    prev[:, 4:] = 1.0  # right half bright
    ref = np.roll(prev, -1, axis=1)  # moved one pixel left
    ref[:, -1] = 1.0
    motion = np.zeros((4, 8, 2), np.float32)
    motion[..., 0] = 1.0  # exact backward motion
    dual = motion.copy()
    dual[:, 0, 0] = 0.0  # one column 'disoccluded'
    e = warp_errors(prev, ref, motion, dual, trim=0.0)
    assert e["motion"] == 0.0 and e["static"] > 0.0
    assert e["disoccluded_fraction"] == pytest.approx(4 / 32)
