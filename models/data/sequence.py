"""Render a scene into a sequence folder: frame_0000.exr ... (every frame-format layer) and sequence.json.

sequence.json holds what a reader needs to reproduce or reproject the frames: per frame the camera
(`world_to_camera`, `projection` to pixels as in models.data.camera, `fov_x`), every object's
`to_world`, and the render settings (spp, ref_spp, seed, variant, seconds per frame).
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path
from typing import Any

from models.data.description import SceneSpec, SceneState
from models.data.motion import DEPTH_MISS
from models.data.render import RenderOptions, previous_of, render_frame
from models.data.variant import load_mitsuba
from service.exr import write_frame

METADATA = "sequence.json"


def frame_name(index: int) -> str:
    return f"frame_{index:04d}.exr"


def frame_metadata(state: SceneState, opts: RenderOptions) -> dict[str, Any]:
    """JSON-ready camera matrices and object transforms of one frame."""
    cam = state.camera
    return {
        "world_to_camera": cam.world_to_camera().tolist(),
        "projection": cam.projection(opts.width, opts.height).tolist(),
        "fov_x": cam.fov_x,
        "camera": {"origin": list(cam.origin), "target": list(cam.target), "up": list(cam.up)},
        "objects": {shape.name: shape.to_world.tolist() for shape in state.shapes},
    }


def render_sequence(spec: SceneSpec, out: str | Path, opts: RenderOptions, frames: int, *, half: bool = False,
                    variant: str | None = None,
                    on_frame: Callable[[int, float], None] | None = None) -> list[float]:
    """Render `frames` frames of `spec` into `out`; returns the seconds each frame took.

    The G-buffer of frame -1 is rendered too, so frame 0 has motion vectors. `half` writes float16
    channels. `on_frame(index, seconds)` is called after each frame is written. sequence.json is
    written last, so a folder with it is complete.
    """
    if frames < 1:
        raise ValueError(f"frames must be >= 1, got {frames}")
    mi = load_mitsuba(variant)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    previous = previous_of(mi, spec, 0, opts)
    seconds, per_frame = [], []
    for index in range(frames):
        rendered = render_frame(mi, spec, index, opts, previous)
        write_frame(out / frame_name(index), rendered.layers, half=half)
        previous = (rendered.gbuffer, rendered.view)
        seconds.append(rendered.seconds)
        per_frame.append(frame_metadata(spec.state(float(index), opts.seed), opts))
        if on_frame is not None:
            on_frame(index, rendered.seconds)
    meta = {
        "source": "models.data",
        "scene": spec.name,
        "stresses": spec.stresses,
        "variant": mi.variant(),
        "size": [opts.width, opts.height],
        "spp": opts.spp,
        "ref_spp": opts.ref_spp,
        "seed": opts.seed,
        "max_depth": opts.max_depth or spec.max_depth,
        "options": asdict(opts),
        "half": half,
        "depth_miss": DEPTH_MISS,
        "conventions": "pixel centres at +0.5, y down; projection maps Mitsuba camera space (+z forward, "
                       "+x left, +y up) to pixels: (P @ p)[:2] / (P @ p)[3]; motion backward in pixels",
        "seconds_per_frame": seconds,
        "frames": per_frame,
    }
    (out / METADATA).write_text(json.dumps(meta, indent=1))
    return seconds
