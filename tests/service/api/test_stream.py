"""The WebSocket stream of a session: a sequence in order, errors as JSON messages in a frame's place."""

from __future__ import annotations

import json

import numpy as np
import pytest
from websockets.exceptions import ConnectionClosedOK, InvalidStatus
from websockets.sync.client import connect

from service.exr import encode_frame, read_frame
from tests.service.api.conftest import HEIGHT, WIDTH, call
from tests.service.api.test_sessions import open_session

pytestmark = pytest.mark.timeout(120)


def ws_url(url: str, session_id: str) -> str:
    return url.replace("http://", "ws://") + f"/v1/sessions/{session_id}/stream"


def test_stream_of_a_sequence_equals_the_cli(server, sequence_exr, cli_outputs):
    info = open_session(server)
    with connect(ws_url(server, info["id"]), max_size=None, compression=None, open_timeout=30) as ws:
        for data in sequence_exr:  # send the whole sequence ahead of the answers
            ws.send(data)
        answers = [ws.recv(timeout=60) for _ in sequence_exr]
    for answer, expected in zip(answers, cli_outputs, strict=True):
        assert isinstance(answer, bytes)
        np.testing.assert_array_equal(read_frame(answer)["color"], expected)
    assert call(server, "GET", f"/v1/sessions/{info['id']}").json()["frames"] == 10
    call(server, "DELETE", f"/v1/sessions/{info['id']}")


def test_errors_are_json_messages_and_the_stream_goes_on(server, sequence_exr, cli_outputs):
    info = open_session(server)
    bad = [
        (b"not an exr at all" * 20, {"code": "invalid_exr"}),
        (encode_frame({"albedo": np.ones((HEIGHT, WIDTH, 3), np.float32)}),
         {"code": "invalid_frame", "layer": "color",
          "message": "missing layer 'color' required by pipeline 'bilateral' (frame has: albedo)"}),
        (encode_frame({"color": np.ones((HEIGHT + 1, WIDTH, 3), np.float32)}),
         {"code": "invalid_frame", "message": f"frame is {WIDTH}x{HEIGHT + 1} but the sequence is {WIDTH}x{HEIGHT}"}),
        (encode_frame({"color": np.ones((HEIGHT, 70, 3), np.float32)}),
         {"code": "too_large", "message": "frame is 70x32; this service takes at most 64x64 (width x height)"}),
        ("a text message", {"code": "invalid_message",
                            "message": "expected a binary message holding one EXR frame, got text"}),
    ]
    with connect(ws_url(server, info["id"]), max_size=None, compression=None, open_timeout=30) as ws:
        messages = [sequence_exr[0]] + [b for b, _ in bad] + [sequence_exr[1]]
        for m in messages:
            ws.send(m)
        answers = [ws.recv(timeout=60) for _ in messages]
    np.testing.assert_array_equal(read_frame(answers[0])["color"], cli_outputs[0])
    np.testing.assert_array_equal(read_frame(answers[-1])["color"], cli_outputs[1])
    for index, ((_, expected), answer) in enumerate(zip(bad, answers[1:-1], strict=True), start=1):
        assert isinstance(answer, str)
        error = json.loads(answer)
        assert error["frame"] == index
        assert {k: error[k] for k in expected} == expected
    status = call(server, "GET", f"/v1/sessions/{info['id']}").json()
    assert status["frames"] == 2
    call(server, "DELETE", f"/v1/sessions/{info['id']}")


def test_stream_of_an_unknown_session_is_refused_with_404(server):
    with pytest.raises(InvalidStatus) as caught:
        connect(ws_url(server, "nope"), open_timeout=30)
    assert caught.value.response.status_code == 404
    assert json.loads(caught.value.response.body)["code"] == "unknown_session"


def test_stream_ends_when_its_session_is_deleted(server, sequence_exr):
    info = open_session(server)
    with connect(ws_url(server, info["id"]), max_size=None, compression=None, open_timeout=30) as ws:
        ws.send(sequence_exr[0])
        assert isinstance(ws.recv(timeout=60), bytes)
        assert call(server, "DELETE", f"/v1/sessions/{info['id']}").status == 200
        ws.send(sequence_exr[1])
        error = json.loads(ws.recv(timeout=60))
        assert (error["code"], error["frame"]) == ("unknown_session", 1)
        with pytest.raises(ConnectionClosedOK):
            ws.recv(timeout=30)
