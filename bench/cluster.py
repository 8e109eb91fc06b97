"""Throughput of `python -m service cluster` with 1, 2, 3, ... replicas on this machine (docs/benchmarks.md).

    python -m bench.cluster [--replicas 1 2 3] [--sessions 6] [--frames 20] [--size 128x128]
                            [--pipeline bilateral] [--out FILE.md]

For each replica count, starts the cluster on free loopback ports (the replicas share the CPUs fairly,
service/cluster/replicas.py), opens `--sessions` sessions at once through HAProxy, half over REST and
half over the WebSocket stream (bench/load.py's sessions, every answer checked against the pipeline
called directly), and measures frames/s from the first frame to the last answer. Prints a markdown table
(and writes it to --out); exit status 1 when any frame was lost, reordered or refused.
"""

from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

from bench.load import ROOT, expected_outputs, run_session
from bench.synthetic import synthetic_sequence
from service.client import Client
from service.cluster.replicas import free_port
from service.exr import encode_frame
from service.process import configure

START_TIMEOUT_S = 300.0
WINDOW = 2  # WebSocket frames in flight per streaming session


def start_cluster(replicas: int, log: Path, settings: dict[str, str], stats_port: int = 0,
                  timeout_s: float = START_TIMEOUT_S) -> tuple[str, subprocess.Popen]:
    """`python -m service cluster --replicas N` on a free port, its output to `log`, with the MCDENOISE_*
    `settings` (no API key); (url, process) once it says it runs. RuntimeError, the cluster stopped, when it
    exits or is not running within `timeout_s` seconds. The caller stops it (SIGTERM)."""
    port = free_port()
    env = {**os.environ, "PYTHONPATH": str(ROOT), **settings}
    env.pop("MCDENOISE_API_KEY", None)
    with open(log, "wb") as sink:
        proc = subprocess.Popen([sys.executable, "-m", "service", "cluster", "--replicas", str(replicas), "--port",
                                 str(port), "--stats-port", str(stats_port)], cwd=ROOT, env=env, stdout=sink,
                                stderr=subprocess.STDOUT)
    deadline = time.monotonic() + timeout_s
    while "cluster: " not in log.read_text():
        if proc.poll() is not None or time.monotonic() > deadline:
            proc.terminate()  # the cluster stops its replicas and HAProxy (a kill would orphan them)
            proc.wait(timeout=60)
            raise RuntimeError(f"the cluster did not start:\n{log.read_text()[-2000:]}")
        time.sleep(0.1)
    return f"http://127.0.0.1:{port}", proc


def measure(replicas: int, args: argparse.Namespace, bodies, expected, size) -> tuple[float, float, int]:
    """(frames/s, latency p50 in ms, frames lost, reordered or refused) with `replicas` replicas."""
    with tempfile.TemporaryDirectory() as folder:
        url, proc = start_cluster(replicas, Path(folder) / "cluster.log",
                                  {"MCDENOISE_MAX_SESSIONS": "64", "MCDENOISE_MAX_INFLIGHT": "64"})
        try:
            with Client(url) as client:  # one session per replica and more: every replica builds the pipeline
                for session in [client.session(args.pipeline, *size) for _ in range(2 * replicas)]:
                    session.close()
            start = time.perf_counter()
            with ThreadPoolExecutor(args.sessions) as pool:
                runs = list(pool.map(lambda s: run_session(url, args.pipeline, bodies[s], expected[s], s % 2 == 1,
                                                           WINDOW, size), range(args.sessions)))
            wall = time.perf_counter() - start
        finally:
            proc.send_signal(signal.SIGTERM)
            proc.wait(timeout=60)
    latency = np.concatenate([r.latency_ms for r in runs])
    failed = sum(r.lost + r.wrong + r.errors for r in runs)
    return args.sessions * args.frames / wall, float(np.percentile(latency, 50)), failed


def main(argv: list[str] | None = None) -> int:
    configure()  # an entry point that runs the service's kernels (service/process.py)
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--replicas", type=int, nargs="+", default=[1, 2, 3])
    parser.add_argument("--sessions", type=int, default=6, help="sessions at once, half REST, half WebSocket")
    parser.add_argument("--frames", type=int, default=20, help="frames per session")
    parser.add_argument("--size", default="128x128", help="WxH")
    parser.add_argument("--pipeline", default="bilateral")
    parser.add_argument("--out", type=Path, help="also write the table to this markdown file")
    args = parser.parse_args(argv)
    if min(args.replicas) < 1 or args.sessions < 1 or args.frames < 1:
        parser.error("--replicas, --sessions and --frames must be at least 1")
    width, height = (int(v) for v in args.size.lower().split("x"))
    sequences = [synthetic_sequence(height=height, width=width, frames=args.frames, spp=2, seed=100 + s)
                 for s in range(args.sessions)]
    bodies = [[encode_frame(layers) for layers in seq] for seq in sequences]
    expected = [expected_outputs(args.pipeline, seq) for seq in sequences]
    lines = [f"{args.pipeline}, {args.sessions} sessions x {args.frames} frames of {width}x{height} (half REST, half "
             f"WebSocket window {WINDOW}), {len(os.sched_getaffinity(0))} CPUs", "",
             "| replicas | frames/s | speed-up | latency p50 ms | lost, reordered or refused |",
             "|---|---|---|---|---|"]
    failed, base = 0, None
    for n in args.replicas:
        fps, p50, bad = measure(n, args, bodies, expected, (width, height))
        base = base or fps
        failed += bad
        lines.append(f"| {n} | {fps:.1f} | {fps / base:.2f} | {p50:.0f} | {bad} |")
    table = "\n".join(lines)
    print(table)
    if args.out:
        args.out.write_text(table + "\n")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
