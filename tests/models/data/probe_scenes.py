"""Two small diffuse probe scenes for the motion-vector proofs: one moving camera, one moving object.

Smooth (sinusoidal) textures under a uniform sky: bilinear warping reproduces them well, while a
wrong motion vector shows up as a large error. Diffuse only, so radiance does not depend on the view.
"""

from __future__ import annotations

import numpy as np

from models.data import transforms as T
from models.data.camera import Camera
from models.data.description import SceneSpec, SceneState, Texture
from models.data.scenes import cube, diffuse, quad, rgb


def _waves(size: int, periods: float, phase: float) -> Texture:
    y, x = np.mgrid[0:size, 0:size].astype(np.float32) / size
    r = 0.5 + 0.4 * np.sin(2 * np.pi * periods * x + phase) * np.cos(2 * np.pi * periods * 0.7 * y)
    g = 0.5 + 0.4 * np.cos(2 * np.pi * periods * 0.8 * (x + y) + phase)
    return Texture(np.stack([r, g, 0.3 + 0.0 * r], axis=-1).astype(np.float32))


_WALL = _waves(128, 3.0, 0.0)
_BOX = _waves(64, 1.5, 1.0)
_SKY = ({"type": "constant", "radiance": rgb((1.0, 1.0, 1.0))},)


def _shapes(box_x: float, spin_deg: float):
    return (
        quad("wall", T.translate([0, 0, -1]) @ T.scale(2.5), diffuse(_WALL)),
        quad("floor", T.translate([0, -1, 0]) @ T.rotate([1, 0, 0], -90) @ T.scale(2.5), diffuse(_WALL)),
        cube("box", (box_x, -0.2, 0.3), 0.35, diffuse(_BOX), spin_deg=spin_deg),
    )


def _moving_camera(t: float, seed: int) -> SceneState:
    cam = Camera((0.3 * t - 0.1, 0.1 * t, 3.0 - 0.1 * t), (0.1 * t, 0.0, 0.0), (0, 1, 0), 50.0)
    return SceneState(cam, _shapes(0.0, 25.0), _SKY)


def _moving_object(t: float, seed: int) -> SceneState:
    cam = Camera((0.0, 0.0, 3.0), (0.0, 0.0, 0.0), (0, 1, 0), 50.0)
    # Unturned and left of the optical axis: translating it uncovers background but none of its own faces.
    return SceneState(cam, _shapes(-0.3 + 0.25 * t, 0.0), _SKY)


MOVING_CAMERA = SceneSpec("probe_camera", "camera translates and turns; static diffuse scene", _moving_camera,
                          max_depth=3)
MOVING_OBJECT = SceneSpec("probe_object", "a box translates in front of a static camera", _moving_object,
                          max_depth=3)
