"""Motion vectors and dual motion vectors from rendered positions and known camera/object motion.

Conventions (FRAME_FORMAT.md): motion is backward and in pixels; the surface seen at pixel centre x
in frame t was seen at x + motion(x) in frame t-1; x grows right, y grows down.

- `motion`: the world position of the surface at x (position AOV at the pixel centre) is carried
  back by its object's transform, p' = M_{t-1} M_t^-1 p, and projected with the previous camera.
  Pixels that see the environment carry their ray direction back through the camera rotation only.
- `motionDual` (Zheng et al. 2021, as Zeng et al. sec. 3.2, eq. 2): where the surface at x was
  occluded in frame t-1, the previous frame at y = x + motion(x) shows the occluder. That occluder
  point, moved forward by its own transform and projected with the current camera, lands at z; the
  occluded background is then fetched at y + (x - z), so motionDual(x) = y + (x - z) - x = y - z.
  The previous G-buffer is read at the pixel containing y, so y is taken at that pixel's centre,
  which makes the vector exact for a rigidly moving occluder. Elsewhere motionDual = motion.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from models.data.camera import pixel_centres, project_directions, project_points

# The renderer's depth for pixels that hit nothing, scene units: large, finite and exact in float16.
DEPTH_MISS = 1.0e4
# A surface counts as occluded in frame t-1 when the previous frame saw something this much closer
# (relative depth) than the surface's own reprojected depth. The depth of a sloped surface changes
# by well under 1% over half a pixel at the scene scales and resolutions used here (grazing angles
# above ~5 degrees at 256 px), so 3% separates occluders from resampling.
OCCLUSION_DEPTH_TOLERANCE = 0.03


@dataclass(frozen=True, eq=False)
class GBuffer:
    """Pixel-centre geometry of one frame (one unjittered sample per pixel)."""

    position: np.ndarray  # (H, W, 3) float64 world position of the first hit (undefined where shape < 0)
    shape: np.ndarray  # (H, W) int32 index into the frame's shape list, -1 where nothing was hit
    depth: np.ndarray  # (H, W) float32 camera-to-hit distance, scene units; DEPTH_MISS where nothing hit


@dataclass(frozen=True, eq=False)
class View:
    """What the scene knows about one frame's geometry."""

    world_to_pixel: np.ndarray  # (4, 4) float64 camera.projection @ world_to_camera
    origin: np.ndarray  # (3,) float64 camera position, world units
    directions: np.ndarray  # (H, W, 3) float64 unit world directions of the pixel-centre rays
    transforms: np.ndarray  # (K, 4, 4) float64 object-to-world of the K shapes


@dataclass(frozen=True, eq=False)
class Motion:
    """Both motion layers and the masks that explain them."""

    motion: np.ndarray  # (H, W, 2) float32 backward motion, pixels
    dual: np.ndarray  # (H, W, 2) float32 dual backward motion, pixels
    occluded: np.ndarray  # (H, W) bool: the surface was hidden in frame t-1 (dual differs there)
    valid: np.ndarray  # (H, W) bool: the surface was in front of the previous camera (motion defined)


def _carry(transforms_from: np.ndarray, transforms_to: np.ndarray, shape: np.ndarray,
           position: np.ndarray) -> np.ndarray:
    """Move hit points with their object: p' = M_to[s] M_from[s]^-1 p. Returns (H, W, 3) float64."""
    relative = transforms_to @ np.linalg.inv(transforms_from)  # (K, 4, 4)
    m = relative[np.maximum(shape, 0)]  # (H, W, 4, 4)
    return np.einsum("hwij,hwj->hwi", m[..., :3, :3], position) + m[..., :3, 3]


def compute_motion(current: GBuffer, view: View, previous: GBuffer, previous_view: View) -> Motion:
    """Motion and dual motion of frame t (`current`, `view`) against frame t-1 (see module docstring)."""
    height, width = current.shape.shape
    x = pixel_centres(height, width)
    hit = current.shape >= 0
    p_prev = _carry(view.transforms, previous_view.transforms, current.shape, current.position)
    y_hit, front_hit = project_points(previous_view.world_to_pixel, p_prev)
    y_env, front_env = project_directions(previous_view.world_to_pixel, view.directions)
    y = np.where(hit[..., None], y_hit, y_env)
    valid = np.where(hit, front_hit, front_env)
    motion = np.where(valid[..., None], y - x, 0.0)

    # Occlusion in frame t-1: look up what the previous frame saw at the pixel containing y.
    cell = np.floor(y).astype(np.int64)
    inside = valid & (cell[..., 0] >= 0) & (cell[..., 0] < width) & (cell[..., 1] >= 0) & (cell[..., 1] < height)
    cx = np.clip(cell[..., 0], 0, width - 1)
    cy = np.clip(cell[..., 1], 0, height - 1)
    seen_shape = previous.shape[cy, cx]
    seen_depth = previous.depth[cy, cx].astype(np.float64)
    expected = np.linalg.norm(p_prev - previous_view.origin, axis=-1)
    hidden_hit = hit & (seen_depth < expected * (1.0 - OCCLUSION_DEPTH_TOLERANCE))
    hidden_env = ~hit & (seen_shape >= 0)
    occluded = inside & (hidden_hit | hidden_env)

    # The occluder point at that pixel centre, moved forward with its own object, seen now at z.
    occluder_now = _carry(previous_view.transforms, view.transforms, seen_shape, previous.position[cy, cx])
    z, front_z = project_points(view.world_to_pixel, occluder_now)
    occluded &= front_z
    centre_prev = np.stack([cx, cy], axis=-1) + 0.5
    dual = np.where(occluded[..., None], centre_prev - z, motion)
    return Motion(motion.astype(np.float32), dual.astype(np.float32), occluded, valid)


def silhouette(shape: np.ndarray) -> np.ndarray:
    """(H, W) bool: pixels whose 3x3 neighbourhood sees more than one shape (or shape and background).

    shape: (H, W) int shape indices, -1 for background."""
    padded = np.pad(shape, 1, mode="edge")
    height, width = shape.shape
    edge = np.zeros(shape.shape, bool)
    for dy in range(3):
        for dx in range(3):
            edge |= padded[dy:dy + height, dx:dx + width] != shape
    return edge
