"""Real uvicorn servers on loopback for the API tests, and small EXR frames.

`server` is `python -m service serve` in a subprocess (the shipped entry point), shared by the module's
tests; `make_server` runs uvicorn.Server in a thread with given Settings, for configurations a test
needs of its own (auth, short idle timeout, tiny pool) and for test-only pipelines registered in this
process. Every wait is bounded.
"""

from __future__ import annotations

import http.client
import json
import os
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import uvicorn

from bench.synthetic import synthetic_sequence
from service.api.core.config import Settings
from service.api.main import create_app
from service.cluster.replicas import free_port
from service.exr import encode_frame

ROOT = Path(__file__).resolve().parents[3]
HEIGHT, WIDTH = 32, 48  # test frames, pixels
START_TIMEOUT_S = 60.0  # a busy 2-core machine can take a while to import numpy + fastapi
SERVER_ENV = {  # limits of the subprocess server
    "MCDENOISE_MAX_BODY_MB": "1",
    "MCDENOISE_MAX_WIDTH": "64",
    "MCDENOISE_MAX_HEIGHT": "64",
    "MCDENOISE_WORKER_THREADS": "2",
    "MCDENOISE_MAX_SESSIONS": "32",
    "MCDENOISE_MAX_INFLIGHT": "32",
}


@dataclass
class Answer:
    status: int
    headers: dict[str, str]
    body: bytes

    def json(self):
        return json.loads(self.body)


def call(url: str, method: str, path: str, body: bytes | None = None, headers: dict[str, str] | None = None,
         timeout: float = 60.0) -> Answer:
    """One HTTP request on a fresh connection (so tests do not share connection state)."""
    host, port = url.removeprefix("http://").split(":")
    conn = http.client.HTTPConnection(host, int(port), timeout=timeout)
    try:
        conn.request(method, path, body=body, headers=headers or {})
        response = conn.getresponse()
        return Answer(response.status, {k.lower(): v for k, v in response.getheaders()}, response.read())
    finally:
        conn.close()


def exr_post(url: str, path: str, body: bytes, **headers: str) -> Answer:
    return call(url, "POST", path, body, {"Content-Type": "image/x-exr", **headers})


def wait_healthy(url: str, timeout: float = START_TIMEOUT_S, proc: subprocess.Popen | None = None) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if proc is not None and proc.poll() is not None:
            raise RuntimeError(f"server exited with status {proc.returncode}")
        try:
            if call(url, "GET", "/healthz", timeout=2).status == 200:
                return
        except OSError:
            pass
        time.sleep(0.1)
    raise TimeoutError(f"server at {url} did not answer /healthz within {timeout} s")


def start_subprocess_server(python: str, env: dict[str, str], log: Path, cwd: Path = ROOT
                            ) -> tuple[str, subprocess.Popen]:
    """`python -m service serve` on a free loopback port; returns (url, process) once /healthz answers."""
    for _ in range(3):  # the free port may be taken between probe and bind
        port = free_port()
        with open(log, "ab") as sink:
            proc = subprocess.Popen([python, "-m", "service", "serve", "--port", str(port), "--log-level", "warning"],
                                    cwd=cwd, env=env, stdout=sink, stderr=subprocess.STDOUT)
        url = f"http://127.0.0.1:{port}"
        try:
            wait_healthy(url, proc=proc)
            return url, proc
        except RuntimeError:
            continue
    raise RuntimeError(f"could not start the server; log:\n{log.read_text()[-3000:]}")


def stop(proc: subprocess.Popen) -> None:
    proc.terminate()
    try:
        proc.wait(timeout=15)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait(timeout=5)


@pytest.fixture(scope="package")
def server(tmp_path_factory) -> Iterator[str]:
    """URL of `python -m service serve` (subprocess) with SERVER_ENV limits."""
    log = tmp_path_factory.mktemp("server") / "server.log"
    env = {**os.environ, **SERVER_ENV, "PYTHONPATH": str(ROOT)}
    env.pop("MCDENOISE_API_KEY", None)
    url, proc = start_subprocess_server(sys.executable, env, log)
    yield url
    stop(proc)


class ThreadServer:
    def __init__(self, settings: Settings):
        self.sock = socket.socket()
        self.sock.bind(("127.0.0.1", 0))
        self.url = f"http://127.0.0.1:{self.sock.getsockname()[1]}"
        config = uvicorn.Config(create_app(settings), log_level="warning", ws_per_message_deflate=False,
                                ws_max_size=settings.max_body_bytes + 1024 * 1024)
        self.server = uvicorn.Server(config)
        self.thread = threading.Thread(target=self.server.run, kwargs={"sockets": [self.sock]}, daemon=True)

    def start(self) -> ThreadServer:
        self.thread.start()
        deadline = time.monotonic() + START_TIMEOUT_S
        while not self.server.started:
            if time.monotonic() > deadline or not self.thread.is_alive():
                raise RuntimeError("threaded uvicorn server did not start")
            time.sleep(0.02)
        return self

    def stop(self) -> None:
        self.server.should_exit = True
        self.thread.join(timeout=15)
        self.sock.close()


@pytest.fixture()
def make_server() -> Iterator[Callable[..., str]]:
    """make_server(**settings) -> URL of a uvicorn.Server running create_app(Settings(**settings)) in a thread."""
    started: list[ThreadServer] = []

    def make(**settings) -> str:
        srv = ThreadServer(Settings(**settings)).start()
        started.append(srv)
        return srv.url

    yield make
    for srv in started:
        srv.stop()


@pytest.fixture(scope="package")
def sequence_layers() -> list[dict[str, np.ndarray]]:
    """Ten 48x32 frames (W x H) of the synthetic scene, every layer."""
    return synthetic_sequence(height=HEIGHT, width=WIDTH, frames=10, spp=4, seed=11)


@pytest.fixture(scope="package")
def sequence_exr(sequence_layers) -> list[bytes]:
    return [encode_frame(layers) for layers in sequence_layers]


@pytest.fixture(scope="package")
def sequence_dir(tmp_path_factory, sequence_exr) -> Path:
    folder = tmp_path_factory.mktemp("seq")
    for t, data in enumerate(sequence_exr):
        (folder / f"frame_{t:04d}.exr").write_bytes(data)
    return folder


@pytest.fixture(scope="package")
def cli_outputs(tmp_path_factory, sequence_dir) -> list[np.ndarray]:
    """`python -m service denoise --pipeline bilateral` on the sequence: the `color` of each output frame."""
    from service.cli import main
    from service.exr import read_frame

    out = tmp_path_factory.mktemp("cli_out")
    assert main(["denoise", "--pipeline", "bilateral", str(sequence_dir), str(out)]) == 0
    return [read_frame(p)["color"] for p in sorted(out.glob("*.exr"))]
