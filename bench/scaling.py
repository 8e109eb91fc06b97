"""`python -m bench scaling`: how each method's cost grows with frame size.

Each (method, size) runs in its own Python process (same interpreter, same thread environment), so
one method's memory never counts against another's: the synthetic scene at that size, a warm-up
of two steps through a discarded state (the first frame and one with history, as `bench run`), then
`frames` timed steps through a fresh sequence state. Reported per size: median ms per frame,
ms per megapixel, and peak memory of the steps:
- peak_traced_mib: tracemalloc's peak over one extra step: the numpy arrays and Python objects one
  step allocates (the working memory that grows with the frame), exact whatever the allocator keeps.
- peak_rss_mib: the process's peak resident set (VmHWM, reset through /proc/self/clear_refs once the
  frames are built) minus its resident set just before the warm-up step; includes what the traced
  number cannot see (ONNX Runtime and OIDN buffers, numba compilation) and so a size-independent
  start-up part. Linux only; None elsewhere.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
import tracemalloc
from pathlib import Path
from typing import Any

import numpy as np

from service.process import configure

SIZES = ((128, 128), (256, 256), (512, 512), (1280, 720), (1920, 1080))  # (width, height)
WORKER_TIMEOUT_S = 900  # per (method, size) process


def _status_kib(field: str) -> int | None:
    try:
        with open("/proc/self/status") as handle:
            for line in handle:
                if line.startswith(field + ":"):
                    return int(line.split()[1])
    except OSError:
        pass
    return None


def _reset_peak_rss() -> bool:
    try:
        with open("/proc/self/clear_refs", "w") as handle:
            handle.write("5")  # Linux: reset VmHWM to the current resident set
        return True
    except OSError:
        return False


def measure(method_name: str, width: int, height: int, frames: int) -> dict[str, Any]:
    """Time and measure one method at one size, in this process (the worker's body)."""
    from bench.methods import ANCHORS, anchor_method, pipeline_method
    from bench.run import WARMUP_FRAMES
    from bench.synthetic import synthetic_sequence
    from service.frame import Frame

    method = anchor_method(method_name) if method_name in ANCHORS else pipeline_method(method_name)
    count = max(frames, WARMUP_FRAMES)
    sequence = [Frame.from_buffers(layers) for layers in synthetic_sequence(height, width, count, spp=2)]
    pipeline = method.make()
    reset = _reset_peak_rss()
    base_kib = _status_kib("VmRSS")
    warm = pipeline.start(height, width)
    for frame in sequence[:WARMUP_FRAMES]:
        _, warm = pipeline.step(frame, warm)
    state = pipeline.start(height, width)
    ms = []
    for frame in sequence[:frames]:
        start = time.perf_counter()
        _, state = pipeline.step(frame, state)
        ms.append(1e3 * (time.perf_counter() - start))
    peak_kib = _status_kib("VmHWM")
    tracemalloc.start()
    pipeline.step(sequence[-1], state)
    _, traced_peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    median = float(np.median(ms))
    return {
        "method": method_name,
        "width": width,
        "height": height,
        "ms": ms,
        "ms_per_frame": median,
        "ms_per_megapixel": median / (width * height / 1e6),
        "peak_rss_mib": (peak_kib - base_kib) / 1024 if reset and peak_kib and base_kib else None,
        "peak_traced_mib": traced_peak / 2**20,
    }


def measure_in_subprocess(method_name: str, width: int, height: int, frames: int) -> dict[str, Any]:
    """`measure` in a fresh interpreter; a failure or timeout becomes a record with `error`."""
    args = json.dumps([method_name, width, height, frames])
    try:
        done = subprocess.run([sys.executable, "-m", "bench.scaling", args], capture_output=True, text=True,
                              timeout=WORKER_TIMEOUT_S, check=False)
    except subprocess.TimeoutExpired:
        return {"method": method_name, "width": width, "height": height, "error": f"timeout {WORKER_TIMEOUT_S} s"}
    if done.returncode != 0:
        tail = done.stderr.strip().splitlines()[-1:] or [f"exit status {done.returncode}"]
        return {"method": method_name, "width": width, "height": height, "error": tail[0]}
    return json.loads(done.stdout.strip().splitlines()[-1])


def run_scaling(methods: list[str], sizes: tuple[tuple[int, int], ...] = SIZES, frames: int = 3,
                progress: bool = True) -> list[dict[str, Any]]:
    """Every method at every size (each in its own process), smallest size first."""
    from tqdm import tqdm

    records = []
    with tqdm(total=len(methods) * len(sizes), desc="scaling", unit="run", disable=not progress) as bar:
        for method in methods:
            for width, height in sizes:
                bar.set_postfix_str(f"{method} {width}x{height}")
                records.append(measure_in_subprocess(method, width, height, frames))
                bar.update(1)
    return records


def table(records: list[dict[str, Any]]) -> str:
    """Markdown: one row per method, per size 'ms/MP (ms per frame; traced peak / RSS peak MiB)'."""
    sizes = list(dict.fromkeys((r["width"], r["height"]) for r in records))
    methods = list(dict.fromkeys(r["method"] for r in records))
    lines = ["| method | " + " | ".join(f"{w}x{h}" for w, h in sizes) + " |", "|" + "---|" * (len(sizes) + 1)]
    for method in methods:
        cells = []
        for w, h in sizes:
            rec = next(r for r in records if r["method"] == method and (r["width"], r["height"]) == (w, h))
            if "error" in rec:
                cells.append("error")
                continue
            rss = "?" if rec["peak_rss_mib"] is None else f"{rec['peak_rss_mib']:.0f}"
            cells.append(f"{rec['ms_per_megapixel']:.0f} ({rec['ms_per_frame']:.0f} ms; "
                         f"{rec['peak_traced_mib']:.0f} / {rss} MiB)")
        lines.append(f"| {method} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def plot(records: list[dict[str, Any]], path: Path) -> None:
    """ms per megapixel and peak memory against megapixels, log-log, one line per method."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 3.8), dpi=100)
    for method in dict.fromkeys(r["method"] for r in records):
        ok = [r for r in records if r["method"] == method and "error" not in r]
        mp = [r["width"] * r["height"] / 1e6 for r in ok]
        axes[0].plot(mp, [r["ms_per_megapixel"] for r in ok], marker="o", label=method)
        axes[1].plot(mp, [max(r["peak_traced_mib"], 0.1) for r in ok], marker="o", label=method)
    labels = ("ms per megapixel", "peak memory allocated by one step (traced), MiB")
    for ax, label in zip(axes, labels, strict=True):
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("megapixels")
        ax.set_ylabel(label)
        ax.grid(True, which="both", alpha=0.25)
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


if __name__ == "__main__":  # worker: python -m bench.scaling '["name", width, height, frames]'
    configure()
    name, w, h, n = json.loads(sys.argv[1])
    print(json.dumps(measure(name, w, h, n)))
