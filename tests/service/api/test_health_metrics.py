"""Health, readiness, Prometheus metrics and the OpenAPI docs."""

from __future__ import annotations

import re
import time

import pytest

from tests.service.api.conftest import call, exr_post

pytestmark = pytest.mark.timeout(120)


def test_health_and_readiness(server):
    assert (call(server, "GET", "/healthz").status, call(server, "GET", "/healthz").json()) == (200, {"status": "ok"})
    ready = call(server, "GET", "/readyz")
    assert ready.status == 200 and ready.json()["ready"] is True and ready.json()["pipelines"] >= 1


def test_not_ready_until_the_configured_pipelines_are_warm(make_server, monkeypatch):
    import threading

    import service.api.state

    release, calls = threading.Event(), []

    def slow_warm_up(pipeline) -> float:
        name = pipeline.name
        calls.append(name)
        assert release.wait(10)
        if name == "flr":
            raise RuntimeError("a pipeline that fails to warm up is skipped, not fatal")
        return 0.0

    monkeypatch.setattr(service.api.state, "warm_up", slow_warm_up)
    url = make_server(warmup="bilateral, flr")
    deadline = time.monotonic() + 5
    while not calls and time.monotonic() < deadline:
        time.sleep(0.01)
    ready = call(url, "GET", "/readyz")
    assert ready.status == 503 and ready.json()["warming_up"] == ["bilateral", "flr"]
    assert call(url, "GET", "/healthz").status == 200  # alive while warming
    release.set()
    deadline = time.monotonic() + 10
    while call(url, "GET", "/readyz").status != 200:
        assert time.monotonic() < deadline, "never became ready"
        time.sleep(0.02)
    assert call(url, "GET", "/readyz").json()["warming_up"] == [] and calls == ["bilateral", "flr"]


def test_metrics_count_frames_errors_latency_and_sessions(make_server, sequence_exr):
    url = make_server()
    for data in sequence_exr[:3]:
        assert exr_post(url, "/v1/denoise?pipeline=bilateral", data).status == 200
    assert exr_post(url, "/v1/denoise?pipeline=bilateral", b"junk" * 30).status == 400
    assert exr_post(url, "/v1/denoise?pipeline=nope", sequence_exr[0]).status == 400
    call(url, "POST", "/v1/sessions", b'{"width": 48, "height": 32}', {"Content-Type": "application/json"})
    answer = call(url, "GET", "/metrics")
    assert answer.status == 200 and answer.headers["content-type"].startswith("text/plain; version=0.0.4")
    text = answer.body.decode()
    assert 'mcdenoise_frames_total{pipeline="bilateral",route="rest"} 3' in text
    assert 'mcdenoise_frame_errors_total{pipeline="bilateral",code="invalid_exr"} 1' in text
    assert 'mcdenoise_frame_errors_total{pipeline="unknown",code="unknown_pipeline"} 1' in text
    assert 'mcdenoise_step_seconds_bucket{pipeline="bilateral",le="+Inf"} 3' in text
    assert 'mcdenoise_frame_seconds_count{pipeline="bilateral"} 3' in text
    assert "mcdenoise_sessions_live 1" in text and "mcdenoise_inflight_frames 0" in text
    assert "# TYPE mcdenoise_online_sessions gauge" in text
    # every sample line is `name{labels} value` or `name value`
    for line in text.splitlines():
        assert line.startswith("# ") or re.fullmatch(r"[a-z_]+(\{[^}]*\})? [0-9.e+-]+", line), line
    buckets = [int(v) for v in re.findall(r'mcdenoise_step_seconds_bucket\{pipeline="bilateral",le="[^"]+"\} (\d+)',
                                          text)]
    assert buckets == sorted(buckets)  # cumulative


def test_openapi_documents_the_routes(server):
    schema = call(server, "GET", "/openapi.json").json()
    assert {"/v1/pipelines", "/v1/denoise", "/v1/sessions", "/v1/sessions/{session_id}",
            "/v1/sessions/{session_id}/frames", "/metrics", "/healthz", "/readyz"} <= set(schema["paths"])
    assert "image/x-exr" in schema["paths"]["/v1/denoise"]["post"]["requestBody"]["content"]
    docs = call(server, "GET", "/docs")
    assert docs.status == 200 and b"swagger" in docs.body.lower()
