"""Milliseconds per frame of registered pipelines beside Intel Open Image Denoise, in one run, and
optionally their relL2 on a sequence folder in the same run.

    python -m bench.classical_speed                                # crossregression, bmfr, flr; 256x256, 1280x720
    python -m bench.classical_speed --pipelines flr bilateral --sizes 640x360 --repeats 7
    python -m bench.classical_speed --pipelines statistical:radius=6 svgf crossreg --sample models/data/samples/shadows

Every method denoises the same synthetic frame (bench.synthetic, all layers) through `Pipeline.step`
(layer check, emission split and guard included), each on one sequence state, so a temporal pipeline is
timed with its history after the first step. OIDN runs as the benchmark anchors (bench.methods: HDR,
albedo and normal, emission split), run through the same `step`. WARMUP_ROUNDS untimed rounds first, the
methods taking turns (numba compilation or cache load, OIDN device creation, and the transient that
follows), then they take turns for `--repeats` timed rounds so that load from other processes falls on all
of them alike; the median, the mean and the minimum are reported (the mean counts the frames where a
pipeline does periodic work, such as `auto`'s evaluation every few frames, which the median can skip).
With `--sample DIR`, each method then denoises that sequence in order on a fresh state and the mean
0.1%-trimmed relL2 against its `reference` is reported.
"""

from __future__ import annotations

import argparse
import os
import statistics
import time

import numpy as np

from bench.methods import OidnFastAnchor, OidnHighAnchor, OidnHighDefaultAnchor, pipeline_method
from bench.synthetic import synthetic_frame
from service import pipelines
from service.exr import list_sequence, read_frame
from service.frame import Frame
from service.metrics import TRIM_FRACTION, rel_l2
from service.pipelines import Pipeline
from service.process import configure

DEFAULT_PIPELINES = ("crossregression", "bmfr", "flr")
# Untimed rounds before the timed ones. After only one, the steps of a method taking turns with OIDN
# (whose first call allocates and frees its buffers) were not yet steady; run alone, they were.
WARMUP_ROUNDS = 4
# `high-default` is the call issue 3's speed targets name: pyoidn.denoise(color, albedo, normal, hdr=True,
# quality='high'); `high` is the benchmark's anchor (clean_aux, a larger network at quality high).
OIDN = {"high-default": OidnHighDefaultAnchor, "high": OidnHighAnchor, "fast": OidnFastAnchor}


def make_methods(specs: list[str], oidn: list[str]) -> dict[str, Pipeline]:
    """Label -> pipeline object. specs: NAME or NAME:KEY=VALUE,KEY=VALUE (pipeline options); oidn: keys of OIDN."""
    methods: dict[str, Pipeline] = {}
    for spec in specs:
        methods[spec] = pipeline_method(spec).make()
    for key in oidn:
        anchor = OIDN[key]()
        methods[anchor.name] = anchor
    return methods


def time_methods(methods: dict[str, Pipeline], height: int, width: int, repeats: int) -> dict[str, list[float]]:
    """Wall times in ms of each method's `step` on one synthetic frame of height x width, `repeats` each."""
    frame = Frame.from_buffers(synthetic_frame(height, width, 1, rng=np.random.default_rng(0)))
    states = {label: method.start(height, width) for label, method in methods.items()}
    for _ in range(WARMUP_ROUNDS):
        for label, method in methods.items():
            _, states[label] = method.step(frame, states[label])
    times: dict[str, list[float]] = {label: [] for label in methods}
    for _ in range(repeats):
        for label, method in methods.items():
            start = time.perf_counter()
            _, states[label] = method.step(frame, states[label])
            times[label].append(1000.0 * (time.perf_counter() - start))
    return times


def sample_rel_l2(methods: dict[str, Pipeline], folder: str) -> tuple[dict[str, float], float, tuple[int, int]]:
    """(label -> mean trimmed relL2 over the sequence's frames, the noisy input's, (width, height))."""
    frames = [read_frame(path) for path in list_sequence(folder)]
    noisy = float(np.mean([rel_l2(f["color"], f["reference"], trim=TRIM_FRACTION) for f in frames]))
    errors = {}
    for label, method in methods.items():
        state = method.start(frames[0].height, frames[0].width)
        values = []
        for frame in frames:
            out, state = method.step(frame, state)
            values.append(rel_l2(out["color"], frame["reference"], trim=TRIM_FRACTION))
        errors[label] = float(np.mean(values))
    return errors, noisy, (frames[0].width, frames[0].height)


def main() -> int:
    configure()
    parser = argparse.ArgumentParser(prog="python -m bench.classical_speed", description=__doc__.split("\n")[0])
    parser.add_argument("--pipelines", nargs="+", default=list(DEFAULT_PIPELINES),
                        help="registered pipeline names, or NAME:KEY=VALUE,... with options")
    parser.add_argument("--sizes", nargs="+", default=["256x256", "1280x720"], help="WxH frame sizes")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--oidn", nargs="*", default=["high-default", "high"], choices=list(OIDN),
                        help="OIDN anchors; ratios are against the first (none: no anchor)")
    parser.add_argument("--sample", help="also report relL2 on this sequence folder (frames with `reference`)")
    args = parser.parse_args()
    unknown = sorted({spec.partition(":")[0] for spec in args.pipelines} - set(pipelines.names()))
    if unknown:
        parser.error(f"unknown pipeline(s) {', '.join(unknown)}; available: {', '.join(pipelines.names())}")
    oidn_label = OIDN[args.oidn[0]].name if args.oidn else None
    print(f"cpus: {os.cpu_count()}, load average: {' '.join(f'{v:.2f}' for v in os.getloadavg())}")
    for size in args.sizes:
        width, height = (int(v) for v in size.lower().split("x"))
        times = time_methods(make_methods(args.pipelines, args.oidn), height, width, args.repeats)
        print(f"\n{width}x{height}, {args.repeats} repeats (ms per frame)")
        print(f"{'method':<22}{'median':>10}{'mean':>10}{'min':>10}  x faster than {oidn_label} (medians)")
        for label, values in times.items():
            median = statistics.median(values)
            ratio = f"{statistics.median(times[oidn_label]) / median:.1f}" if oidn_label else "-"
            print(f"{label:<22}{median:>10.1f}{statistics.mean(values):>10.1f}{min(values):>10.1f}{ratio:>12}")
    if args.sample:
        errors, noisy, (width, height) = sample_rel_l2(make_methods(args.pipelines, args.oidn), args.sample)
        print(f"\n{args.sample} ({width}x{height}), mean relL2 (0.1% trimmed); noisy input {noisy:.4f}")
        for label, value in errors.items():
            print(f"{label:<22}{value:>10.4f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
