"""Load test of the HTTP service: concurrent sessions streaming frames, what it sustains on this machine.

    python -m bench.load [--sessions 8] [--frames 30] [--size 256x256] [--pipeline crossregression]
                         [--window 4] [--workers 2] [--url URL]

Starts `python -m service serve` on a free loopback port (or uses --url) with room for every frame in
flight (MCDENOISE_MAX_INFLIGHT), opens `--sessions` sessions at once, half sending their frames one
request at a time over REST (a frame answered `503 busy` is sent again, and counted) and half over the
WebSocket stream with `--window` frames in flight, each on its own connection. Every answer is checked
against the pipeline called directly on the same frames (computed before the clock starts): a frame
answered with another frame's output, out of order, or not at all counts as lost or reordered. Prints
sessions x frames, wall time, frames/s, per-frame latency p50/p95/max (REST: the request; WebSocket: from
the frame's send to its answer, so it includes the frames queued ahead of it in the window) and the error
count; exit status 1 when any frame was lost, reordered or refused. Numbers depend on the machine and its
load.
"""

from __future__ import annotations

import argparse
import os
import socket
import subprocess
import sys
import time
import urllib.request
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from bench.synthetic import synthetic_sequence
from service import pipelines
from service.client import Client, ServiceError, Session
from service.exr import encode_frame, read_frame
from service.frame import Frame
from service.process import configure

ROOT = Path(__file__).resolve().parents[1]
BUSY_RETRY_S = 0.05  # wait before resending a frame answered 503 busy (the service says Retry-After: 1)


@dataclass
class SessionRun:
    """What one session saw."""

    latency_ms: list[float] = field(default_factory=list)  # per answered frame
    errors: int = 0  # frames answered with an error (after retries of `busy`)
    busy: int = 0  # 503 busy answers, each retried after its Retry-After
    lost: int = 0  # frames never answered
    wrong: int = 0  # frames answered with another frame's output (reordered or mixed with another session)


def expected_outputs(name: str, frames: list[dict[str, np.ndarray]]) -> list[np.ndarray]:
    """(H, W, 3) float32 `color` of the pipeline called directly, frame after frame (what the service must answer)."""
    pipeline = pipelines.get(name)
    state = pipeline.start(*frames[0]["color"].shape[:2])
    out = []
    for layers in frames:
        result, state = pipeline.step(Frame.from_buffers(layers), state)
        out.append(result["color"])
    return out


def run_session(url: str, name: str, bodies: list[bytes], expected: list[np.ndarray], ws: bool, window: int,
                size: tuple[int, int]) -> SessionRun:
    run = SessionRun()
    answers: list[bytes | ServiceError] = []
    with Client(url, timeout=300) as client, client.session(name, *size) as session:
        if ws:
            sent: list[float] = []

            def timed() -> Iterator[bytes]:
                for body in bodies:
                    sent.append(time.perf_counter())
                    yield body

            for k, answer in enumerate(session.stream(timed(), window=window)):
                run.latency_ms.append(1e3 * (time.perf_counter() - sent[k]))
                answers.append(answer)
        else:
            for body in bodies:
                start = time.perf_counter()
                answers.append(_denoise_retrying(session, body, run))
                run.latency_ms.append(1e3 * (time.perf_counter() - start))
    run.lost = len(bodies) - len(answers)
    for answer, want in zip(answers, expected, strict=False):
        if isinstance(answer, ServiceError):
            run.errors += 1
        elif not np.array_equal(read_frame(answer)["color"], want):
            run.wrong += 1
    return run


def _denoise_retrying(session: Session, body: bytes, run: SessionRun) -> bytes | ServiceError:
    """One REST frame; a `503 busy` is retried after BUSY_RETRY_S (what a client does with Retry-After)."""
    while True:
        try:
            return session.denoise(body)
        except ServiceError as err:
            if err.code != "busy":
                return err
            run.busy += 1
            time.sleep(BUSY_RETRY_S)


def start_server(workers: int, max_inflight: int) -> tuple[str, subprocess.Popen]:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    env = {**os.environ, "PYTHONPATH": str(ROOT), "MCDENOISE_WORKER_THREADS": str(workers),
           "MCDENOISE_MAX_SESSIONS": "64", "MCDENOISE_MAX_INFLIGHT": str(max_inflight)}
    env.pop("MCDENOISE_API_KEY", None)
    proc = subprocess.Popen([sys.executable, "-m", "service", "serve", "--port", str(port), "--log-level", "warning"],
                            cwd=ROOT, env=env)
    url = f"http://127.0.0.1:{port}"
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        try:
            with urllib.request.urlopen(f"{url}/readyz", timeout=2) as answer:
                if answer.status == 200:
                    return url, proc
        except OSError:
            time.sleep(0.2)
    proc.kill()
    raise RuntimeError("the service did not become ready within 60 s")


def main(argv: list[str] | None = None) -> int:
    configure()  # an entry point that runs the service's kernels (service/process.py)
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sessions", type=int, default=8)
    parser.add_argument("--frames", type=int, default=30, help="frames per session")
    parser.add_argument("--size", default="256x256", help="WxH")
    parser.add_argument("--pipeline", default=pipelines.DEFAULT)
    parser.add_argument("--window", type=int, default=4, help="WebSocket frames in flight")
    parser.add_argument("--workers", type=int, default=2, help="MCDENOISE_WORKER_THREADS of the started service")
    parser.add_argument("--url", help="use this service instead of starting one")
    args = parser.parse_args(argv)
    width, height = (int(v) for v in args.size.lower().split("x"))
    sequences = [synthetic_sequence(height=height, width=width, frames=args.frames, spp=2, seed=100 + s)
                 for s in range(args.sessions)]
    bodies = [[encode_frame(layers) for layers in seq] for seq in sequences]
    expected = [expected_outputs(args.pipeline, seq) for seq in sequences]
    # Room for every frame in flight (REST: one per session, WebSocket: a window each): frames queue, not 503
    max_inflight = max(4 * args.workers, args.sessions * args.window)
    url, proc = (args.url, None) if args.url else start_server(args.workers, max_inflight)
    try:
        Client(url).session(args.pipeline, width, height).close()  # warm the pipeline before the clock starts
        start = time.perf_counter()
        with ThreadPoolExecutor(args.sessions) as pool:
            runs = list(pool.map(lambda s: run_session(url, args.pipeline, bodies[s], expected[s], s % 2 == 1,
                                                       args.window, (width, height)), range(args.sessions)))
        wall = time.perf_counter() - start
    finally:
        if proc is not None:
            proc.terminate()
            proc.wait(timeout=15)
    latency = np.concatenate([r.latency_ms for r in runs])
    total = args.sessions * args.frames
    lost, wrong, errors, busy = (sum(getattr(r, k) for r in runs) for k in ("lost", "wrong", "errors", "busy"))
    print(f"{args.pipeline}, {args.sessions} sessions x {args.frames} frames of {width}x{height} "
          f"(half REST, half WebSocket window {args.window}), {args.workers} worker threads, {os.cpu_count()} CPUs"
          + ("" if args.url else f", MCDENOISE_MAX_INFLIGHT {max_inflight}"))
    p50, p95 = np.percentile(latency, [50, 95])
    print(f"{total} frames in {wall:.1f} s: {total / wall:.1f} frames/s; latency p50 {p50:.0f} ms, p95 {p95:.0f} ms, "
          f"max {latency.max():.0f} ms")
    print(f"lost {lost}, reordered or mixed {wrong}, errors {errors} (503 busy retried: {busy})")
    return 1 if lost or wrong or errors else 0


if __name__ == "__main__":
    sys.exit(main())
