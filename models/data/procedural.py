"""Procedural textures, environment maps and meshes as numpy arrays, for the scene library.

Textures are (h, w, 3) float32 linear RGB; meshes are `description.Mesh` (object space, unit size).
Everything is deterministic in its arguments (a seed where randomness is involved).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from models.data.description import Mesh

RGB = Sequence[float]


def checker(size: int, cells: int, a: RGB, b: RGB) -> np.ndarray:
    """(size, size, 3) float32 checkerboard of `cells` x `cells` squares of colours `a` and `b`."""
    idx = (np.arange(size) * cells // size)[:, None] + (np.arange(size) * cells // size)[None, :]
    odd = (idx % 2).astype(np.float32)[..., None]
    return (np.asarray(a, np.float32) * (1 - odd) + np.asarray(b, np.float32) * odd).astype(np.float32)


def stripes(size: int, count: int, a: RGB, b: RGB, angle_deg: float = 0.0) -> np.ndarray:
    """(size, size, 3) float32 hard-edged stripes, `count` periods across, rotated by `angle_deg`."""
    y, x = np.mgrid[0:size, 0:size].astype(np.float32) / size
    t = np.radians(angle_deg)
    phase = (x * np.cos(t) + y * np.sin(t)) * count
    odd = ((np.floor(phase) % 2) == 1).astype(np.float32)[..., None]
    return (np.asarray(a, np.float32) * (1 - odd) + np.asarray(b, np.float32) * odd).astype(np.float32)


def value_noise(size: int, octaves: int, seed: int, low: RGB, high: RGB) -> np.ndarray:
    """(size, size, 3) float32 multi-octave value noise (finest octave at 1 texel) blended from `low` to
    `high`: a high-frequency, aperiodic texture."""
    rng = np.random.default_rng(seed)
    total = np.zeros((size, size), np.float32)
    weight = 0.0
    for octave in range(octaves):
        cells = max(2, size >> octave)
        grid = rng.random((cells, cells)).astype(np.float32)
        reps = int(np.ceil(size / cells))
        layer = np.kron(grid, np.ones((reps, reps), np.float32))[:size, :size]
        amplitude = 0.5**octave
        total += amplitude * layer
        weight += amplitude
    t = (total / weight)[..., None]
    return (np.asarray(low, np.float32) * (1 - t) + np.asarray(high, np.float32) * t).astype(np.float32)


def sky(height: int, sun_elevation_deg: float, sun_azimuth_deg: float, *, sun_radiance: float,
        sun_size_deg: float = 2.0, zenith: RGB = (0.25, 0.45, 0.9), horizon: RGB = (0.9, 0.9, 1.0),
        ground: RGB = (0.25, 0.2, 0.15)) -> np.ndarray:
    """(height, 2 * height, 3) float32 HDR environment map (Mitsuba `envmap` lat-long layout: row 0 is the
    zenith, +y up): a sky gradient, a dim ground and a disc sun of `sun_radiance` (linear radiance)."""
    width = 2 * height
    v = (np.arange(height, dtype=np.float32) + 0.5) / height
    u = (np.arange(width, dtype=np.float32) + 0.5) / width
    theta = v[:, None] * np.pi  # from +y
    phi = u[None, :] * 2 * np.pi
    elevation = np.pi / 2 - theta
    t = np.clip(elevation / (np.pi / 2), 0, 1)[..., None] ** 0.5
    img = np.asarray(horizon, np.float32) * (1 - t) + np.asarray(zenith, np.float32) * t
    img = np.where((elevation < 0)[..., None], np.asarray(ground, np.float32), img)
    img = np.broadcast_to(img, (height, width, 3)).copy()
    direction = _envmap_direction(theta + 0 * phi, phi + 0 * theta)
    sun = _envmap_direction(np.float32(np.pi / 2 - np.radians(sun_elevation_deg)),
                            np.float32(np.radians(sun_azimuth_deg)))
    cos_angle = direction @ sun
    img[cos_angle > np.cos(np.radians(sun_size_deg / 2))] = sun_radiance
    return img.astype(np.float32)


def _envmap_direction(theta: np.ndarray, phi: np.ndarray) -> np.ndarray:
    """Unit directions (..., 3) for polar angle theta from +y and azimuth phi (Mitsuba envmap mapping)."""
    s = np.sin(theta)
    return np.stack([s * np.sin(phi), np.cos(theta), -s * np.cos(phi)], axis=-1).astype(np.float32)


def torus(major: float, minor: float, segments: int = 48, sides: int = 24) -> Mesh:
    """Torus around the y axis, centred at the origin, with uvs; `major`/`minor` radii in object units."""
    u = np.linspace(0, 2 * np.pi, segments, endpoint=False)
    v = np.linspace(0, 2 * np.pi, sides, endpoint=False)
    uu, vv = np.meshgrid(u, v, indexing="ij")
    r = major + minor * np.cos(vv)
    verts = np.stack([r * np.cos(uu), minor * np.sin(vv), r * np.sin(uu)], axis=-1).reshape(-1, 3)
    uvs = np.stack([uu / (2 * np.pi), vv / (2 * np.pi)], axis=-1).reshape(-1, 2)
    i, j = np.meshgrid(np.arange(segments), np.arange(sides), indexing="ij")
    a = i * sides + j
    b = ((i + 1) % segments) * sides + j
    c = ((i + 1) % segments) * sides + (j + 1) % sides
    d = i * sides + (j + 1) % sides
    faces = np.concatenate([np.stack([a, d, c], -1).reshape(-1, 3), np.stack([a, c, b], -1).reshape(-1, 3)])
    return Mesh(verts.astype(np.float32), faces.astype(np.uint32), uvs.astype(np.float32))


def box(lo: RGB, hi: RGB) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (24, 3) float32 and faces (12, 3) uint32 of an axis-aligned box, outward winding."""
    lo, hi = np.asarray(lo, np.float32), np.asarray(hi, np.float32)
    corners = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], np.float32)
    pts = lo + corners * (hi - lo)
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    verts, faces = [], []
    for q in quads:
        base = len(verts)
        verts.extend(pts[list(q)])
        faces += [(base, base + 1, base + 2), (base, base + 2, base + 3)]
    return np.asarray(verts, np.float32), np.asarray(faces, np.uint32)


def lattice(count: int, spacing: float, thickness: float, length: float, *, crossbars: int = 0) -> Mesh:
    """A fence: `count` thin vertical bars `thickness` wide and `length` tall, `spacing` apart, centred on
    the origin in the xy plane, plus `crossbars` thin horizontal bars; one mesh of boxes."""
    verts, faces = [], []
    half_w = 0.5 * (count - 1) * spacing

    def add(lo, hi):
        v, f = box(lo, hi)
        faces.append(f + sum(len(x) for x in verts))
        verts.append(v)

    h = thickness / 2
    for k in range(count):
        x = -half_w + k * spacing
        add((x - h, 0.0, -h), (x + h, length, h))
    for k in range(crossbars):
        y = length * (k + 1) / (crossbars + 1)
        add((-half_w - h, y - h, -h), (half_w + h, y + h, h))
    return Mesh(np.concatenate(verts), np.concatenate(faces).astype(np.uint32))
