"""Pinhole camera of a frame: Mitsuba's `perspective` sensor as matrices, projection to pixels and back.

Pixel coordinates follow FRAME_FORMAT.md: x grows to the right, y grows downwards, the centre of
pixel (column i, row j) is (i + 0.5, j + 0.5). Camera space is Mitsuba's: +z looks forward, +y is up,
+x points to the left of the image. `projection` maps camera space to pixels:
(x_pix, y_pix) = (P @ p)[:2] / (P @ p)[3] and (P @ p)[2] / (P @ p)[3] = 1 / z, for p = (x, y, z, 1).
This is Mitsuba's `perspective_projection` (sensor.h) with the sample-space [0, 1]^2 scaled to pixels.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from models.data import transforms


@dataclass(frozen=True)
class Camera:
    """One frame's pinhole camera."""

    origin: tuple[float, float, float]  # eye position, world units
    target: tuple[float, float, float]  # point looked at, world units
    up: tuple[float, float, float]  # approximate up direction
    fov_x: float  # horizontal field of view, degrees (Mitsuba `fov` with fov_axis = "x")

    def camera_to_world(self) -> np.ndarray:
        """(4, 4) float64, Mitsuba look_at."""
        return transforms.look_at(self.origin, self.target, self.up)

    def world_to_camera(self) -> np.ndarray:
        """(4, 4) float64 inverse of `camera_to_world`."""
        return np.linalg.inv(self.camera_to_world())

    def projection(self, width: int, height: int) -> np.ndarray:
        """(4, 4) float64 camera space -> pixels (see module docstring) for a `width` x `height` film."""
        cot = 1.0 / np.tan(np.radians(self.fov_x) / 2.0)
        aspect = width / height
        return np.array(
            [
                [-0.5 * width * cot, 0.0, 0.5 * width, 0.0],
                [0.0, -0.5 * height * aspect * cot, 0.5 * height, 0.0],
                [0.0, 0.0, 0.0, 1.0],
                [0.0, 0.0, 1.0, 0.0],
            ]
        )

    def world_to_pixel(self, width: int, height: int) -> np.ndarray:
        """(4, 4) float64 projection @ world_to_camera."""
        return self.projection(width, height) @ self.world_to_camera()


def pixel_centres(height: int, width: int) -> np.ndarray:
    """(H, W, 2) float64 pixel-centre coordinates (x, y) = (i + 0.5, j + 0.5)."""
    y, x = np.mgrid[0:height, 0:width].astype(np.float64) + 0.5
    return np.stack([x, y], axis=-1)


def project_points(world_to_pixel: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Project world points (..., 3) with a (4, 4) `world_to_pixel`.

    Returns (pixels (..., 2) float64, in_front (...) bool: the point lies in front of the camera)."""
    p = np.asarray(points, np.float64)
    h = p @ world_to_pixel[:, :3].T + world_to_pixel[:, 3]
    w = h[..., 3]
    in_front = w > 1e-9
    safe = np.where(in_front, w, 1.0)
    return h[..., :2] / safe[..., None], in_front


def project_directions(world_to_pixel: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Project world directions (..., 3) (points at infinity, e.g. the environment) to pixels.

    Returns (pixels (..., 2) float64, in_front (...) bool)."""
    d = np.asarray(directions, np.float64)
    h = d @ world_to_pixel[:, :3].T
    w = h[..., 3]
    in_front = w > 1e-12
    safe = np.where(in_front, w, 1.0)
    return h[..., :2] / safe[..., None], in_front


def pixel_directions(camera: Camera, height: int, width: int) -> np.ndarray:
    """(H, W, 3) float64 unit world directions of the rays through the pixel centres."""
    inverse = np.linalg.inv(camera.projection(width, height))
    xy = pixel_centres(height, width)
    # A camera-space point on the ray: pixel (x, y) with w = z = 1 -> P^-1 (x, y, 1, 1).
    h = np.concatenate([xy, np.ones_like(xy)], axis=-1) @ inverse.T
    local = h[..., :3] / h[..., 3:4]
    world = transforms.apply(camera.camera_to_world(), local, w=0.0)
    return world / np.linalg.norm(world, axis=-1, keepdims=True)
