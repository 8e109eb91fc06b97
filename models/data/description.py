"""Scene descriptions without mitsuba: what a scene holds at one instant, as plain numpy and dicts.

A `SceneSpec` builds a `SceneState` for any frame time; the renderer turns a state into a Mitsuba
scene (models.data.mitsuba_scene) and the motion-vector code reads the same state's camera and
object transforms. BSDF and light entries are Mitsuba plugin dicts in which a `Texture` may stand
for any texture (or for an environment map's `bitmap`) and a (4, 4) array for any transform.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from models.data.camera import Camera

# Values of the `roughness` layer by material family: Lambertian surfaces scatter like the roughest
# microfacet surface, ideal mirrors and glass are perfectly smooth.
ROUGHNESS_DIFFUSE = 1.0
ROUGHNESS_SPECULAR = 0.0
SHAPE_KINDS = ("sphere", "cube", "rectangle", "disk", "cylinder", "mesh")
# Albedo of Mitsuba's measured metals: linear reflectance at normal incidence, F0 (Akenine-Moeller et al.,
# Real-Time Rendering 4th ed., Table 9.2). Mitsuba's albedo AOV is unbounded for glossy conductors
# (it evaluates the BSDF lobe), so the albedo pass uses these instead.
METAL_ALBEDO = {"Au": (1.0, 0.782, 0.344), "Cu": (0.955, 0.638, 0.538), "Al": (0.913, 0.922, 0.924),
                "Ag": (0.972, 0.960, 0.915)}


@dataclass(frozen=True, eq=False)
class Texture:
    """A bitmap texture made from a numpy array."""

    pixels: np.ndarray  # (h, w, 3) float32 linear RGB: reflectance in [0, 1] or radiance (HDR)
    filter: str = "bilinear"  # Mitsuba filter_type: "bilinear" or "nearest"


@dataclass(frozen=True, eq=False)
class Mesh:
    """A triangle mesh made from numpy arrays, in object space."""

    vertices: np.ndarray  # (V, 3) float32, object space units
    faces: np.ndarray  # (F, 3) uint32 vertex indices, counter-clockwise seen from the front
    uvs: np.ndarray | None = None  # (V, 2) float32 texture coordinates in [0, 1], or None


@dataclass(frozen=True, eq=False)
class Shape:
    """One object at one instant."""

    name: str  # unique within the scene; the Mitsuba id, the key of its transform in sequence.json
    kind: str  # a Mitsuba built-in of unit size (see SHAPE_KINDS) or "mesh"
    to_world: np.ndarray  # (4, 4) float64 object-to-world transform at this instant
    bsdf: dict[str, Any]  # Mitsuba BSDF dict (Texture allowed for textures)
    roughness: float  # value written to the `roughness` layer, [0, 1] (microfacet alpha, 1 for diffuse)
    radiance: tuple[float, float, float] | None = None  # area-emitter radiance (linear RGB), None: not emissive
    mesh: Mesh | None = None  # geometry when kind == "mesh"

    def albedo(self) -> dict[str, Any] | Texture:
        """Albedo of the first-hit surface as a Mitsuba reflectance (rgb dict) or Texture: a diffuse BSDF's
        reflectance, a plastic's diffuse base, a metal's F0 (METAL_ALBEDO)."""
        bsdf = self.bsdf
        kind = bsdf["type"]
        if kind == "diffuse":
            return bsdf["reflectance"]
        if kind in ("plastic", "roughplastic"):
            return bsdf["diffuse_reflectance"]
        if kind in ("conductor", "roughconductor"):
            return {"type": "rgb", "value": list(METAL_ALBEDO[bsdf.get("material", "Cu")])}
        raise ValueError(f"shape '{self.name}': no albedo rule for BSDF type '{kind}'")

    def __post_init__(self):
        if self.kind not in SHAPE_KINDS:
            raise ValueError(f"shape '{self.name}': kind '{self.kind}' is not one of {SHAPE_KINDS}")
        if (self.kind == "mesh") != (self.mesh is not None):
            raise ValueError(f"shape '{self.name}': a mesh needs kind 'mesh' and mesh data, and only it")
        self.albedo()  # fail early on a BSDF without an albedo rule


@dataclass(frozen=True, eq=False)
class SceneState:
    """A scene at one instant: camera, shapes (same names in every frame) and non-shape lights."""

    camera: Camera
    shapes: tuple[Shape, ...]
    lights: tuple[dict[str, Any], ...] = ()  # Mitsuba emitter dicts: point, spot, envmap, constant

    def transforms(self) -> np.ndarray:
        """(K, 4, 4) float64 object-to-world transforms of the K shapes, in `shapes` order."""
        return np.stack([s.to_world for s in self.shapes])


@dataclass(frozen=True)
class SceneSpec:
    """An animated procedural scene of the library."""

    name: str  # command-line name
    stresses: str  # one line: what about it is hard for a denoiser
    build: Callable[[float, int], SceneState] = field(repr=False)  # (frame time, variation seed) -> state
    max_depth: int = 6  # path length limit of the path tracer (Mitsuba max_depth)
    ao_distance: float = 0.5  # ambient-occlusion ray length, scene units (a quarter of a room)
    # frames after which the animation plays backwards, then forwards again (`scene_clock`): scenes whose
    # camera or objects move in a straight line and would leave the view; 0: the clock runs on
    period: float = 0.0

    def state(self, t: float, seed: int) -> SceneState:
        """The scene at frame time `t` (frames) of variation `seed`: `build` at `scene_clock(t, period)`."""
        return self.build(scene_clock(t, self.period), seed)


def scene_clock(t: float, period: float) -> float:
    """Frame time -> the scene's own time: `t` up to `period` (and for any t when period is 0), beyond it a
    triangle wave between 0 and `period` (back to 0 at 2 period, up again...), so that a sequence of any
    length keeps moving within the frames the scene was designed for. Continuous in t."""
    if period <= 0 or t <= period:
        return t
    u = t % (2 * period)
    return u if u <= period else 2 * period - u
