"""4x4 affine transforms as numpy float64 arrays, in Mitsuba's conventions (column vectors, p' = M @ p).

Scene descriptions and the motion-vector code use these, so neither needs mitsuba; the renderer hands
the same matrices to Mitsuba (`mi.ScalarTransform4f(matrix)`).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

Vec3 = Sequence[float] | np.ndarray


def identity() -> np.ndarray:
    """(4, 4) float64 identity."""
    return np.eye(4)


def translate(offset: Vec3) -> np.ndarray:
    """(4, 4) translation by `offset` (3,), scene units."""
    m = np.eye(4)
    m[:3, 3] = offset
    return m


def scale(factor: float | Vec3) -> np.ndarray:
    """(4, 4) scale by a scalar or per-axis (3,) factor."""
    return np.diag([*np.broadcast_to(np.asarray(factor, np.float64), (3,)), 1.0])


def rotate(axis: Vec3, degrees: float) -> np.ndarray:
    """(4, 4) rotation by `degrees` about `axis` (3,), right-handed (Rodrigues), as Mitsuba's rotate()."""
    a = np.asarray(axis, np.float64)
    a = a / np.linalg.norm(a)
    theta = np.radians(degrees)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    m = np.eye(4)
    m[:3, :3] = np.eye(3) + np.sin(theta) * k + (1 - np.cos(theta)) * (k @ k)
    return m


def look_at(origin: Vec3, target: Vec3, up: Vec3) -> np.ndarray:
    """(4, 4) camera-to-world matrix of Mitsuba's look_at: camera +z looks at `target`, +y is up and +x
    points to the left of the image (Mitsuba's camera space is left-handed in image terms)."""
    origin = np.asarray(origin, np.float64)
    direction = np.asarray(target, np.float64) - origin
    direction /= np.linalg.norm(direction)
    left = np.cross(np.asarray(up, np.float64), direction)
    left /= np.linalg.norm(left)
    new_up = np.cross(direction, left)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = left, new_up, direction, origin
    return m


def apply(matrix: np.ndarray, points: np.ndarray, *, w: float = 1.0) -> np.ndarray:
    """Transform points (w=1) or directions (w=0): matrix (4, 4), points (..., 3). Returns (..., 3) float64.

    For w=1 the result is divided by its homogeneous coordinate (affine matrices leave it at 1)."""
    p = np.asarray(points, np.float64)
    out = p @ matrix[:3, :3].T + w * matrix[:3, 3]
    if w:
        h = p @ matrix[3, :3] + matrix[3, 3]
        out = out / h[..., None]
    return out
