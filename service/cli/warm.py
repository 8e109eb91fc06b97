"""`python -m service warm`: compile (or load from the cache) the kernels of the named pipelines, or of
all, ahead of their first frame (`service.warmup.warm_up`). With `--jobs N` the pipelines are warmed in N
processes at once (numba compiles in one thread; the cache is shared, each file written atomically)."""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor


def add_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("names", nargs="*", metavar="PIPELINE", help="pipelines to warm (default: all)")
    p.add_argument("--jobs", "-j", type=int, default=1,
                   help="processes compiling at once (default 1; 0: one per CPU)")


def run(args: argparse.Namespace) -> int:
    from service import pipelines

    names = args.names or pipelines.names()
    for name in names:
        pipelines.pipeline_class(name)  # an unknown name fails before any compiling
    if args.jobs < 0:
        raise ValueError(f"--jobs must be >= 0, got {args.jobs}")
    jobs = min(len(names), args.jobs or os.cpu_count() or 1)
    return _warm_here(names) if jobs == 1 else _warm_in_processes(names, jobs)


def _warm_here(names: list[str]) -> int:
    from service import pipelines
    from service.warmup import CompileNotice, warm_up

    for name in names:
        with CompileNotice(name):
            seconds = warm_up(pipelines.get(name))
        print(f"{name}: ready in {seconds:.1f} s", flush=True)
    return 0


def _warm_in_processes(names: list[str], jobs: int) -> int:
    """Each pipeline in a `python -m service warm NAME` child, `jobs` at a time; their lines are printed as
    each finishes. Returns 0, or the first failing child's status."""
    print(f"compiling the kernels of {len(names)} pipelines in {jobs} processes (first run, cached after)...",
          file=sys.stderr, flush=True)
    start = time.perf_counter()
    lock = threading.Lock()  # one child's lines together

    def child(name: str) -> int:
        done = subprocess.run([sys.executable, "-m", "service", "warm", name], capture_output=True, text=True)
        with lock:
            sys.stderr.write(done.stderr)
            sys.stdout.write(done.stdout)
            sys.stdout.flush()
        return done.returncode

    with ThreadPoolExecutor(jobs) as pool:
        codes = list(pool.map(child, names))
    failed = [name for name, code in zip(names, codes, strict=True) if code]
    if failed:
        print(f"error: warming failed for {', '.join(failed)}", file=sys.stderr)
        return next(code for code in codes if code)
    print(f"warmed {len(names)} pipelines in {time.perf_counter() - start:.0f} s", flush=True)
    return 0
