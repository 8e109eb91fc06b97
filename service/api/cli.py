"""`python -m service serve` and `python -m service stream`: the HTTP service and its client on the command line.

Both import their heavy modules (uvicorn, the app, websockets) only when run.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

from service.api.core.config import Settings

WS_SLACK_BYTES = 1024 * 1024  # a WebSocket message may exceed the body limit by this before uvicorn drops it
# Where one frame's thread count goes: ONNX Runtime sessions (service.runtime reads MCDENOISE_ORT_THREADS),
# numba, OpenMP and BLAS. Set in the environment before the app (and its worker processes) load them.
THREAD_VARIABLES = ("MCDENOISE_ORT_THREADS", "NUMBA_NUM_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS",
                    "MKL_NUM_THREADS")


def add_serve_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--host", default="127.0.0.1", help="address to bind (default 127.0.0.1)")
    p.add_argument("--port", type=int, default=8000, help="port (default 8000)")
    p.add_argument("--workers", type=int, default=1,
                   help="processes (default 1; sessions live in one process, see README)")
    p.add_argument("--log-level", default="info", choices=["critical", "error", "warning", "info", "debug"])


def run_serve(args: argparse.Namespace) -> int:
    import uvicorn

    from service.api.deadline import header_deadline_protocol

    settings = Settings.from_env()  # refuse bad settings before binding (exit 2)
    if args.workers < 1:
        raise ValueError(f"--workers must be at least 1, got {args.workers}")
    if args.workers > 1:
        print(f"note: {args.workers} worker processes: sessions live in one process each, so session "
              "requests must reach the process that created the session", file=sys.stderr)
    if not settings.api_keys and args.host not in ("127.0.0.1", "localhost", "::1"):
        print(f"warning: serving on {args.host} without MCDENOISE_API_KEY: anyone who reaches it can use it",
              file=sys.stderr)
    limit_threads(settings.frame_threads)
    uvicorn.run(
        "service.api.main:create_app",
        factory=True,
        host=args.host,
        port=args.port,
        workers=args.workers,
        log_level=args.log_level,
        ws_max_size=settings.max_body_bytes + WS_SLACK_BYTES,
        ws_per_message_deflate=False,  # EXR frames are compressed already
        timeout_graceful_shutdown=10,
        server_header=False,
        http=header_deadline_protocol(settings.client_timeout_s),
    )
    return 0


def limit_threads(n: int) -> None:
    """Cap the threads one frame may use (MCDENOISE_FRAME_THREADS) unless the environment says otherwise."""
    for name in THREAD_VARIABLES:
        os.environ.setdefault(name, str(n))
    numba = sys.modules.get("numba")
    if numba is not None:  # already loaded by a pipeline module: too late for the environment
        try:
            numba.set_num_threads(min(n, numba.config.NUMBA_NUM_THREADS))
        except (ValueError, RuntimeError):
            print(f"warning: could not limit numba to {n} threads", file=sys.stderr)


def add_stream_args(p: argparse.ArgumentParser) -> None:
    from service.cli import add_sequence_args

    add_sequence_args(p)
    p.add_argument("--url", default="http://127.0.0.1:8000", help="service url (default http://127.0.0.1:8000)")
    p.add_argument("--api-key", default=os.environ.get("MCDENOISE_API_KEY"),
                   help="API key (default: $MCDENOISE_API_KEY)")
    p.add_argument("--window", type=int, default=4, help="frames sent ahead of the answers (default 4)")


def run_stream(args: argparse.Namespace) -> int:
    from service.cli import parse_options, resolve_pipeline
    from service.client import Client, ServiceError
    from service.exr import list_sequence, read_header

    options = parse_options(args.option)
    name = resolve_pipeline(args.pipeline, args.in_dir)
    first = read_header(list_sequence(args.in_dir)[0])
    try:
        with Client(args.url, args.api_key) as client, client.session(
            name, first.width, first.height, options=options, online=args.online
        ) as session:
            start = time.perf_counter()
            results = session.stream_folder(args.in_dir, args.out_dir, window=args.window)
            seconds = time.perf_counter() - start
            status = session.status()
    except ServiceError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    for r in results:
        print(f"{r.name:<24} {'ok' if r.error is None else f'error {r.error.code}: {r.error.message}'}")
    failed = sum(r.error is not None for r in results)
    print(f"{name}: {len(results) - failed}/{len(results)} frames in {seconds:.2f} s "
          f"({len(results) / seconds:.1f} frames/s), step mean {status['mean_ms']} ms, p95 {status['p95_ms']} ms")
    print(f"outputs in {args.out_dir}")
    return 2 if failed else 0
