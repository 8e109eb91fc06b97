"""`python -m service serve`: every pipeline over HTTP (FastAPI + uvicorn), REST frames, sessions and
WebSocket streams. uvicorn and the app load only when it runs."""

from __future__ import annotations

import argparse
import os
import secrets
import sys
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from service.api.core.config import Settings

WS_SLACK_BYTES = 1024 * 1024  # a WebSocket message may exceed the body limit by this before uvicorn drops it
# Where one frame's thread count goes: ONNX Runtime sessions (service.runtime reads MCDENOISE_ORT_THREADS),
# numba, OpenMP and BLAS. Set in the environment before the app (and its worker processes) load them.
THREAD_VARIABLES = ("MCDENOISE_ORT_THREADS", "NUMBA_NUM_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS",
                    "MKL_NUM_THREADS")


def add_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--host", default="127.0.0.1", help="address to bind (default 127.0.0.1)")
    p.add_argument("--port", type=int, default=8000, help="port (default 8000)")
    p.add_argument("--workers", type=int, default=1,
                   help="processes (default 1; sessions live in one process, see README)")
    p.add_argument("--log-level", default="info", choices=["critical", "error", "warning", "info", "debug"])


def run(args: argparse.Namespace) -> int:
    import uvicorn

    from service.api.core.config import Settings
    from service.api.deadline import header_deadline_protocol
    from service.api.sessions import INSTANCE_ENV

    settings = Settings.from_env()  # refuse bad settings before binding (exit 2)
    if args.workers < 1:
        raise ValueError(f"--workers must be at least 1, got {args.workers}")
    if args.workers > 1:
        print(f"note: {args.workers} worker processes: sessions live in one process each, so session "
              "requests must reach the process that created the session (or use `cluster`)", file=sys.stderr)
    warn_if_open(settings, args.host)
    limit_threads(settings.frame_threads)
    os.environ[INSTANCE_ENV] = secrets.token_hex(4)  # one instance for all worker processes (api/sessions.py)
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


def warn_if_open(settings: Settings, host: str) -> None:
    """Warn on stderr when `host` is not loopback and no API key is set."""
    if not settings.api_keys and host not in ("127.0.0.1", "localhost", "::1"):
        print(f"warning: serving on {host} without MCDENOISE_API_KEY: anyone who reaches it can use it",
              file=sys.stderr)


def limit_threads(n: int) -> None:
    """Cap the threads one frame may use (MCDENOISE_FRAME_THREADS) unless the environment says otherwise.

    numba, loaded already by the pipeline registry, has read its environment, and it reads it again at
    every compile: a NUMBA_NUM_THREADS that differs from its configuration once its threads run fails that
    compile (a 500 on the first frame of an uncached kernel). Before its threads start, both are set."""
    for name in THREAD_VARIABLES:
        os.environ.setdefault(name, str(n))
    numba = sys.modules.get("numba")
    if numba is None:
        return
    from numba.np.ufunc import parallel

    wanted = int(os.environ["NUMBA_NUM_THREADS"])
    if not parallel._is_initialized:  # no kernel has run: the thread pool starts with `wanted` threads
        numba.config.NUMBA_NUM_THREADS = parallel.NUM_THREADS = wanted
    elif wanted != numba.config.NUMBA_NUM_THREADS:
        print(f"warning: numba runs {numba.config.NUMBA_NUM_THREADS} threads already, not {wanted}", file=sys.stderr)
