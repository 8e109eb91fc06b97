"""Cold first frame of each named pipeline: a new process per pipeline with an empty numba cache
(NUMBA_CACHE_DIR a new temporary folder), which reads the first frame of a sequence folder and times
`Pipeline.start` and two `step`s; the first step includes compiling every kernel it calls. Prints the
seconds of the first frame, the milliseconds of the second, and the kernels that took longest to compile
(numba's compile timer per kernel, inclusive of what it calls).

    python -m bench.cold_start                                   # crossregression flr bmfr; bundled sample
    python -m bench.cold_start --pipelines crossreg --sample DIR --kernels 8

The machine's load average is printed first: on a shared machine, compare runs made one after the other.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time

from service.process import configure

DEFAULT_PIPELINES = ("crossregression", "flr", "bmfr")
DEFAULT_SAMPLE = "models/data/samples/shadows"


def child(name: str, sample: str, kernels: int) -> dict:
    """In the cold process: time the pipeline on the sample's first two frames, collect compile times."""
    configure()
    from numba.core.dispatcher import Dispatcher

    from service import pipelines
    from service.exr import list_sequence, read_frame

    paths = list_sequence(sample)
    frames = [read_frame(path) for path in paths[:2]]
    pipeline = pipelines.get(name)
    state = pipeline.start(frames[0].height, frames[0].width)
    times = []
    for frame in frames:
        start = time.perf_counter()
        _, state = pipeline.step(frame, state)
        times.append(time.perf_counter() - start)
    state.close()
    compiled = []
    for module_name, module in list(sys.modules.items()):
        if not module_name.startswith("service."):
            continue
        for attr, value in list(vars(module).items()):
            if isinstance(value, Dispatcher) and value.py_func.__module__ == module_name:
                for result in value.overloads.values():
                    seconds = (result.metadata or {}).get("timers", {}).get("compiler_lock", 0.0)
                    compiled.append((seconds, f"{module_name}.{attr}"))
    compiled.sort(reverse=True)
    return {"first_s": times[0], "second_ms": 1e3 * times[1] if len(times) > 1 else None,
            "kernels": compiled[:kernels]}


def main() -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.cold_start", description=__doc__.split("\n")[0])
    parser.add_argument("--pipelines", nargs="+", default=list(DEFAULT_PIPELINES))
    parser.add_argument("--sample", default=DEFAULT_SAMPLE, help="sequence folder whose first frames are used")
    parser.add_argument("--kernels", type=int, default=5, help="how many of the slowest compiles to list")
    parser.add_argument("--child", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        print(json.dumps(child(args.child, args.sample, args.kernels)))
        return 0
    print(f"cpus: {os.cpu_count()}, load average: {' '.join(f'{v:.2f}' for v in os.getloadavg())}")
    for name in args.pipelines:
        with tempfile.TemporaryDirectory(prefix="numba-cold-") as cache:
            env = {**os.environ, "NUMBA_CACHE_DIR": cache}
            run = subprocess.run([sys.executable, "-m", "bench.cold_start", "--child", name, "--sample", args.sample,
                                  "--kernels", str(args.kernels)], env=env, capture_output=True, text=True)
        if run.returncode != 0:
            print(f"{name}: failed\n{run.stderr[-2000:]}", file=sys.stderr)
            return 1
        result = json.loads(run.stdout.strip().splitlines()[-1])
        second = "" if result["second_ms"] is None else f", second frame {result['second_ms']:.1f} ms"
        print(f"{name}: first frame {result['first_s']:.1f} s{second}")
        for seconds, kernel in result["kernels"]:
            print(f"    {seconds:6.1f} s  {kernel}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
