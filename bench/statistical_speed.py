"""Milliseconds per frame of `statistical` (radius 6 and 20) and `svgf` beside OIDN, in one run.

    python -m bench.statistical_speed --sizes 256x256 1280x720 --repeats 5

Like bench.classical_speed (which times pipelines with default options from a fresh state), but with
pipeline options and steady-state temporal pipelines: `svgf` steps through consecutive synthetic
frames with its history kept (after a warm-up of 4 frames), so the timing is that of a running
sequence; `svgf-first` times a first frame (spatial variance everywhere); `reproject` and `reproject-numpy`
time the shared reprojection stage alone (compiled and numpy reference) on svgf's (H, W, 6) history with
depth and normal checks. All methods take turns for
`--repeats` rounds so that load from other processes falls on all of them alike; median and min.
"""

from __future__ import annotations

import argparse
import os
import statistics
import time
from collections.abc import Callable

import numba
import numpy as np

from bench.synthetic import synthetic_frame
from service import pipelines
from service.frame import Frame
from service.stages import reprojection

METHODS = {
    "statistical-r6": ("statistical", {"radius": 6}),
    "statistical-r20": ("statistical", {"radius": 20}),
    "svgf": ("svgf", {}),
    "svgf-first": ("svgf", {}),
    "reproject": ("reproject", {}),
    "reproject-numpy": ("reproject_numpy", {}),
}


def _runners(height: int, width: int, repeats: int, names: list[str]) -> dict[str, Callable[[], None]]:
    rng = np.random.default_rng(0)
    frames = [Frame.from_buffers(synthetic_frame(height, width, t, rng=rng)) for t in range(5 + repeats + 1)]
    runners: dict[str, Callable[[], None]] = {}
    for label in names:
        name, options = METHODS[label]
        if name.startswith("reproject"):
            runners[label] = _reprojection_runner(getattr(reprojection, name), frames[0], frames[1], rng)
            continue
        pipeline = pipelines.get(name, **options)
        if label == "svgf":
            state = pipeline.start(height, width)
            for frame in frames[:5]:
                _, state = pipeline.step(frame, state)
            sequence = iter(frames[5:])

            def run(pipeline=pipeline, state=state, sequence=sequence) -> None:
                pipeline.step(next(sequence), state)
        else:
            def run(pipeline=pipeline) -> None:
                pipeline.step(frames[0], pipeline.start(height, width))

            run()  # compile or load the numba cache
        runners[label] = run
    import pyoidn

    layers = frames[0]
    color = np.ascontiguousarray(np.maximum(layers["color"], 0.0))
    albedo = np.ascontiguousarray(np.clip(layers["albedo"], 0.0, 1.0))
    normal = np.ascontiguousarray(np.clip(layers["normal"], -1.0, 1.0))

    def oidn() -> None:
        pyoidn.denoise(color, albedo, normal, hdr=True, quality="high")

    oidn()
    runners["oidn-high"] = oidn
    return runners


def _reprojection_runner(warp: Callable, prev: Frame, frame: Frame, rng: np.random.Generator) -> Callable[[], None]:
    history = rng.random((frame.height, frame.width, 6), dtype=np.float32)
    kwargs = {"depth": frame["depth"], "prev_depth": prev["depth"], "normal": frame["normal"],
              "prev_normal": prev["normal"]}

    def run() -> None:
        warp(history, frame["motion"], **kwargs)

    run()
    return run


def main() -> None:
    parser = argparse.ArgumentParser(prog="python -m bench.statistical_speed", description=__doc__.split("\n")[0])
    parser.add_argument("--sizes", nargs="+", default=["256x256", "1280x720"], help="WxH frame sizes")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--methods", nargs="+", default=list(METHODS), choices=list(METHODS))
    parser.add_argument("--threading-layer", choices=["default", "omp", "workqueue", "tbb"], default="default",
                        help="numba threading layer (the GNU OpenMP default spins at barriers, which a busy shared "
                             "machine punishes)")
    args = parser.parse_args()
    if args.threading_layer != "default":
        numba.config.THREADING_LAYER = args.threading_layer
    print(f"cpus: {os.cpu_count()}, load average: {' '.join(f'{v:.2f}' for v in os.getloadavg())}", flush=True)
    for size in args.sizes:
        width, height = map(int, size.split("x"))
        runners = _runners(height, width, args.repeats, args.methods)
        times: dict[str, list[float]] = {label: [] for label in runners}
        for _ in range(args.repeats):
            for label, run in runners.items():
                start = time.perf_counter()
                run()
                times[label].append(1e3 * (time.perf_counter() - start))
        oidn = statistics.median(times["oidn-high"])
        for label, values in times.items():
            median = statistics.median(values)
            print(f"{size:>10} {label:<16} median {median:8.1f} ms  min {min(values):8.1f} ms  "
                  f"{median / oidn:5.2f} x OIDN-high", flush=True)


if __name__ == "__main__":
    main()
