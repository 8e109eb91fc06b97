"""Warm-up: run a pipeline on generated frames so its numba kernels compile (or load from the cache) and
its ONNX model loads before the first real frame; and `CompileNotice`, the progress line that the command
line shows while kernels compile. A pipeline compiles only the kernels it calls, once per machine and
version of the kernel sources (`service.process.numba_cache_dir`); `python -m service warm` compiles them
ahead (the Docker image does at build time); the HTTP service warms the shared pipelines named in
`MCDENOISE_WARMUP` at start.
"""

from __future__ import annotations

import os
import sys
import threading
import time
from typing import TextIO

import numpy as np
from numba.core import event

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


class CompileNotice(event.Listener):
    """Context manager: while numba compiles a kernel (a cache miss; a cache load says nothing) inside the
    block, a progress line on `stream`, "compiling kernels for LABEL (first run, cached after)... 12 s",
    redrawn every `interval` seconds on a terminal, written once elsewhere; at `report()` and at the end of
    the block, if anything compiled since the last report, "compiled kernels for LABEL in 35 s (cached in
    DIR)" (call `report()` before writing to the terminal yourself). `compiled_s`: the seconds reported, in
    all (from each first compile to its report), None if nothing compiled. Listens to numba's
    "numba:compile" events, which fire in the compiling thread; the line is drawn from a thread of its own."""

    def __init__(self, label: str, stream: TextIO | None = None, interval: float = 1.0) -> None:
        self.label, self.stream, self.interval = label, stream or sys.stderr, interval
        self.compiled_s: float | None = None
        self._started: float | None = None  # perf_counter of the first compile since the last report
        self._drawn = False  # the progress line is on the stream (on a terminal: without its newline)
        self._lock = threading.Lock()
        self._done = threading.Event()
        self._thread: threading.Thread | None = None

    def on_start(self, ev: event.Event) -> None:
        with self._lock:
            if self._started is None:
                self._started = time.perf_counter()

    def on_end(self, ev: event.Event) -> None:
        pass

    def _tty(self) -> bool:
        isatty = getattr(self.stream, "isatty", None)
        return bool(isatty and isatty())

    def _draw(self) -> None:
        """The progress line, if a compile is under way (lock held)."""
        if self._started is None:
            return
        message = f"compiling kernels for {self.label} (first run, cached after)..."
        if self._tty():
            self.stream.write(f"\r{message} {time.perf_counter() - self._started:.0f} s")
        elif not self._drawn:
            self.stream.write(message + "\n")
        else:
            return
        self.stream.flush()
        self._drawn = True

    def _run(self) -> None:
        while not self._done.wait(self.interval):
            with self._lock:
                self._draw()

    def report(self) -> None:
        """The final line for what compiled since the last report, if anything did."""
        with self._lock:
            if self._started is None:
                return
            seconds = time.perf_counter() - self._started
            self.compiled_s = (self.compiled_s or 0.0) + seconds
            if self._tty() and self._drawn:
                self.stream.write("\r\033[K")  # the progress line gives way to the final one
            where = os.environ.get("NUMBA_CACHE_DIR")
            self.stream.write(f"compiled kernels for {self.label} in {seconds:.0f} s"
                              + (f" (cached in {where})" if where else "") + "\n")
            self.stream.flush()
            self._started, self._drawn = None, False

    def __enter__(self) -> CompileNotice:
        event.register("numba:compile", self)
        self._thread = threading.Thread(target=self._run, name="compile-notice", daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._done.set()
        if self._thread is not None:
            self._thread.join()
        event.unregister("numba:compile", self)
        self.report()
