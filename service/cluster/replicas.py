"""The local replicas of `python -m service cluster`: `python -m service serve` processes on loopback
ports, each with its own replica id and a fair share of the CPUs, started, awaited and stopped."""

from __future__ import annotations

import socket
import subprocess
import sys
import time
import urllib.error
import urllib.request
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass

from service.cluster.haproxy import READY_PATH, Replica

LOOPBACK = "127.0.0.1"
POLL_S = 0.1  # between two /readyz probes of a starting replica, seconds


@dataclass
class Running:
    replica: Replica
    process: subprocess.Popen


def free_port() -> int:
    """A TCP port free on loopback now (the OS's choice; another process may take it before we bind)."""
    with socket.socket() as s:
        s.bind((LOOPBACK, 0))
        return s.getsockname()[1]


def replica_environment(environ: Mapping[str, str], replica_id: str, replicas: int, cpus: int) -> dict[str, str]:
    """The environment of one of `replicas` replicas on `cpus` CPUs: its MCDENOISE_REPLICA_ID, and unless set
    already, a fair share of the CPUs (max(1, cpus // replicas)) as its frames at once
    (MCDENOISE_WORKER_THREADS) and one thread per frame when that share is one worker each."""
    env = dict(environ)
    env["MCDENOISE_REPLICA_ID"] = replica_id
    share = max(1, cpus // replicas)
    env.setdefault("MCDENOISE_WORKER_THREADS", str(share))
    workers = env["MCDENOISE_WORKER_THREADS"].strip()
    env.setdefault("MCDENOISE_FRAME_THREADS", str(max(1, share // int(workers)) if workers.isdigit() and
                                                  int(workers) > 0 else 1))
    return env


def start(count: int, environ: Mapping[str, str], cpus: int, log_level: str) -> Iterator[Running]:
    """Start `count` replicas `r0`, `r1`, ... on free loopback ports (their output goes to ours), yielding each
    as soon as its process runs."""
    for i in range(count):
        replica = Replica(f"r{i}", f"{LOOPBACK}:{free_port()}")
        command = [sys.executable, "-m", "service", "serve", "--host", LOOPBACK,
                   "--port", replica.address.rpartition(":")[2], "--log-level", log_level]
        env = replica_environment(environ, replica.name, count, cpus)
        yield Running(replica, subprocess.Popen(command, env=env))


def wait_ready(running: Sequence[Running], timeout_s: float) -> None:
    """Return once every replica's /readyz answers 200; RuntimeError when one exits or `timeout_s` passes."""
    deadline = time.monotonic() + timeout_s
    waiting = list(running)
    while waiting:
        for r in list(waiting):
            if r.process.poll() is not None:
                raise RuntimeError(f"replica {r.replica.name} exited with status {r.process.returncode} "
                                   "before it was ready (its output is above)")
            if _ready(r.replica.address):
                waiting.remove(r)
        if waiting and time.monotonic() > deadline:
            raise RuntimeError(f"replicas {', '.join(r.replica.name for r in waiting)} were not ready within "
                               f"{timeout_s:g} s")
        time.sleep(POLL_S if waiting else 0)


def _ready(address: str) -> bool:
    try:
        with urllib.request.urlopen(f"http://{address}{READY_PATH}", timeout=2) as answer:
            return answer.status == 200
    except (urllib.error.URLError, OSError):
        return False


def stop(processes: Sequence[subprocess.Popen], grace_s: float) -> None:
    """SIGTERM every process still running, wait up to `grace_s` seconds for all, then SIGKILL the rest."""
    for p in processes:
        if p.poll() is None:
            p.terminate()
    deadline = time.monotonic() + grace_s
    for p in processes:
        try:
            p.wait(timeout=max(0.0, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()
