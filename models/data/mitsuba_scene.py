"""Turn a `SceneState` into a Mitsuba scene for one render pass; map Mitsuba shape indices back to shapes.

Call only after `variant.load_mitsuba()` (this module imports mitsuba). Every pass uses a box pixel
filter, so each sample lands in exactly one pixel and separate 1-spp passes stay independent per pixel.
"""

from __future__ import annotations

from typing import Any

import drjit as dr
import mitsuba as mi
import numpy as np

from models.data.description import Mesh, SceneState, Shape, Texture


def build_scene(state: SceneState, width: int, height: int, integrator: dict[str, Any],
                sampler: dict[str, Any], *, albedo_bsdfs: bool = False) -> mi.Scene:
    """A Mitsuba scene of `state` rendered by `integrator` with `sampler` on a `width` x `height` film.

    albedo_bsdfs: replace every BSDF by a diffuse one of the shape's albedo (Shape.albedo), for the
    albedo AOV pass.
    """
    cam = state.camera
    scene: dict[str, Any] = {
        "type": "scene",
        "integrator": integrator,
        "sensor": {
            "type": "perspective",
            "fov": cam.fov_x,
            "fov_axis": "x",
            "to_world": mi.ScalarTransform4f(cam.camera_to_world()),
            "film": {"type": "hdrfilm", "width": width, "height": height, "rfilter": {"type": "box"},
                     "pixel_format": "rgb", "component_format": "float32"},
            "sampler": sampler,
        },
    }
    for shape in state.shapes:
        scene[shape.name] = _shape(shape, albedo_bsdfs)
    for k, light in enumerate(state.lights):
        scene[f"light{k}"] = _convert(light)
    # optimize=False: Mitsuba would otherwise merge meshes that share a BSDF into one shape, losing the
    # per-object identity the shape-index AOV and the motion vectors need.
    return mi.load_dict(scene, optimize=False)


def _convert(value: Any, key: str = "") -> Any:
    """Replace Textures by bitmap textures (or bare Bitmaps under `bitmap`) and (4, 4) arrays by transforms."""
    if isinstance(value, dict):
        return {k: _convert(v, k) for k, v in value.items()}
    if isinstance(value, Texture):
        bitmap = mi.Bitmap(np.ascontiguousarray(value.pixels, np.float32))
        if key == "bitmap":
            return bitmap
        return {"type": "bitmap", "bitmap": bitmap, "filter_type": value.filter, "raw": True}
    if isinstance(value, np.ndarray) and value.shape == (4, 4):
        return mi.ScalarTransform4f(value)
    return value


def _shape(shape: Shape, albedo_bsdf: bool) -> Any:
    bsdf = {"type": "diffuse", "reflectance": shape.albedo()} if albedo_bsdf else shape.bsdf
    emitter = None
    if shape.radiance is not None:
        emitter = {"type": "area", "radiance": {"type": "rgb", "value": list(shape.radiance)}}
    if shape.mesh is not None:
        return _mesh(shape.name, shape.mesh, shape.to_world, _convert(bsdf), emitter)
    out = {"type": shape.kind, "to_world": mi.ScalarTransform4f(shape.to_world), "bsdf": _convert(bsdf)}
    if emitter is not None:
        out["emitter"] = emitter
    return out


def _mesh(name: str, mesh: Mesh, to_world: np.ndarray, bsdf: dict, emitter: dict | None) -> mi.Mesh:
    """A Mitsuba mesh with the vertices moved to world space by `to_world` (baked, as Mitsuba does)."""
    props = mi.Properties()
    props["bsdf"] = mi.load_dict(bsdf)
    if emitter is not None:
        props["emitter"] = mi.load_dict(emitter)
    verts = mesh.vertices.astype(np.float64) @ to_world[:3, :3].T + to_world[:3, 3]
    out = mi.Mesh(name, len(verts), len(mesh.faces), has_vertex_normals=False,
                  has_vertex_texcoords=mesh.uvs is not None, props=props)
    params = mi.traverse(out)
    params["vertex_positions"] = _flat(verts, mi.Float)
    params["faces"] = _flat(mesh.faces, mi.UInt32)
    if mesh.uvs is not None:
        params["vertex_texcoords"] = _flat(mesh.uvs, mi.Float)
    params.update()
    return out


def _flat(array: np.ndarray, kind: type) -> Any:
    flat = np.ascontiguousarray(array).ravel()
    if dr.is_jit_v(mi.Float):
        return kind(flat.astype(np.uint32 if kind is mi.UInt32 else np.float32))
    return flat.astype(np.uint32 if kind is mi.UInt32 else np.float32)


def shape_index_lookup(scene: mi.Scene, state: SceneState) -> dict[int, int]:
    """Value of the `shape_index` AOV -> index into `state.shapes`.

    The AOV holds, in scalar variants, the 1-based position in `scene.shapes()` and, in JIT variants,
    the shape's registry id (Mitsuba aov.cpp); 0 means nothing was hit in both.
    """
    order = {shape.name: k for k, shape in enumerate(state.shapes)}
    lookup: dict[int, int] = {}
    for position, shape in enumerate(scene.shapes()):
        if dr.is_jit_v(mi.Float):
            value = int(dr.reinterpret_array(mi.UInt32, mi.ShapePtr(shape))[0])
        else:
            value = position + 1
        lookup[value] = order[shape.id()]
    return lookup
