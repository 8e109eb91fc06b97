"""Milliseconds per frame of registered pipelines beside Intel Open Image Denoise, in one run.

    python -m bench.classical_speed                                # crossregression, bmfr, flr; 256x256, 1280x720
    python -m bench.classical_speed --pipelines flr bilateral --sizes 640x360 --repeats 7
    python -m bench.classical_speed --pipelines statistical:radius=6 svgf crossreg

Every method denoises the same synthetic frame (bench.synthetic, all layers) through `Pipeline.step`
(layer check, emission split and guard included), each on one sequence state, so a temporal pipeline is
timed with its history after the first step; OIDN gets pyoidn.denoise(color, albedo, normal,
hdr=True, quality=...) on the same frame. One untimed call each first (numba compilation or cache load,
OIDN device creation), then the methods take turns for `--repeats` rounds so that load from other
processes falls on all of them alike; the median and the minimum of the wall times are reported.
"""

from __future__ import annotations

import argparse
import os
import statistics
import time
from collections.abc import Callable

import numpy as np

from bench.synthetic import synthetic_frame
from service import pipelines
from service.cli import parse_options
from service.frame import Frame

DEFAULT_PIPELINES = ("crossregression", "bmfr", "flr")


def _pipeline_runner(spec: str, frame: Frame) -> Callable[[], None]:
    """A runner stepping one sequence state, so temporal pipelines are timed in steady state (with
    history) after the warm-up step. spec: NAME or NAME:KEY=VALUE,KEY=VALUE (pipeline options)."""
    name, _, option_text = spec.partition(":")
    pipeline = pipelines.get(name, **parse_options(option_text.split(",") if option_text else []))
    state = pipeline.start(frame.height, frame.width)

    def run() -> None:
        nonlocal state
        _, state = pipeline.step(frame, state)

    return run


def _oidn_runner(layers: dict[str, np.ndarray], quality: str) -> Callable[[], None]:
    import pyoidn

    color = np.ascontiguousarray(np.maximum(layers["color"], 0.0))
    albedo = np.ascontiguousarray(np.clip(layers["albedo"], 0.0, 1.0))
    normal = np.ascontiguousarray(np.clip(layers["normal"], -1.0, 1.0))

    def run() -> None:
        pyoidn.denoise(color, albedo, normal, hdr=True, quality=quality)

    return run


def time_methods(
    names: list[str], height: int, width: int, repeats: int, oidn_quality: str | None = "high"
) -> dict[str, list[float]]:
    """Wall times in ms of each method on one synthetic frame of height x width, `repeats` each."""
    layers = synthetic_frame(height, width, 1, rng=np.random.default_rng(0))
    frame = Frame.from_buffers(layers)
    runners = {name: _pipeline_runner(name, frame) for name in names}
    if oidn_quality is not None:
        runners[f"oidn-{oidn_quality}"] = _oidn_runner(layers, oidn_quality)
    for run in runners.values():
        run()  # warm-up: compilation, caches, device creation
    times: dict[str, list[float]] = {name: [] for name in runners}
    for _ in range(repeats):
        for name, run in runners.items():
            start = time.perf_counter()
            run()
            times[name].append(1000.0 * (time.perf_counter() - start))
    return times


def main() -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.classical_speed", description=__doc__.split("\n")[0])
    parser.add_argument("--pipelines", nargs="+", default=list(DEFAULT_PIPELINES),
                        help="registered pipeline names, or NAME:KEY=VALUE,... with options")
    parser.add_argument("--sizes", nargs="+", default=["256x256", "1280x720"], help="WxH frame sizes")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--oidn", default="high", choices=["high", "balanced", "fast", "none"])
    args = parser.parse_args()
    unknown = sorted({spec.partition(":")[0] for spec in args.pipelines} - set(pipelines.names()))
    if unknown:
        parser.error(f"unknown pipeline(s) {', '.join(unknown)}; available: {', '.join(pipelines.names())}")
    print(f"cpus: {os.cpu_count()}, load average: {' '.join(f'{v:.2f}' for v in os.getloadavg())}")
    for size in args.sizes:
        width, height = (int(v) for v in size.lower().split("x"))
        times = time_methods(args.pipelines, height, width, args.repeats, None if args.oidn == "none" else args.oidn)
        oidn = times.get(f"oidn-{args.oidn}")
        print(f"\n{width}x{height}, {args.repeats} repeats (ms per frame)")
        print(f"{'method':<18}{'median':>10}{'min':>10}{'x faster than OIDN':>22}")
        for name, values in times.items():
            median = statistics.median(values)
            ratio = f"{statistics.median(oidn) / median:.1f}" if oidn else "-"
            print(f"{name:<18}{median:>10.1f}{min(values):>10.1f}{ratio:>22}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
