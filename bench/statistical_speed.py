"""Milliseconds per frame of `statistical` (radius 6 and 20) and `svgf` beside OIDN, in one run.

    python -m bench.statistical_speed --sizes 256x256 1280x720 --repeats 5

Like bench.classical_speed (which times pipelines with default options from a fresh state), but with
pipeline options and steady-state temporal pipelines: `svgf` steps through consecutive synthetic
frames with its history kept (after a warm-up of 4 frames), so the timing is that of a running
sequence; `svgf-first` times a first frame (spatial variance everywhere). All methods take turns for
`--repeats` rounds so that load from other processes falls on all of them alike; median and min.
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections.abc import Callable

import numpy as np

from bench.synthetic import synthetic_frame
from service import pipelines
from service.frame import Frame

METHODS = {
    "statistical-r6": ("statistical", {"radius": 6}),
    "statistical-r20": ("statistical", {"radius": 20}),
    "svgf": ("svgf", {}),
    "svgf-first": ("svgf", {}),
}


def _runners(height: int, width: int, repeats: int, names: list[str]) -> dict[str, Callable[[], None]]:
    rng = np.random.default_rng(0)
    frames = [Frame.from_buffers(synthetic_frame(height, width, t, rng=rng)) for t in range(5 + repeats + 1)]
    runners: dict[str, Callable[[], None]] = {}
    for label in names:
        name, options = METHODS[label]
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


def main() -> None:
    parser = argparse.ArgumentParser(prog="python -m bench.statistical_speed", description=__doc__.split("\n")[0])
    parser.add_argument("--sizes", nargs="+", default=["256x256", "1280x720"], help="WxH frame sizes")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--methods", nargs="+", default=list(METHODS), choices=list(METHODS))
    args = parser.parse_args()
    for size in args.sizes:
        width, height = map(int, size.split("x"))
        runners = _runners(height, width, args.repeats, args.methods)
        times: dict[str, list[float]] = {label: [] for label in runners}
        for _ in range(args.repeats):
            for label, run in runners.items():
                start = time.perf_counter()
                run()
                times[label].append(1e3 * (time.perf_counter() - start))
        for label, values in times.items():
            print(f"{size:>10} {label:<16} median {statistics.median(values):8.1f} ms  min {min(values):8.1f} ms",
                  flush=True)


if __name__ == "__main__":
    main()
