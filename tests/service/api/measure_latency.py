"""Latency and throughput of the HTTP service against calling the pipeline directly, in one run.

    python -m tests.service.api.measure_latency [--size 256] [--frames 40] [--pipeline bilateral] [--layers used]

Starts `python -m service serve` on a free loopback port, then times, on the same frames:
direct pipeline.step; direct decode + step + encode (what the server does per frame); REST
/v1/denoise one frame at a time on a kept-alive connection; a session's WebSocket stream with one
frame in flight (latency) and with four in flight (throughput). Not a test: numbers depend on the
machine and its load.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

from bench.synthetic import synthetic_sequence
from service import pipelines
from service.api import codec
from service.client import Client
from service.exr import encode_frame
from service.frame import Frame
from tests.service.api.conftest import ROOT, start_subprocess_server, stop


def summary(name: str, ms: list[float]) -> str:
    a = np.asarray(ms)
    return (f"{name:<34} p50 {np.percentile(a, 50):7.1f} ms   p95 {np.percentile(a, 95):7.1f} ms   "
            f"{1e3 * len(a) / a.sum():6.1f} frames/s")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=256)
    parser.add_argument("--frames", type=int, default=40)
    parser.add_argument("--pipeline", default="bilateral")
    parser.add_argument("--layers", choices=["all", "used"], default="all",
                        help="send every layer of the frame format, or only those the pipeline uses")
    args = parser.parse_args()
    layers = synthetic_sequence(height=args.size, width=args.size, frames=8, spp=4, seed=5)
    if args.layers == "used":
        cls = pipelines.pipeline_class(args.pipeline)
        layers = [{k: v for k, v in x.items() if k in (*cls.requires, *cls.optional)} for x in layers]
    sequence = [layers[i % len(layers)] for i in range(args.frames)]
    exr = [encode_frame(x) for x in sequence]
    frames = [Frame.from_buffers(x) for x in sequence]
    pipeline = pipelines.get(args.pipeline)
    print(f"{args.pipeline}, {args.size}x{args.size}, {args.layers} layers, {args.frames} frames, "
          f"EXR in {len(exr[0]) / 1e6:.2f} MB, {os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.1f}")
    state = pipeline.start(args.size, args.size)

    def direct(i: int) -> None:
        nonlocal state
        _, state = pipeline.step(frames[i], state)

    def direct_codec(i: int) -> None:
        nonlocal state
        out, state = pipeline.step(codec.decode(exr[i], 8192, 8192), state)
        codec.encode(out, codec.Output())

    log = Path(os.environ.get("TMPDIR", "/tmp")) / "mcdenoise_measure_server.log"
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    env.pop("MCDENOISE_API_KEY", None)
    url, proc = start_subprocess_server(sys.executable, env, log)
    try:
        with Client(url) as client, client.session(args.pipeline, args.size, args.size) as rest_session, \
                client.session(args.pipeline, args.size, args.size) as ws_session:
            stream = ws_session.stream(iter(exr * 2), window=1)
            methods = {
                "direct pipeline.step": direct,
                "direct decode+step+encode": direct_codec,
                "REST /v1/denoise": lambda i: client.denoise(exr[i], args.pipeline),
                "REST session frames": lambda i: rest_session.denoise(exr[i]),
                "WebSocket stream, 1 in flight": lambda i: next(stream),
            }
            for fn in methods.values():  # warm-up
                fn(0)
            ms: dict[str, list[float]] = {name: [] for name in methods}
            for i in range(args.frames):  # round robin: every method sees the same machine load
                for name, fn in methods.items():
                    t = time.perf_counter()
                    fn(i)
                    ms[name].append(1e3 * (time.perf_counter() - t))
            stream.close()
            for name, values in ms.items():
                print(summary(name, values))
            with client.session(args.pipeline, args.size, args.size) as session:
                start = time.perf_counter()
                answers = list(session.stream(exr, window=4))
                wall = time.perf_counter() - start
                assert all(isinstance(a, bytes) for a in answers)
                print(f"{'WebSocket stream, 4 in flight':<34} {len(answers) / wall:6.1f} frames/s "
                      f"({1e3 * wall / len(answers):.1f} ms/frame)")
    finally:
        stop(proc)
    return 0


if __name__ == "__main__":
    sys.exit(main())
