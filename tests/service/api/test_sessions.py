"""Sessions over REST: round trip equal to the CLI, survival of bad frames, limits, idle expiry."""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field

import numpy as np
import pytest

from service import pipelines
from service.exr import encode_frame, read_frame
from service.pipelines import Pipeline, SequenceState
from service.pipelines.options import option
from tests.service.api.conftest import HEIGHT, WIDTH, call, exr_post

pytestmark = pytest.mark.timeout(120)


def open_session(url: str, **spec) -> dict:
    body = {"pipeline": "bilateral", "width": WIDTH, "height": HEIGHT, **spec}
    answer = call(url, "POST", "/v1/sessions", json.dumps(body).encode(), {"Content-Type": "application/json"})
    assert answer.status == 201, answer.body
    return answer.json()


def test_session_round_trip_equals_the_cli(server, sequence_exr, cli_outputs):
    info = open_session(server)
    assert len(info["id"]) >= 43 and info["frames"] == 0 and info["mean_ms"] is None
    assert info["options"]["radius"] == 6 and info["online"] is False and info["online_status"] is None
    path = f"/v1/sessions/{info['id']}"
    for t, (data, expected) in enumerate(zip(sequence_exr, cli_outputs, strict=True)):
        answer = exr_post(server, f"{path}/frames", data)
        assert answer.status == 200 and answer.headers["x-frame-index"] == str(t)
        np.testing.assert_array_equal(read_frame(answer.body)["color"], expected)
    status = call(server, "GET", path).json()
    assert status["frames"] == 10 and status["errors"] == 0
    assert 0 < status["mean_ms"] and status["mean_ms"] <= status["p95_ms"] * 10
    final = call(server, "DELETE", path)
    assert final.status == 200 and final.json()["frames"] == 10
    assert call(server, "GET", path).status == 404
    assert exr_post(server, f"{path}/frames", sequence_exr[0]).status == 404


def test_session_survives_bad_frames_and_goes_on(server, sequence_exr, cli_outputs):
    info = open_session(server)
    path = f"/v1/sessions/{info['id']}"
    assert exr_post(server, f"{path}/frames", sequence_exr[0]).status == 200
    other_size = encode_frame({"color": np.ones((HEIGHT, WIDTH + 2, 3), np.float32)})
    answer = exr_post(server, f"{path}/frames", other_size)
    assert answer.status == 422
    assert answer.json() == {"code": "invalid_frame", "message": f"frame is {WIDTH + 2}x{HEIGHT} but the sequence "
                                                                 f"is {WIDTH}x{HEIGHT}"}
    missing = exr_post(server, f"{path}/frames", encode_frame({"depth": np.ones((HEIGHT, WIDTH, 1), np.float32)}))
    assert missing.status == 422 and missing.json()["layer"] == "color"
    assert exr_post(server, f"{path}/frames", b"garbage" * 50).status == 400
    assert call(server, "POST", f"{path}/frames", sequence_exr[1], {"Content-Type": "text/plain"}).status == 415
    answer = exr_post(server, f"{path}/frames", sequence_exr[1])
    assert answer.status == 200 and answer.headers["x-frame-index"] == "1"
    np.testing.assert_array_equal(read_frame(answer.body)["color"], cli_outputs[1])
    status = call(server, "GET", path).json()
    assert (status["frames"], status["errors"]) == (2, 3)  # the 415 never reached the session
    call(server, "DELETE", path)


def test_a_temporal_session_starts_its_sequence_again_after_a_refused_frame(server, sequence_exr):
    """svgf: after a 422 the pipeline gave, the next good frame comes out as the first frame of a sequence (what
    the stateless route makes of it), its index counting on; a 400 before the step leaves the history as it was."""
    path = f"/v1/sessions/{open_session(server, pipeline='svgf')['id']}"
    assert exr_post(server, f"{path}/frames", sequence_exr[0]).status == 200
    assert exr_post(server, f"{path}/frames", b"garbage" * 50).status == 400
    kept = exr_post(server, f"{path}/frames", sequence_exr[1])
    first = read_frame(exr_post(server, "/v1/denoise?pipeline=svgf", sequence_exr[1]).body)["color"]
    assert kept.status == 200 and not np.array_equal(read_frame(kept.body)["color"], first)
    refused = exr_post(server, f"{path}/frames", encode_frame({"color": np.ones((HEIGHT, WIDTH, 3), np.float32)}))
    assert refused.status == 422 and refused.json()["layer"] == "normal"
    again = exr_post(server, f"{path}/frames", sequence_exr[2])
    assert again.status == 200 and again.headers["x-frame-index"] == "2"
    expected = read_frame(exr_post(server, "/v1/denoise?pipeline=svgf", sequence_exr[2]).body)["color"]
    np.testing.assert_array_equal(read_frame(again.body)["color"], expected)
    call(server, "DELETE", path)


@pytest.mark.parametrize(("spec", "status", "code", "message"), [
    ({"pipeline": "nope"}, 400, "unknown_pipeline", None),
    ({"options": {"radios": 3}}, 400, "invalid_options", "pipeline 'bilateral' has no option 'radios'; options: "
     "demodulate, radius, sigma2_albedo, sigma2_log_depth, sigma2_normal, sigma2_position"),
    ({"online": True}, 400, "invalid_options", "pipeline 'bilateral' does not support online training"),
    ({"options": {"online": True}}, 400, "invalid_options",
     "ask for online training with the session's 'online' field, not an option"),
    ({"width": 0}, 422, "invalid_request", "width: Input should be greater than 0"),
    ({"color": "red"}, 422, "invalid_request", "color: Extra inputs are not permitted"),
    ({"width": 65}, 413, "too_large", "frame is 65x32; this service takes at most 64x64 (width x height)"),
])
def test_bad_session_requests(server, spec, status, code, message):
    body = json.dumps({"pipeline": "bilateral", "width": WIDTH, "height": HEIGHT, **spec}).encode()
    answer = call(server, "POST", "/v1/sessions", body, {"Content-Type": "application/json"})
    assert (answer.status, answer.json()["code"]) == (status, code)
    if message:
        assert answer.json()["message"] == message


def test_unknown_session_is_404_everywhere(server, sequence_exr):
    message = {"code": "unknown_session", "message": "unknown session 'nope' (never created, ended, or expired)"}
    for method, path, body in (("GET", "/v1/sessions/nope", None), ("DELETE", "/v1/sessions/nope", None)):
        answer = call(server, method, path, body)
        assert (answer.status, answer.json()) == (404, message)
    answer = exr_post(server, "/v1/sessions/nope/frames", sequence_exr[0])
    assert (answer.status, answer.json()) == (404, message)


def test_idle_sessions_expire_and_the_limit_answers_429(make_server, sequence_exr):
    url = make_server(session_idle_s=0.6, max_sessions=2)
    first, second = open_session(url), open_session(url)
    answer = call(url, "POST", "/v1/sessions", json.dumps({"width": WIDTH, "height": HEIGHT}).encode(),
                  {"Content-Type": "application/json"})
    assert answer.status == 429 and int(answer.headers["retry-after"]) >= 1
    assert answer.json()["code"] == "too_many_sessions"
    # `second` stays in use; `first` idles past the timeout and ends
    deadline = time.monotonic() + 1.5
    while time.monotonic() < deadline:
        assert exr_post(url, f"/v1/sessions/{second['id']}/frames", sequence_exr[0]).status == 200
        time.sleep(0.15)
    assert call(url, "GET", f"/v1/sessions/{first['id']}").status == 404
    assert call(url, "GET", f"/v1/sessions/{second['id']}").json()["frames"] >= 5
    metrics = call(url, "GET", "/metrics").body.decode()
    assert "mcdenoise_sessions_expired_total 1" in metrics and "mcdenoise_sessions_live 1" in metrics
    open_session(url)  # room again


@dataclass(frozen=True)
class OnlineOptions:
    online: bool = option(False)  # fine-tune while streaming


@dataclass
class OnlineState(SequenceState):
    online_status: dict | None = None
    closed: list = field(default_factory=list)

    def close(self) -> None:
        self.closed.append(True)


class OnlineEcho(Pipeline):
    """Test-only pipeline with an `online` option, reporting a worker state like crossreg's."""

    name = "test_online"
    summary = "test only"
    requires = ("color",)
    Options = OnlineOptions
    states: list[OnlineState] = []

    def new_state(self, height: int, width: int) -> OnlineState:
        state = OnlineState(height, width, online_status={"state": "training", "updates": 0}
                            if self.options.online else None)
        OnlineEcho.states.append(state)
        return state

    def denoise(self, frame, state):
        if state.online_status is not None:
            state.online_status["updates"] += 1
        return {"color": frame["color"]}, state


def test_online_flag_is_a_pipeline_option_and_its_state_is_reported(make_server, monkeypatch, sequence_exr):
    monkeypatch.setitem(pipelines._REGISTRY, OnlineEcho.name, OnlineEcho)
    OnlineEcho.states.clear()
    url = make_server()
    online = open_session(url, pipeline="test_online", online=True)
    offline = open_session(url, pipeline="test_online")
    assert online["online"] is True and online["options"] == {"online": True}
    assert online["online_status"] == {"state": "training", "updates": 0}
    assert offline["options"] == {"online": False} and offline["online_status"] is None
    assert exr_post(url, f"/v1/sessions/{online['id']}/frames", sequence_exr[0]).status == 200
    assert call(url, "GET", f"/v1/sessions/{online['id']}").json()["online_status"]["updates"] == 1
    metrics = call(url, "GET", "/metrics").body.decode()
    assert 'mcdenoise_online_sessions{state="training"} 1' in metrics
    assert call(url, "DELETE", f"/v1/sessions/{online['id']}").status == 200
    assert [bool(s.closed) for s in OnlineEcho.states] == [True, False]  # the ended session's state was closed


def test_rae_session_carries_its_recurrent_state_like_the_cli(server, sequence_exr, sequence_dir, tmp_path):
    """The recurrent autoencoder over a REST session gives the CLI's frames: its hidden state lives in the
    session's state between requests, as in the CLI's frame loop."""
    from service.cli import main

    assert main(["denoise", "--pipeline", "rae", str(sequence_dir), str(tmp_path)]) == 0
    expected = [read_frame(p)["color"] for p in sorted(tmp_path.glob("*.exr"))]
    info = open_session(server, pipeline="rae")
    path = f"/v1/sessions/{info['id']}"
    for data, want in zip(sequence_exr, expected, strict=True):
        answer = exr_post(server, f"{path}/frames", data)
        assert answer.status == 200, answer.body
        np.testing.assert_allclose(read_frame(answer.body)["color"], want, rtol=1e-5, atol=1e-6)
    assert call(server, "DELETE", path).status == 200
