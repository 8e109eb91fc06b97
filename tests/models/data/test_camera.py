"""Camera matrices and transforms agree with Mitsuba and invert each other."""

import numpy as np
import pytest

from models.data import transforms as T
from models.data.camera import Camera, pixel_centres, pixel_directions, project_directions, project_points

CAM = Camera((0.3, 1.2, 3.0), (0.0, 0.5, 0.0), (0.0, 1.0, 0.0), 45.0)


def test_pixel_directions_project_back_to_pixel_centres():
    h, w = 12, 20
    xy, front = project_directions(CAM.world_to_pixel(w, h), pixel_directions(CAM, h, w))
    assert front.all()
    np.testing.assert_allclose(xy, pixel_centres(h, w), atol=1e-9)


def test_points_on_the_optical_axis_land_in_the_image_centre_and_behind_is_flagged():
    h, w = 10, 16
    forward = np.asarray(CAM.target) - np.asarray(CAM.origin)
    xy, front = project_points(CAM.world_to_pixel(w, h), np.stack([CAM.origin + 2 * forward, CAM.origin - forward]))
    np.testing.assert_allclose(xy[0], [w / 2, h / 2], atol=1e-9)
    assert front.tolist() == [True, False]


def test_transforms_match_mitsuba():
    mi = pytest.importorskip("mitsuba")
    mi.set_variant("scalar_rgb")
    look = mi.ScalarTransform4f().look_at(origin=[1, 2, 3], target=[0, 0.5, 0], up=[0, 1, 0])
    np.testing.assert_allclose(np.array(look.matrix), T.look_at([1, 2, 3], [0, 0.5, 0], [0, 1, 0]), atol=1e-6)
    rot = mi.ScalarTransform4f().rotate([0, 1, 0], 33.0)
    np.testing.assert_allclose(np.array(rot.matrix), T.rotate([0, 1, 0], 33.0), atol=1e-6)
    m = T.translate([1, 2, 3]) @ T.rotate([1, 0, 0], -90) @ T.scale([2, 3, 4])
    np.testing.assert_allclose(T.apply(m, np.array([0.0, 0.0, 1.0])), [1, 6, 3], atol=1e-12)
