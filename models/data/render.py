"""Render one frame of a scene into every layer of the frame format with Mitsuba 3.

Passes per frame (all with a box pixel filter):
1. noise: `spp` independent 1-spp path-tracing passes (different seeds). Their mean is `color`, the
   means of the first and second half are `colorA`/`colorB`, and the per-sample Box-Cox statistics
   give `sampleCount`/`bcMean`/`bcM2`/`bcM3` (service.stages.sample_statistics).
2. emission: the path tracer at max_depth 1 (directly seen emitters and environment only), stratified
   within each call of `mean_of_calls`, `emission_spp` = 1024 samples, so that the layer is as noise-free
   as FRAME_FORMAT.md says. Where a small light covers part of a pixel, one stratum of 16 samples put 167
   (1/16 of the light's 2667) into a pixel whose reference held 1.5 (`fireflies`), and pipelines take the
   layer as exact.
3. reference: `ref_spp` samples of the same path tracer with directly seen emitters hidden, other seeds,
   in chunks, plus the emission layer: the reference's directly seen emission is the layer itself, not a
   second estimate whose sampling noise at the edges of small lights the benchmark would score.
4. G-buffer, anti-aliased: `albedo` and `normal` averaged over `gbuffer_spp` jittered samples (the
   normal renormalised; zero where no sample hit anything). The albedo comes from the scene with every
   BSDF replaced by a diffuse one of the shape's albedo (description.Shape.albedo), which keeps it in
   [0, 1] for glossy metals and anti-aliases textures.
5. G-buffer, pixel centre (one unjittered sample): position and shape index, and from them `depth`
   (camera-to-hit distance; DEPTH_MISS where nothing was hit). They give `roughness` (per shape, from the scene) and,
   with the previous frame's, `motion` and `motionDual` (models.data.motion).
6. `ao`: the mcd_ao integrator (models.data.integrators), `ao_spp` rays per pixel.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from types import ModuleType

import numpy as np

from models.data.camera import pixel_directions
from models.data.description import SceneSpec, SceneState
from models.data.integrators import AO_INTEGRATOR
from models.data.motion import DEPTH_MISS, GBuffer, View, compute_motion
from service.stages.sample_statistics import statistics_from_samples

# Samples per Mitsuba render call for the reference: bounds the JIT wavefront (pixels x spp) to ~4M lanes.
MAX_LANES_PER_CALL = 1 << 22


@dataclass(frozen=True)
class RenderOptions:
    """How a sequence is rendered."""

    width: int  # film width, pixels
    height: int  # film height, pixels
    spp: int  # samples per pixel of the noisy input, each its own 1-spp pass (>= 2: colorA/colorB halves)
    ref_spp: int  # samples per pixel of the reference
    seed: int = 0  # noise seed and scene variation seed (scenes.variation)
    gbuffer_spp: int = 16  # jittered samples averaged for albedo and normal
    emission_spp: int = 1024  # samples of the max-depth-1 emission pass, stratified in square sets (mean_of_calls)
    ao_spp: int = 64  # ambient-occlusion rays per pixel (binary visibility each: 64 keeps the layer smooth)
    max_depth: int | None = None  # path length limit; None: the scene's

    def __post_init__(self):
        if self.width < 1 or self.height < 1:
            raise ValueError(f"size must be positive, got {self.width}x{self.height}")
        if self.spp < 2:
            raise ValueError(f"spp must be >= 2 (colorA and colorB each need samples), got {self.spp}")
        if self.ref_spp < 1:
            raise ValueError(f"ref_spp must be >= 1, got {self.ref_spp}")


@dataclass(frozen=True, eq=False)
class RenderedFrame:
    """One rendered frame."""

    layers: dict[str, np.ndarray]  # frame-format layer -> (H, W, C) float32
    gbuffer: GBuffer  # pixel-centre geometry, kept for the next frame's motion vectors
    view: View  # camera and transforms, kept for the next frame's motion vectors
    seconds: float  # wall time of the passes, seconds


def seed_for(seed: int, frame: int, stream: int, index: int = 0) -> int:
    """A uint32 Mitsuba seed, distinct per (sequence seed, frame, pass stream, pass index)."""
    return int(np.random.SeedSequence([seed, frame + 1_000, stream, index]).generate_state(1)[0])


STREAM_NOISE, STREAM_REFERENCE, STREAM_EMISSION, STREAM_GBUFFER, STREAM_AO = range(5)


def make_view(state: SceneState, width: int, height: int) -> View:
    """The motion-vector view of `state` on a `width` x `height` film."""
    cam = state.camera
    return View(cam.world_to_pixel(width, height), np.asarray(cam.origin, np.float64),
                pixel_directions(cam, height, width), state.transforms())


def _independent() -> dict:
    return {"type": "independent"}


def _render(mi: ModuleType, scene, spp: int, seed: int) -> np.ndarray:
    """(H, W, C) float32 of one Mitsuba render call."""
    return np.array(mi.render(scene, spp=spp, seed=seed), dtype=np.float32)


def render_gbuffer(mi: ModuleType, state: SceneState, opts: RenderOptions) -> GBuffer:
    """Pixel-centre position, shape index and depth (pass 5).

    Depth is the distance from the camera position to the hit position. (Mitsuba's depth AOV measures
    from the near clip plane, where its perspective rays start, so it is short by about near_clip.)
    """
    from models.data.mitsuba_scene import build_scene, shape_index_lookup

    integrator = {"type": "aov", "aovs": "p:position,s:shape_index"}
    sampler = {"type": "stratified", "sample_count": 1, "jitter": False}
    scene = build_scene(state, opts.width, opts.height, integrator, sampler)
    img = _render(mi, scene, 1, 0)
    lookup = shape_index_lookup(scene, state)
    raw = np.rint(img[..., 3]).astype(np.int64)
    shape = np.full(raw.shape, -1, np.int32)
    for value, index in lookup.items():
        shape[raw == value] = index
    unknown = (raw != 0) & (shape < 0)
    if unknown.any():
        raise RuntimeError(f"shape_index AOV holds values {np.unique(raw[unknown])[:5]} that match no shape")
    position = img[..., :3].astype(np.float64)
    distance = np.linalg.norm(position - np.asarray(state.camera.origin, np.float64), axis=-1)
    depth = np.where(shape >= 0, distance, DEPTH_MISS).astype(np.float32)
    return GBuffer(position, shape, depth)


def render_frame(mi: ModuleType, spec: SceneSpec, frame: int, opts: RenderOptions,
                 previous: tuple[GBuffer, View]) -> RenderedFrame:
    """Render frame `frame` of `spec` (all layers); `previous` is frame-1's G-buffer and view."""
    start = time.perf_counter()
    state = spec.state(float(frame), opts.seed)
    layers = {**_radiance_layers(mi, spec, state, frame, opts), **_surface_layers(mi, spec, state, frame, opts)}
    gbuffer = render_gbuffer(mi, state, opts)
    layers["depth"] = gbuffer.depth[..., None]
    roughness = np.array([s.roughness for s in state.shapes] + [0.0], np.float32)
    layers["roughness"] = roughness[gbuffer.shape][..., None]  # index -1 (nothing hit) -> 0
    view = make_view(state, opts.width, opts.height)
    motion = compute_motion(gbuffer, view, *previous)
    layers["motion"] = motion.motion
    layers["motionDual"] = motion.dual
    layers = {name: np.ascontiguousarray(value, np.float32) for name, value in layers.items()}
    return RenderedFrame(layers, gbuffer, view, time.perf_counter() - start)


def _radiance_layers(mi: ModuleType, spec: SceneSpec, state: SceneState, frame: int,
                     opts: RenderOptions) -> dict[str, np.ndarray]:
    """Passes 1-3: color, colorA, colorB, the sample statistics, emission and reference ((H, W, C) float32)."""
    from models.data.mitsuba_scene import build_scene

    w, h = opts.width, opts.height
    depth = opts.max_depth or spec.max_depth
    path = build_scene(state, w, h, {"type": "path", "max_depth": depth}, _independent())
    samples = np.stack([_render(mi, path, 1, seed_for(opts.seed, frame, STREAM_NOISE, k))[..., :3]
                        for k in range(opts.spp)])
    half = opts.spp // 2
    emission = render_emission(mi, state, opts, frame)
    hidden = build_scene(state, w, h, {"type": "path", "max_depth": depth, "hide_emitters": True}, _independent())
    return {
        "color": samples.mean(axis=0),
        "colorA": samples[:half].mean(axis=0),
        "colorB": samples[half:].mean(axis=0),
        **statistics_from_samples(samples),
        "emission": emission,
        "reference": mean_of_calls(mi, hidden, opts.ref_spp, opts, frame, STREAM_REFERENCE) + emission,
    }


def render_emission(mi: ModuleType, state: SceneState, opts: RenderOptions, frame: int) -> np.ndarray:
    """Pass 2: (H, W, 3) float32 radiance of directly seen emitters and environment, `opts.emission_spp`
    stratified samples."""
    from models.data.mitsuba_scene import build_scene

    scene = build_scene(state, opts.width, opts.height, {"type": "path", "max_depth": 1},
                        {"type": "stratified", "jitter": True})
    return mean_of_calls(mi, scene, opts.emission_spp, opts, frame, STREAM_EMISSION, square=True)


def _surface_layers(mi: ModuleType, spec: SceneSpec, state: SceneState, frame: int,
                    opts: RenderOptions) -> dict[str, np.ndarray]:
    """Passes 4 and 6: anti-aliased albedo and normal, and ambient occlusion ((H, W, C) float32)."""
    from models.data.mitsuba_scene import build_scene

    w, h = opts.width, opts.height
    aa = build_scene(state, w, h, {"type": "aov", "aovs": "a:albedo,n:sh_normal"}, _independent(),
                     albedo_bsdfs=True)
    img = _render(mi, aa, opts.gbuffer_spp, seed_for(opts.seed, frame, STREAM_GBUFFER))
    ao = build_scene(state, w, h, {"type": AO_INTEGRATOR, "distance": spec.ao_distance}, _independent())
    return {
        "albedo": img[..., 0:3],
        "normal": _unit_or_zero(img[..., 3:6]),
        "ao": _render(mi, ao, opts.ao_spp, seed_for(opts.seed, frame, STREAM_AO))[..., :1],
    }


def mean_of_calls(mi: ModuleType, scene, spp: int, opts: RenderOptions, frame: int, stream: int, *,
                  square: bool = False) -> np.ndarray:
    """(H, W, 3) float32 mean of `spp` samples of `scene`, rendered in calls of at most MAX_LANES_PER_CALL
    lanes, each seeded by (opts.seed, frame, stream, call). `square`: every call takes the largest square
    sample count that divides `spp` (a stratified sampler's set; the samples are stratified within a call)."""
    per_call = max(1, min(spp, MAX_LANES_PER_CALL // (opts.width * opts.height)))
    if square:  # the largest square count that divides spp: every call a whole stratified set
        per_call = max(k * k for k in range(1, math.isqrt(per_call) + 1) if spp % (k * k) == 0)
    total = np.zeros((opts.height, opts.width, 3), np.float64)
    done, call = 0, 0
    while done < spp:
        n = min(per_call, spp - done)
        total += n * _render(mi, scene, n, seed_for(opts.seed, frame, stream, call))[..., :3]
        done += n
        call += 1
    return (total / spp).astype(np.float32)


def _unit_or_zero(normal: np.ndarray) -> np.ndarray:
    """(H, W, 3) normals scaled to unit length; zero where the length is ~0 (nothing hit)."""
    length = np.linalg.norm(normal, axis=-1, keepdims=True)
    return np.where(length > 1e-6, normal / np.maximum(length, 1e-12), 0.0).astype(np.float32)


def previous_of(mi: ModuleType, spec: SceneSpec, frame: int, opts: RenderOptions) -> tuple[GBuffer, View]:
    """G-buffer and view of frame `frame` - 1 rendered on their own (for the first frame of a sequence)."""
    state = spec.state(float(frame - 1), opts.seed)
    return render_gbuffer(mi, state, opts), make_view(state, opts.width, opts.height)
