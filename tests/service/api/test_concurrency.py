"""Concurrent sessions: every frame answered, in order, no cross-talk; a slow frame stalls no other session;
a full pool answers 503 with Retry-After at once."""

from __future__ import annotations

import json
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
import pytest

from bench.synthetic import synthetic_sequence
from service import pipelines
from service.client import Client
from service.exr import encode_frame, read_frame
from service.frame import Frame
from service.pipelines import Pipeline, SequenceState
from tests.service.api.conftest import HEIGHT, WIDTH, call, exr_post

pytestmark = pytest.mark.timeout(180)
SESSIONS, FRAMES = 8, 10


@dataclass
class SumState(SequenceState):
    total: np.ndarray | None = None


class RunningMean(Pipeline):
    """Test-only temporal pipeline: output k is the mean of input colors 0..k, so any reordering or
    mixing of two sessions' frames shows in the output."""

    name = "test_running_mean"
    summary = "test only"
    requires = ("color",)
    temporal = True

    def new_state(self, height: int, width: int) -> SumState:
        return SumState(height, width)

    def denoise(self, frame: Frame, state: SumState):
        time.sleep(0.002)  # let other sessions' frames interleave
        state.total = frame["color"].copy() if state.total is None else state.total + frame["color"]
        return {"color": state.total / np.float32(state.frame_index + 1)}, state


GATE = threading.Event()  # opened by the test; a gated step waits for it
ENTERED = threading.Semaphore(0)  # released when a gated step starts


class Gated(Pipeline):
    """Test-only pipeline whose step blocks until GATE opens: a frame as slow as the test wants."""

    name = "test_gated"
    summary = "test only"
    requires = ("color",)

    def denoise(self, frame: Frame, state: SequenceState):
        ENTERED.release()
        GATE.wait(timeout=30)
        return {"color": frame["color"]}, state


@pytest.fixture()
def test_pipelines(monkeypatch):
    for cls in (RunningMean, Gated):
        monkeypatch.setitem(pipelines._REGISTRY, cls.name, cls)
    GATE.clear()
    yield
    GATE.set()


def sequences() -> list[list[dict[str, np.ndarray]]]:
    return [synthetic_sequence(height=HEIGHT, width=WIDTH, frames=FRAMES, spp=2, seed=100 + s) for s in range(SESSIONS)]


def direct(name: str, layers: list[dict[str, np.ndarray]]) -> list[np.ndarray]:
    """The pipeline called directly, frame after frame: what the service must answer."""
    pipeline = pipelines.get(name)
    state = pipeline.start(HEIGHT, WIDTH)
    outputs = []
    for frame in layers:
        out, state = pipeline.step(Frame.from_buffers(frame), state)
        outputs.append(out["color"])
    return outputs


def run_sessions(url: str, name: str, seqs: list[list[dict[str, np.ndarray]]]) -> list[list[np.ndarray]]:
    """SESSIONS sessions at once, half over REST and half over the WebSocket, each on its own client."""
    barrier = threading.Barrier(SESSIONS, timeout=60)

    def one(s: int) -> list[np.ndarray]:
        frames = [encode_frame(layers) for layers in seqs[s]]
        with Client(url, timeout=60) as client, client.session(name, WIDTH, HEIGHT) as session:
            barrier.wait()
            if s % 2:
                answers = list(session.stream(frames, window=4))
            else:
                answers = [session.denoise(f) for f in frames]
            assert session.status()["frames"] == FRAMES
        assert all(isinstance(a, bytes) for a in answers), answers
        return [read_frame(a)["color"] for a in answers]

    with ThreadPoolExecutor(SESSIONS) as pool:
        return list(pool.map(one, range(SESSIONS), timeout=150))


def test_8_concurrent_sessions_of_10_frames_on_the_served_process(server):
    seqs = sequences()
    results = run_sessions(server, "bilateral", seqs)
    for seq, got in zip(seqs, results, strict=True):
        assert len(got) == FRAMES
        for out, expected in zip(got, direct("bilateral", seq), strict=True):
            np.testing.assert_array_equal(out, expected)


def test_8_concurrent_temporal_sessions_keep_order_and_state_apart(make_server, test_pipelines):
    url = make_server(worker_threads=4, max_inflight=16)
    seqs = sequences()
    results = run_sessions(url, "test_running_mean", seqs)
    for seq, got in zip(seqs, results, strict=True):
        for out, expected in zip(got, direct("test_running_mean", seq), strict=True):
            np.testing.assert_array_equal(out, expected)


def test_a_slow_frame_stalls_no_other_session_and_a_full_pool_answers_503(make_server, test_pipelines, sequence_exr):
    url = make_server(worker_threads=2, max_inflight=2, retry_after_s=2)
    spec = json.dumps({"pipeline": "test_gated", "width": WIDTH, "height": HEIGHT}).encode()
    slow = call(url, "POST", "/v1/sessions", spec, {"Content-Type": "application/json"}).json()
    fast_spec = json.dumps({"pipeline": "bilateral", "width": WIDTH, "height": HEIGHT}).encode()
    fast = call(url, "POST", "/v1/sessions", fast_spec, {"Content-Type": "application/json"}).json()
    with ThreadPoolExecutor(2) as pool:
        try:
            blocked = pool.submit(exr_post, url, f"/v1/sessions/{slow['id']}/frames", sequence_exr[0])
            assert ENTERED.acquire(timeout=30)
            for data in sequence_exr[:3]:  # the other session is served while the slow frame runs
                assert exr_post(url, f"/v1/sessions/{fast['id']}/frames", data).status == 200
            assert not blocked.done()
            stateless = pool.submit(exr_post, url, "/v1/denoise?pipeline=test_gated", sequence_exr[1])
            assert ENTERED.acquire(timeout=30)
            started = time.monotonic()
            busy = exr_post(url, f"/v1/sessions/{fast['id']}/frames", sequence_exr[3])
            assert time.monotonic() - started < 5  # answered at once, not queued
            assert busy.status == 503 and busy.headers["retry-after"] == "2"
            assert busy.json() == {"code": "busy", "message": "all 2 frame slots are taken; retry later"}
            assert call(url, "GET", f"/v1/sessions/{fast['id']}").json()["frames"] == 3  # reads need no slot
            assert not blocked.done() and not stateless.done()
        finally:
            GATE.set()
        assert blocked.result(timeout=30).status == 200 and stateless.result(timeout=30).status == 200
    answer = exr_post(url, f"/v1/sessions/{fast['id']}/frames", sequence_exr[3])
    assert answer.status == 200 and answer.headers["x-frame-index"] == "3"
    metrics = call(url, "GET", "/metrics").body.decode()
    assert 'mcdenoise_rejected_total{reason="busy"} 1' in metrics
    assert 'mcdenoise_frame_errors_total{pipeline="bilateral",code="busy"} 1' in metrics
