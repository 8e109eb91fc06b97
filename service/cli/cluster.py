"""`python -m service cluster`: N replicas of `serve` on loopback ports behind HAProxy (docs/cluster.md).

Sessions stick to the replica that holds them, everything else goes to the least loaded one, and a lost
replica's sessions answer `410 session_lost`. SIGTERM or Ctrl-C stops HAProxy and the replicas, exit 0.
HAProxy is the distribution's package (`make haproxy`); without it: exit 2."""

from __future__ import annotations

import argparse
import math
import os
import shutil
import signal
import subprocess
import sys
import tempfile
from pathlib import Path

MAX_REPLICAS = 64
STOP_GRACE_S = 15.0  # a replica finishes its frames in progress within this on SIGTERM, seconds
SERVER_TIMEOUT_MARGIN_S = 30  # HAProxy waits for a replica's answer this much beyond its frame timeout, s


def add_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--replicas", type=int, default=2, help=f"replicas (1 to {MAX_REPLICAS}, default 2)")
    p.add_argument("--host", default="127.0.0.1", help="IPv4 address or host name HAProxy binds (default 127.0.0.1)")
    p.add_argument("--port", type=int, default=8000, help="port HAProxy serves on (default 8000)")
    p.add_argument("--stats-port", type=int, default=8404,
                   help="loopback port of HAProxy's stats page, /stats (default 8404; 0: none)")
    p.add_argument("--start-timeout", type=float, default=300.0,
                   help="seconds the replicas may take to become ready (default 300)")
    p.add_argument("--log-level", default="warning", choices=["critical", "error", "warning", "info", "debug"],
                   help="the replicas' log level (default warning)")


def run(args: argparse.Namespace) -> int:
    from service.api.core.config import Settings, usable_cpus
    from service.cli.serve import warn_if_open
    from service.cluster import replicas
    from service.cluster.haproxy import ProxyOptions, Replica, render

    settings = Settings.from_env()  # refuse bad settings before starting anything (exit 2)
    if not 1 <= args.replicas <= MAX_REPLICAS:
        raise ValueError(f"--replicas must be 1 to {MAX_REPLICAS}, got {args.replicas}")
    for name in ("port", "stats_port"):
        if not (0 if name == "stats_port" else 1) <= getattr(args, name) <= 65535:
            raise ValueError(f"--{name.replace('_', '-')} must be a TCP port, got {getattr(args, name)}")
    if args.stats_port == args.port:
        raise ValueError(f"--stats-port must differ from --port ({args.port})")
    if not args.host.strip() or any(c in args.host for c in " /:[]"):
        raise ValueError(f"--host must be an IPv4 address or a host name, got {args.host!r}")
    if args.start_timeout <= 0:
        raise ValueError(f"--start-timeout must be > 0, got {args.start_timeout}")
    haproxy = shutil.which("haproxy")
    if haproxy is None:
        raise ValueError("haproxy not found: install it with `make haproxy` (Debian package haproxy)")
    warn_if_open(settings, args.host)
    _stop_on_signals()
    running: list[replicas.Running] = []
    proxy: subprocess.Popen | None = None
    try:
        for replica in replicas.start(args.replicas, os.environ, usable_cpus(), args.log_level):
            running.append(replica)  # one by one: a signal during start stops those already running
        replicas.wait_ready(running, args.start_timeout)
        stats = f"{replicas.LOOPBACK}:{args.stats_port}" if args.stats_port else None
        options = ProxyOptions(bind=f"{args.host}:{args.port}", stats=stats,
                               server_timeout_s=math.ceil(settings.frame_timeout_s) + SERVER_TIMEOUT_MARGIN_S)
        config = render([r.replica for r in running], options)
        with tempfile.TemporaryDirectory(prefix="mcdenoise-cluster-") as folder:
            path = Path(folder) / "haproxy.cfg"
            path.write_text(config)
            proxy = subprocess.Popen([haproxy, "-f", str(path), "-db"])
            front = "127.0.0.1" if args.host == "0.0.0.0" else args.host
            replicas.wait_ready([replicas.Running(Replica("haproxy", f"{front}:{args.port}"), proxy)],
                                args.start_timeout)  # /readyz through HAProxy: it listens and routes
            for r in running:
                print(f"replica {r.replica.name}: pid {r.process.pid}, http://{r.replica.address}", flush=True)
            print(f"cluster: {args.replicas} replicas behind http://{args.host}:{args.port}"
                  + (f", stats http://{stats}/stats" if stats else ""), flush=True)
            status = _wait(proxy)
    except (RuntimeError, KeyboardInterrupt) as err:
        print(f"error: {err}" if isinstance(err, RuntimeError) else "stopping", file=sys.stderr)
        status = 1 if isinstance(err, RuntimeError) else 0
    finally:
        _ignore_signals()  # nothing may cut the stop short
        if proxy is not None and proxy.poll() is None:
            proxy.send_signal(signal.SIGUSR1)  # soft stop: no new connections; answers in flight still pass
        replicas.stop([r.process for r in running], STOP_GRACE_S)  # each finishes its frames in flight
        if proxy is not None:
            replicas.stop([proxy], STOP_GRACE_S)
    return status


def _ignore_signals() -> None:
    for signum in (signal.SIGTERM, signal.SIGINT):
        signal.signal(signum, signal.SIG_IGN)


def _stop_on_signals() -> None:
    """Make the first SIGTERM or SIGINT raise KeyboardInterrupt (the cluster stops); later ones are ignored, so
    that they cannot cut the replicas' graceful stop short."""

    def handler(signum: int, frame: object) -> None:
        _ignore_signals()
        raise KeyboardInterrupt

    for signum in (signal.SIGTERM, signal.SIGINT):
        signal.signal(signum, handler)


def _wait(proxy: subprocess.Popen) -> int:
    """Wait until a signal arrives (0) or HAProxy exits by itself (1)."""
    try:
        code = proxy.wait()
    except KeyboardInterrupt:
        return 0
    print(f"error: haproxy exited with status {code}", file=sys.stderr)
    return 1
