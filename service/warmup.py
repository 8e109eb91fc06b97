"""Warm-up: run a pipeline on generated frames so its numba kernels compile (or load from the cache) and
its ONNX model loads before the first real frame. A cold first frame costs tens of seconds (`make demo`
on a fresh clone with an empty cache: 27 s in all, 2026-11-21); the HTTP service warms the shared
pipelines named in `MCDENOISE_WARMUP` at start.
"""

from __future__ import annotations

import time

import numpy as np

from service.frame import LAYERS, Frame
from service.pipelines import Pipeline

WARMUP_SIZE = (37, 70)  # H, W: small, and no multiple of any block size (edge paths compile too)


def warmup_frame(height: int, width: int, seed: int = 0) -> Frame:
    """A Frame with every layer of the format but `reference`, plausible values, float32 (H, W, C)."""
    rng = np.random.default_rng(seed)
    buffers = {
        name: rng.uniform(0.05, 1.0, (height, width, len(spec.channels))).astype(np.float32)
        for name, spec in LAYERS.items()
        if name != "reference"
    }
    buffers["normal"] /= np.linalg.norm(buffers["normal"], axis=-1, keepdims=True)
    buffers["motion"] = buffers["motionDual"] = rng.uniform(-2.0, 2.0, (height, width, 2)).astype(np.float32)
    buffers["sampleCount"] = np.full((height, width, 1), 4.0, np.float32)
    buffers["emission"] = np.zeros((height, width, 3), np.float32)
    return Frame.from_buffers(buffers)


def warm_up(pipeline: Pipeline) -> float:
    """Step `pipeline` over two warm-up frames, so temporal pipelines reach their history path too, and
    what it loads on first use (crossreg's ONNX model) stays loaded in that object. Returns the wall time
    in seconds; raises what the pipeline raises."""
    height, width = WARMUP_SIZE
    start = time.perf_counter()
    state = pipeline.start(height, width)
    try:
        for seed in (0, 1):
            _, state = pipeline.step(warmup_frame(height, width, seed), state)
    finally:
        state.close()
    return time.perf_counter() - start
