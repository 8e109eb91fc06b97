"""The environment seen directly passes through a denoiser as it came.

A pixel where the camera ray hit nothing (zero `normal`, FRAME_FORMAT.md) shows the environment: one lookup
per sample, so its only noise is the pixel filter's jitter over the environment's detail, and no surface's
G-buffer says anything about it. (A pixel within the pixel filter's reach of a surface, FILTER_REACH, also
holds that surface's noisy samples: it is left to the denoiser.) A filter that mixes such a pixel with its
neighbours (a sky of radiance 1e3 beside a window frame, a sun's disc) blurs that detail or drags surfaces'
radiance into it. So the pipeline step (Pipeline.step) returns these pixels as they came, before its guards,
unless the renderer's `emission` layer holds them: then the step's emission split keeps the environment out
of the filters, and the denoisers' smoothing of what remains (the jitter) is kept. Most renderers write no
`emission` layer; ours carry the environment in theirs, and the Blender dialect adds `Env` to `Emit` when the
file has it (without it, the sky is not in `Emit`, and passes through here).

Measured, `python -m bench.hard_cases table` (64x64): on `glints` (no emission layer, sky seen directly) the
worst 16x16 tile of `statistical` goes from 1.13x to 1.01x the noisy input's error, `crossregression`'s from
1.6x to 1.13x (its sky tiles are the input's own now; what is left is a reflection). On `make bench`'s four
sequences (emission layers throughout) nothing changes but `rae`'s, `kpn`'s and `auto`'s background, which
those networks' pipelines used to pass through whatever the frame: their relL2 on fireflies and textures is
0.3-1.5% lower now, `auto`'s 3% and 7% (python -m bench run --no-flip --anchors none, 2026-11-27). Time at
1280x720 (a script over `pass_background`, 2026-11-27): 1.5 ms for a frame that hit everywhere (the normal's
test), 20 ms with a sky over 200 rows, 21 ms with an emission layer too.
"""

from __future__ import annotations

import numpy as np

from service.stages.reprojection import surface_hit
from service.stages.svgf import box_mean

FILTER_REACH = 2  # pixels: a surface this close can reach a pixel through the renderer's pixel filter


def pass_background(out: np.ndarray, color: np.ndarray, normal: np.ndarray,
                    emission: np.ndarray | None = None) -> np.ndarray:
    """out, color: (H, W, 3) float32 denoised and noisy linear radiance; normal: (H, W, 3) float32 unit normals,
    zero where nothing was hit; emission: the renderer's (H, W, 3) float32 emission layer or None. Returns
    (H, W, 3) float32: `color` where nothing was hit within FILTER_REACH pixels and the emission (if any) is
    zero, `out` elsewhere (`out` itself when there is no such pixel)."""
    given = [x for x in (out, color, normal, emission) if x is not None]
    if len({x.shape for x in given}) != 1 or out.ndim != 3:
        raise ValueError(f"background: out, color, normal and emission must share one (H, W, 3) shape, got "
                         f"{[x.shape for x in given]}")
    hit = surface_hit(normal)
    if hit.all():
        return out
    background = box_mean(hit[..., None].astype(np.float32), FILTER_REACH)[..., 0] == 0  # no hit within reach
    if emission is not None:  # per channel: `any` over a last axis of 3 is eight times as slow
        background &= (emission[..., 0] == 0) & (emission[..., 1] == 0) & (emission[..., 2] == 0)
    if not background.any():
        return out
    return np.where(background[..., None], color, out).astype(np.float32, copy=False)
