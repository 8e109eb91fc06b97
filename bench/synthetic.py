"""A small analytic sequence with every layer of the frame format, for tests and the stability suite.

The scene: a textured floor seen from a static camera, a diffuse sphere moving right by `speed` pixels
per frame, its soft shadow on the floor (visible in radiance only, no G-buffer shows it) and a small
emitter in a corner (in `emission`). Each of the `spp` samples is the reference times a log-normal
factor of mean 1 (heavy right tail: fireflies), so `color` is unbiased and `colorA`/`colorB` are the
means of disjoint halves. Motion vectors are exact; `motionDual` differs from `motion` only on
background uncovered since the previous frame, where it carries the sphere's motion (Zeng sec. 3.2).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from service.exr import write_frame
from service.stages.sample_statistics import statistics_from_samples

LIGHT_DIR = np.array([0.5, 0.75, 0.45], np.float32) / np.linalg.norm([0.5, 0.75, 0.45])
NOISE_SIGMA = 1.1  # log-normal sigma of the per-sample factor; variance of one sample = e^(s^2) - 1
EMITTER_RADIANCE = 8.0  # linear radiance of the corner emitter


def _sphere(height: int, width: int, t: int, speed: float) -> tuple[float, float, float]:
    """(centre x, centre y, radius) in pixels of the sphere at frame t."""
    radius = 0.22 * min(height, width)
    return 0.3 * width + speed * t, 0.45 * height, radius


def lognormal_samples(radiance: np.ndarray, emission: np.ndarray, spp: int, rng: np.random.Generator) -> np.ndarray:
    """(spp, H, W, 3) float32 samples: `radiance` times a log-normal factor of mean 1 per sample and pixel
    (sigma NOISE_SIGMA), plus the noise-free `emission`; both (H, W, 3) float32 linear radiance."""
    factors = rng.lognormal(-0.5 * NOISE_SIGMA**2, NOISE_SIGMA, (spp, *radiance.shape[:2], 1)).astype(np.float32)
    return radiance[None] * factors + emission[None]


def synthetic_frame(
    height: int, width: int, t: int, *, spp: int = 8, speed: float = 3.0, rng: np.random.Generator
) -> dict[str, np.ndarray]:
    """Layers of frame t: every frame-format layer as float32 (H, W, C) arrays, incl. `reference`."""
    y, x = np.mgrid[0:height, 0:width].astype(np.float32) + 0.5
    cx, cy, radius = _sphere(height, width, t, speed)
    px, _, _ = _sphere(height, width, t - 1, speed)
    checker = ((x // 8 + y // 8) % 2).astype(np.float32)
    albedo = np.stack([0.25 + 0.5 * checker, 0.3 + 0.3 * checker, 0.6 - 0.3 * checker], axis=-1)
    normal = np.broadcast_to(np.array([0.0, 1.0, 0.0], np.float32), (height, width, 3)).copy()
    depth = (2.0 + 8.0 * (1.0 - y / height))[..., None]
    r2 = ((x - cx) ** 2 + (y - cy) ** 2) / radius**2
    on_sphere = r2 < 1.0
    nz = np.sqrt(np.clip(1.0 - r2, 0.0, 1.0))
    sphere_normal = np.stack([(x - cx) / radius, -(y - cy) / radius, nz], axis=-1)
    normal[on_sphere] = sphere_normal[on_sphere]
    albedo[on_sphere] = np.array([0.7, 0.2, 0.15], np.float32)
    depth[on_sphere, 0] = 4.0 - nz[on_sphere]
    # Soft shadow: an ellipse below-right of the sphere, smooth edge; only radiance shows it.
    sx, sy = cx + 0.5 * radius, cy + 1.1 * radius
    s2 = ((x - sx) / (1.3 * radius)) ** 2 + ((y - sy) / (0.5 * radius)) ** 2
    visibility = np.clip((s2 - 0.6) / 0.8, 0.0, 1.0)
    visibility[on_sphere] = 1.0
    shading = np.maximum(normal @ LIGHT_DIR, 0.0) * visibility + 0.15
    radiance = (albedo * shading[..., None] * 2.0).astype(np.float32)
    emission = np.zeros((height, width, 3), np.float32)
    emitter = (x > width - 0.15 * width) & (y < 0.15 * height)
    emission[emitter] = EMITTER_RADIANCE
    albedo[emitter] = 0.0
    radiance[emitter] = 0.0
    samples = lognormal_samples(radiance, emission, spp, rng)
    half = spp // 2
    motion = np.zeros((height, width, 2), np.float32)
    motion[on_sphere, 0] = -speed
    was_sphere = ((x - px) ** 2 + (y - cy) ** 2) < radius**2
    motion_dual = motion.copy()
    motion_dual[was_sphere & ~on_sphere, 0] = -speed
    layers = {
        "color": samples.mean(axis=0),
        "colorA": samples[:half].mean(axis=0),
        "colorB": samples[half:].mean(axis=0),
        "albedo": albedo,
        "normal": normal,
        "depth": depth,
        "motion": motion,
        "motionDual": motion_dual,
        "roughness": np.where(on_sphere, 0.2, 0.6)[..., None],
        "ao": np.ones((height, width, 1)),
        "emission": emission,
        "reference": radiance + emission,
        **statistics_from_samples(samples),
    }
    return {name: np.asarray(value, np.float32) for name, value in layers.items()}


def synthetic_sequence(
    height: int = 64, width: int = 96, frames: int = 4, *, spp: int = 8, seed: int = 0
) -> list[dict[str, np.ndarray]]:
    """`frames` consecutive frames of the scene (see module docstring), deterministic in `seed`."""
    if spp < 2:
        raise ValueError(f"spp must be >= 2 (two half buffers), got {spp}")
    rng = np.random.default_rng(seed)
    return [synthetic_frame(height, width, t, spp=spp, rng=rng) for t in range(frames)]


def write_synthetic_sequence(out: str | Path, **kwargs: int) -> list[Path]:
    """Write `synthetic_sequence(**kwargs)` as `out/frame_NNNN.exr` plus `sequence.json`."""
    out = Path(out)
    frames = synthetic_sequence(**kwargs)
    paths = []
    for t, layers in enumerate(frames):
        path = out / f"frame_{t:04d}.exr"
        write_frame(path, layers)
        paths.append(path)
    (out / "sequence.json").write_text(json.dumps({"source": "bench.synthetic", **kwargs}, indent=2))
    return paths
