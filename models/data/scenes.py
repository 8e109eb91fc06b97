"""The scene library: animated procedural scenes chosen to stress denoisers.

Every scene animates its camera and at least one object; `SCENES[name].state(t, seed)` gives the state
at frame time `t` (frames, float). Seed 0 is the canonical animation; other seeds vary phases, speeds
and the camera path a little, for training data. Units are scene units (the rooms are 2 units wide).
`python -m models.data scenes` lists the names with what each stresses.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from models.data import procedural
from models.data import transforms as T
from models.data.camera import Camera
from models.data.description import ROUGHNESS_DIFFUSE, SceneSpec, SceneState, Shape, Texture

WHITE = (0.75, 0.75, 0.75)
RED = (0.63, 0.07, 0.05)
GREEN = (0.12, 0.45, 0.09)
BLACK = (0.0, 0.0, 0.0)


@dataclass(frozen=True)
class Variation:
    """Per-seed animation changes (seed 0: none)."""

    phase: float  # frames added to the object clock
    speed: float  # object speed factor
    camera_offset: float  # sideways camera shift, scene units
    camera_speed: float  # camera speed factor


def variation(seed: int) -> Variation:
    """The animation changes of `seed`; seed 0 is the identity."""
    if seed == 0:
        return Variation(0.0, 1.0, 0.0, 1.0)
    rng = np.random.default_rng([seed, 7])
    return Variation(
        float(rng.uniform(0, 16)), float(rng.uniform(0.7, 1.3)), float(rng.uniform(-0.25, 0.25)),
        float(rng.uniform(0.5, 1.5)) * float(rng.choice([-1.0, 1.0])),
    )


# --- materials and primitives ------------------------------------------------------------------------


def rgb(value) -> dict:
    return {"type": "rgb", "value": list(map(float, value))}


def diffuse(reflectance) -> dict:
    """Lambertian BSDF; `reflectance` is an RGB triple or a Texture."""
    return {"type": "diffuse", "reflectance": reflectance if isinstance(reflectance, Texture) else rgb(reflectance)}


def conductor(alpha: float, material: str = "Au") -> dict:
    """GGX rough conductor of roughness `alpha`; `material` one of Mitsuba's measured metals (Au, Cu, Al...)."""
    return {"type": "roughconductor", "material": material, "alpha": alpha}


def plastic(reflectance, alpha: float) -> dict:
    """GGX rough plastic (diffuse base, dielectric coat) of roughness `alpha`."""
    base = reflectance if isinstance(reflectance, Texture) else rgb(reflectance)
    return {"type": "roughplastic", "diffuse_reflectance": base, "alpha": alpha}


def sphere(name: str, centre, radius: float, bsdf: dict, roughness: float = ROUGHNESS_DIFFUSE, **kw) -> Shape:
    return Shape(name, "sphere", T.translate(centre) @ T.scale(radius), bsdf, roughness, **kw)


def cube(name: str, centre, half_size, bsdf: dict, *, spin_deg: float = 0.0, axis=(0, 1, 0),
         roughness: float = ROUGHNESS_DIFFUSE, **kw) -> Shape:
    """Box [-1, 1]^3 scaled by `half_size` (scalar or (3,)), turned by `spin_deg` about `axis`, moved to `centre`."""
    m = T.translate(centre) @ T.rotate(axis, spin_deg) @ T.scale(half_size)
    return Shape(name, "cube", m, bsdf, roughness, **kw)


def quad(name: str, to_world: np.ndarray, bsdf: dict, roughness: float = ROUGHNESS_DIFFUSE, **kw) -> Shape:
    """Mitsuba rectangle ([-1, 1]^2 in xy, front face +z) placed by `to_world`."""
    return Shape(name, "rectangle", to_world, bsdf, roughness, **kw)


def cornell_room(*, ceiling: bool = True, walls=(RED, GREEN), white=WHITE, floor=None) -> list[Shape]:
    """A 2 x 2 x 2 box open to +z: floor y=0, ceiling y=2, back z=-1, left x=-1, right x=1, normals inward."""
    shapes = [
        quad("floor", T.translate([0, 0, 0]) @ T.rotate([1, 0, 0], -90), diffuse(floor or white)),
        quad("back", T.translate([0, 1, -1]), diffuse(white)),
        quad("left", T.translate([-1, 1, 0]) @ T.rotate([0, 1, 0], 90), diffuse(walls[0])),
        quad("right", T.translate([1, 1, 0]) @ T.rotate([0, 1, 0], -90), diffuse(walls[1])),
    ]
    if ceiling:
        shapes.append(quad("ceiling", T.translate([0, 2, 0]) @ T.rotate([1, 0, 0], 90), diffuse(white)))
    return shapes


def ceiling_light(name: str, half_size: float, radiance) -> Shape:
    """A downward-facing square area light just under the Cornell ceiling."""
    m = T.translate([0, 1.99, 0]) @ T.rotate([1, 0, 0], 90) @ T.scale(half_size)
    return quad(name, m, diffuse(BLACK), radiance=tuple(map(float, radiance)))


def point_light(position, intensity) -> dict:
    return {"type": "point", "position": list(map(float, position)), "intensity": rgb(intensity)}


def spot_light(origin, target, intensity, cutoff_deg: float, beam_deg: float) -> dict:
    """Spot light at `origin` aimed at `target`; `intensity` W/sr (linear RGB), angles in degrees."""
    direction = np.asarray(target, np.float64) - np.asarray(origin, np.float64)
    up = (0.0, 0.0, 1.0) if abs(direction[1]) > 0.99 * np.linalg.norm(direction) else (0.0, 1.0, 0.0)
    return {"type": "spot", "to_world": T.look_at(origin, target, up), "intensity": rgb(intensity),
            "cutoff_angle": cutoff_deg, "beam_width": beam_deg}


# --- cached textures (built once per process) --------------------------------------------------------


@functools.cache
def _tex(kind: str, *args) -> Texture:
    maker: Callable[..., np.ndarray] = getattr(procedural, kind)
    filt = "nearest" if kind in ("checker", "stripes") else "bilinear"
    return Texture(maker(*args), filt)


@functools.cache
def _sky(height: int, elevation: float, azimuth: float, sun: float) -> Texture:
    return Texture(procedural.sky(height, elevation, azimuth, sun_radiance=sun))


@functools.cache
def _torus(major: float, minor: float):
    return procedural.torus(major, minor)


@functools.cache
def _lattice(count: int, spacing: float, thickness: float, length: float, crossbars: int):
    return procedural.lattice(count, spacing, thickness, length, crossbars=crossbars)


def _cornell_camera(v: Variation, t: float, *, sway: float, target_y: float = 0.9, fov: float = 40.0,
                    height: float = 1.0, distance: float = 3.4) -> Camera:
    x = v.camera_offset + sway * np.sin(0.35 * v.camera_speed * t)
    return Camera((x, height, distance), (0.3 * x, target_y, 0.0), (0.0, 1.0, 0.0), fov)


# --- the scenes -----------------------------------------------------------------------------------------


def _shadows(t: float, seed: int) -> SceneState:
    """Cornell box with a large ceiling light (soft shadows) and a spot light (hard shadows)."""
    v = variation(seed)
    s = (t + v.phase) * v.speed
    shapes = cornell_room(ceiling=True) + [
        ceiling_light("panel", 0.45, (4.0, 3.8, 3.4)),
        sphere("ball", (-0.45 + 0.35 * np.sin(0.3 * s), 0.3, 0.1), 0.3, diffuse((0.7, 0.7, 0.2))),
        cube("block", (0.45, 0.35, -0.3), (0.2, 0.35, 0.2), diffuse(WHITE), spin_deg=12 * s),
        Shape("pole", "cylinder", T.translate([0.1, 0.0, 0.45]) @ T.rotate([1, 0, 0], -90) @
              T.rotate([0, 1, 0], 10 * np.sin(0.4 * s)) @ T.scale([0.025, 0.025, 1.2]), diffuse(WHITE),
              ROUGHNESS_DIFFUSE),
    ]
    lights = (spot_light((-0.8, 1.9, 0.9), (0.2, 0.0, -0.2), (25.0, 24.0, 22.0), 28.0, 22.0),)
    return SceneState(_cornell_camera(v, t, sway=0.35), tuple(shapes), lights)


def _disocclusion(t: float, seed: int) -> SceneState:
    """Textured wall and floor; a fast box near the camera sweeps across and uncovers them."""
    v = variation(seed)
    s = (t + v.phase % 4) * v.speed
    wall = _tex("checker", 512, 16, (0.8, 0.8, 0.75), (0.1, 0.15, 0.5))
    floor = _tex("stripes", 512, 24, (0.7, 0.6, 0.4), (0.2, 0.1, 0.05), 45.0)
    shapes = [
        quad("floor", T.rotate([1, 0, 0], -90) @ T.scale(3.0), diffuse(floor)),
        quad("wall", T.translate([0, 1.5, -1.5]) @ T.scale([3.0, 1.5, 1.0]), diffuse(wall)),
        cube("mover", (-1.3 + 0.32 * s, 0.55, 1.2), (0.22, 0.45, 0.22), diffuse((0.85, 0.25, 0.1)),
             spin_deg=9 * s),
        sphere("roller", (1.0 - 0.08 * s, 0.35, -0.2), 0.35, plastic((0.1, 0.4, 0.8), 0.2), 0.2),
        quad("lamp", T.translate([0.5, 3.0, 1.5]) @ T.rotate([1, 0, 0], 90) @ T.scale(0.6), diffuse(BLACK),
             radiance=(6.0, 6.0, 6.0)),
    ]
    z = 3.6 - 0.04 * v.camera_speed * t
    cam = Camera((v.camera_offset, 1.1, z), (v.camera_offset * 0.5, 0.7, 0.0), (0, 1, 0), 45.0)
    return SceneState(cam, tuple(shapes), ({"type": "constant", "radiance": rgb((0.35, 0.38, 0.45))},))


def _fireflies(t: float, seed: int) -> SceneState:
    """Glossy metal and plastic under one tiny, very bright light: caustics and fireflies."""
    v = variation(seed)
    s = (t + v.phase) * v.speed
    torus_to_world = T.translate([0.45, 0.45, -0.1]) @ T.rotate([0, 1, 0], 15 * s) @ T.rotate([1, 0, 0], 60)
    shapes = cornell_room(ceiling=True, walls=((0.5, 0.5, 0.55), (0.5, 0.5, 0.55))) + [
        sphere("bulb", (-0.3, 1.7, 0.3), 0.03, diffuse(BLACK), radiance=(3000.0, 2700.0, 2300.0)),
        sphere("gold", (-0.4, 0.3 + 0.1 * np.sin(0.5 * s), 0.0), 0.3, conductor(0.05, "Au"), 0.05),
        Shape("ring", "mesh", torus_to_world, conductor(0.15, "Cu"), 0.15, mesh=_torus(0.3, 0.09)),
        cube("glossy_block", (0.1, 0.15, 0.5), 0.15, plastic((0.6, 0.05, 0.05), 0.08), spin_deg=-20 * s,
             roughness=0.08),
    ]
    angle = v.camera_offset + 0.04 * v.camera_speed * t
    cam = Camera((3.8 * np.sin(angle), 1.0, 3.8 * np.cos(angle)), (0, 0.8, 0), (0, 1, 0), 40.0)
    return SceneState(cam, tuple(shapes), ())


def _indirect(t: float, seed: int) -> SceneState:
    """A spot light lights only the (unseen) ceiling: every visible surface gets indirect light only."""
    v = variation(seed)
    s = (t + v.phase) * v.speed
    shapes = cornell_room(ceiling=True) + [
        sphere("ball", (0.35 * np.cos(0.3 * s), 0.28, 0.2 + 0.3 * np.sin(0.3 * s)), 0.28, diffuse(WHITE)),
        cube("block", (-0.45, 0.4, -0.4), (0.25, 0.4, 0.25), diffuse((0.3, 0.5, 0.8)), spin_deg=15 * s),
    ]
    lights = (spot_light((0.0, 0.05, -0.2), (0.0, 2.0, -0.2), (40.0, 38.0, 34.0), 25.0, 20.0),)
    cam = _cornell_camera(v, t, sway=0.3, target_y=0.3)
    return SceneState(cam, tuple(shapes), lights)


def _textures(t: float, seed: int) -> SceneState:
    """High-frequency textures (noise, fine stripes, checker) under a sky with a sun; camera moves in."""
    v = variation(seed)
    s = (t + v.phase) * v.speed
    ground = _tex("value_noise", 1024, 6, 3, (0.15, 0.12, 0.1), (0.8, 0.75, 0.6))
    shapes = [
        quad("ground", T.rotate([1, 0, 0], -90) @ T.scale(6.0), diffuse(ground)),
        cube("striped", (-0.6, 0.5, 0.0), 0.5, diffuse(_tex("stripes", 512, 40, (0.9,) * 3, (0.05,) * 3, 30.0)),
             spin_deg=8 * s),
        sphere("checker_ball", (0.7, 0.4, 0.3 - 0.05 * s), 0.4,
               diffuse(_tex("checker", 512, 32, (0.8, 0.1, 0.1), (0.9, 0.9, 0.9)))),
    ]
    z = 4.0 - 0.12 * v.camera_speed * t
    cam = Camera((v.camera_offset, 1.4 - 0.04 * t, z), (0, 0.3, 0), (0, 1, 0), 45.0)
    env = {"type": "envmap", "bitmap": _sky(128, 35.0, 40.0, 2000.0), "scale": 1.0}
    return SceneState(cam, tuple(shapes), (env,))


def _thin(t: float, seed: int) -> SceneState:
    """A fence of thin bars and swinging wires in front of a bright sky; the camera pans (parallax)."""
    v = variation(seed)
    s = (t + v.phase) * v.speed
    fence = _lattice(14, 0.18, 0.025, 1.4, 3)
    shapes = [
        quad("ground", T.rotate([1, 0, 0], -90) @ T.scale(5.0), diffuse((0.35, 0.4, 0.3))),
        Shape("fence", "mesh", T.translate([0.05 * np.sin(0.3 * s), 0, 0.6]), diffuse((0.55, 0.5, 0.45)),
              ROUGHNESS_DIFFUSE, mesh=fence),
        Shape("wire", "cylinder", T.translate([-0.2, 1.8, 1.2]) @ T.rotate([0, 0, 1], 20 * np.sin(0.5 * s))
              @ T.rotate([1, 0, 0], 90) @ T.scale([0.008, 0.008, 1.7]), diffuse((0.1, 0.1, 0.1)), ROUGHNESS_DIFFUSE),
        sphere("behind", (0.4 - 0.06 * s, 0.5, -0.8), 0.5, plastic((0.8, 0.3, 0.1), 0.3), 0.3),
    ]
    x = v.camera_offset + 0.05 * v.camera_speed * t
    cam = Camera((x, 1.0, 3.3), (x * 0.3, 0.8, 0.0), (0, 1, 0), 40.0)
    env = {"type": "envmap", "bitmap": _sky(64, 50.0, -30.0, 300.0), "scale": 1.0}
    return SceneState(cam, tuple(shapes), (env, point_light((1.5, 2.5, 2.5), (3.0, 3.0, 3.0))))


def _dark(t: float, seed: int) -> SceneState:
    """A dim room: a weak point light in a corner and a small dim window; radiance around 1e-2."""
    v = variation(seed)
    s = (t + v.phase) * v.speed
    dim = (0.3, 0.3, 0.3)
    shapes = cornell_room(ceiling=True, walls=((0.3, 0.2, 0.15), (0.15, 0.2, 0.3)), white=dim) + [
        quad("window", T.translate([-0.99, 1.3, -0.3]) @ T.rotate([0, 1, 0], 90) @ T.scale([0.25, 0.35, 1]),
             diffuse(BLACK), radiance=(0.25, 0.3, 0.45)),
        sphere("ball", (0.3 * np.sin(0.4 * s), 0.25, 0.1), 0.25, diffuse((0.6, 0.6, 0.6))),
        cube("crate", (0.5, 0.3, -0.4), 0.3, diffuse((0.5, 0.4, 0.3)), spin_deg=-10 * s),
    ]
    lights = (point_light((0.8, 1.8, 0.8), (0.15, 0.12, 0.08)),)
    return SceneState(_cornell_camera(v, t, sway=0.3), tuple(shapes), lights)


def _emissive(t: float, seed: int) -> SceneState:
    """Many moving coloured emitters seen directly and in a glossy floor: emission dominates the image."""
    v = variation(seed)
    s = (t + v.phase) * v.speed
    colours = [(12.0, 2.0, 1.0), (1.0, 10.0, 2.0), (1.5, 3.0, 14.0), (10.0, 8.0, 1.0), (8.0, 1.0, 9.0)]
    shapes = [
        quad("floor", T.rotate([1, 0, 0], -90) @ T.scale(3.0), plastic((0.05, 0.05, 0.06), 0.12), 0.12),
        quad("back", T.translate([0, 1.5, -1.5]) @ T.scale([3.0, 1.5, 1.0]), diffuse((0.4, 0.4, 0.4))),
        Shape("tube", "cylinder", T.translate([-1.2, 0.1, -1.3]) @ T.rotate([0, 1, 0], 90) @
              T.scale([0.04, 0.04, 2.4]), diffuse(BLACK), ROUGHNESS_DIFFUSE, radiance=(20.0, 4.0, 16.0)),
    ]
    for k, colour in enumerate(colours):
        a = 2 * np.pi * k / len(colours) + 0.12 * s
        centre = (0.9 * np.cos(a), 0.45 + 0.25 * np.sin(1.7 * a), 0.9 * np.sin(a) - 0.2)
        shapes.append(sphere(f"glow{k}", centre, 0.12, diffuse(BLACK), radiance=colour))
    shapes.append(cube("pedestal", (0.0, 0.25, -0.2), 0.25, diffuse((0.7, 0.7, 0.7)), spin_deg=6 * s))
    angle = v.camera_offset - 0.05 * v.camera_speed * t
    cam = Camera((3.4 * np.sin(angle), 1.3, 3.4 * np.cos(angle)), (0, 0.5, -0.2), (0, 1, 0), 45.0)
    return SceneState(cam, tuple(shapes), ())


def _glossy_env(t: float, seed: int) -> SceneState:
    """Outdoor: rough plastic and metal under a sky with a small, very bright sun (hard shadows, glints)."""
    v = variation(seed)
    s = (t + v.phase) * v.speed
    shapes = [
        quad("ground", T.rotate([1, 0, 0], -90) @ T.scale(6.0), diffuse(_tex("checker", 256, 12, (0.6,) * 3,
                                                                                (0.3,) * 3))),
        Shape("torus", "mesh", T.translate([-0.5, 0.45, 0]) @ T.rotate([0, 1, 0], -12 * s) @ T.rotate([1, 0, 0], 75),
              plastic((0.1, 0.5, 0.2), 0.1), 0.1, mesh=_torus(0.4, 0.12)),
        sphere("chrome", (0.6, 0.35 + 0.15 * abs(np.sin(0.5 * s)), 0.2), 0.35, conductor(0.02, "Al"), 0.02),
    ]
    angle = v.camera_offset + 0.05 * v.camera_speed * t
    cam = Camera((3.5 * np.sin(angle), 1.2, 3.5 * np.cos(angle)), (0, 0.4, 0), (0, 1, 0), 40.0)
    env = {"type": "envmap", "bitmap": _sky(128, 25.0, 120.0, 20000.0), "scale": 1.0}
    return SceneState(cam, tuple(shapes), (env,))


def _veiled_light(t: float, seed: int) -> SceneState:
    """A small, very bright sphere light seen directly through a grid of thin bars; a glossy floor
    mirrors it. The bars cover part of the light in most pixels around it."""
    v = variation(seed)
    s = (t + v.phase) * v.speed
    room = cornell_room(ceiling=True, walls=((0.5, 0.45, 0.4), (0.4, 0.45, 0.5)))[1:]  # all but the floor
    shapes = [quad("floor", T.rotate([1, 0, 0], -90), plastic((0.3, 0.3, 0.3), 0.05), 0.05), *room,
        sphere("lamp", (0.05 * np.sin(0.3 * s), 1.2, -0.4), 0.07, diffuse(BLACK), radiance=(1000.0, 900.0, 750.0)),
        sphere("metal", (0.45, 0.3, 0.1 + 0.1 * np.sin(0.4 * s)), 0.3, conductor(0.1, "Cu"), 0.1),
        Shape("bars", "mesh", T.translate([0.0, 0.55, 0.3]), diffuse((0.2, 0.2, 0.22)), ROUGHNESS_DIFFUSE,
              mesh=_lattice(7, 0.1, 0.025, 1.1, 4)),
    ]
    return SceneState(_cornell_camera(v, t, sway=0.15, target_y=1.0), tuple(shapes), ())


def _window(t: float, seed: int) -> SceneState:
    """Inside a closed room looking at a window: a sky of radiance 1e3 outside, the room lit only
    through the window (a bright sun patch on the floor, the rest indirect light)."""
    v = variation(seed)
    s = (t + v.phase) * v.speed
    wall = (0.7, 0.68, 0.62)
    x0, x1, y0, y1 = -0.3, 0.2, 1.0, 1.5  # window opening in the back wall (z = -1)
    back = T.translate([0, 0, -1])
    shapes = [
        quad("floor", T.rotate([1, 0, 0], -90) @ T.scale([1, 1.3, 1]), diffuse((0.5, 0.4, 0.3))),
        quad("ceiling", T.translate([0, 2, 0]) @ T.rotate([1, 0, 0], 90) @ T.scale([1, 1.3, 1]), diffuse(wall)),
        quad("left", T.translate([-1, 1, 0]) @ T.rotate([0, 1, 0], 90) @ T.scale([1.3, 1, 1]), diffuse(wall)),
        quad("right", T.translate([1, 1, 0]) @ T.rotate([0, 1, 0], -90) @ T.scale([1.3, 1, 1]), diffuse(wall)),
        quad("front", T.translate([0, 1, 1.3]) @ T.rotate([0, 1, 0], 180), diffuse(wall)),
        quad("below", back @ T.translate([0, y0 / 2, 0]) @ T.scale([1, y0 / 2, 1]), diffuse(wall)),
        quad("above", back @ T.translate([0, (y1 + 2) / 2, 0]) @ T.scale([1, (2 - y1) / 2, 1]), diffuse(wall)),
        quad("beside_l", back @ T.translate([(x0 - 1) / 2, (y0 + y1) / 2, 0])
             @ T.scale([(x0 + 1) / 2, (y1 - y0) / 2, 1]), diffuse(wall)),
        quad("beside_r", back @ T.translate([(x1 + 1) / 2, (y0 + y1) / 2, 0])
             @ T.scale([(1 - x1) / 2, (y1 - y0) / 2, 1]), diffuse(wall)),
        sphere("ball", (0.3 * np.sin(0.4 * s), 0.25, -0.3), 0.25, diffuse((0.7, 0.7, 0.7))),
    ]
    x = v.camera_offset + 0.1 * np.sin(0.3 * v.camera_speed * t)
    cam = Camera((x, 1.0, 1.2), (0.3 * x, 0.8, -1.0), (0.0, 1.0, 0.0), 60.0)
    return SceneState(cam, tuple(shapes), ({"type": "constant", "radiance": rgb((1000.0, 1000.0, 1100.0))},))


SCENES: dict[str, SceneSpec] = {
    spec.name: spec
    for spec in (
        SceneSpec("shadows", "hard (spot) and soft (area) shadows of moving objects that no G-buffer shows", _shadows),
        SceneSpec("disocclusion", "a fast box near the camera uncovers textured background every frame",
                  _disocclusion, period=8.0),  # the box crosses the view in about 8 frames
        SceneSpec("fireflies", "glossy metal/plastic under a tiny very bright light: fireflies and caustics",
                  _fireflies, max_depth=8, period=16.0),  # the orbit leaves the room after about 30 frames
        SceneSpec("indirect", "only indirect light reaches visible surfaces (the lit ceiling is out of view)",
                  _indirect, max_depth=8),
        SceneSpec("textures", "high-frequency noise, stripe and checker textures with minification", _textures,
                  period=16.0),  # the camera flies in: at frame 30 it would reach the ball
        SceneSpec("thin", "thin fence bars and wires against a bright sky, camera parallax", _thin,
                  ao_distance=0.25),
        SceneSpec("dark", "a dim room (radiance ~1e-2) lit by a weak point light and a small window", _dark),
        SceneSpec("emissive", "many moving emitters seen directly and in a glossy floor", _emissive),
        SceneSpec("glossy_env", "rough plastic and near-mirror metal under an HDR sky with a tiny bright sun",
                  _glossy_env),
        SceneSpec("veiled_light", "a small light of radiance 1e3 seen through thin bars, mirrored by a glossy floor",
                  _veiled_light, max_depth=8),
        SceneSpec("window", "a closed room lit only through a window by a sky of radiance 1e3 (seen directly)",
                  _window, max_depth=8),
    )
}


def get(name: str) -> SceneSpec:
    """The library scene `name`; ValueError listing the names when unknown."""
    try:
        return SCENES[name]
    except KeyError:
        raise ValueError(f"unknown scene '{name}'; scenes: {', '.join(SCENES)}") from None
