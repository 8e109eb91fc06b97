"""REST over a real `python -m service serve`: pipelines, stateless frames, every bad-input case."""

from __future__ import annotations

import io

import numpy as np
import OpenEXR
import pytest

from service import pipelines
from service.exr import encode_frame, read_frame
from tests.service.api.conftest import HEIGHT, WIDTH, call, exr_post

pytestmark = pytest.mark.timeout(120)


def test_pipelines_lists_layers_and_temporal_flag(server):
    answer = call(server, "GET", "/v1/pipelines")
    assert answer.status == 200
    body = answer.json()
    assert body["default"] == pipelines.DEFAULT
    bilateral = next(p for p in body["pipelines"] if p["name"] == "bilateral")
    assert bilateral["requires"] == ["color"] and "albedo" in bilateral["optional"]
    assert bilateral["temporal"] is False and bilateral["options"]["radius"] == 6


def test_denoise_equals_the_cli_frame_by_frame(server, sequence_exr, cli_outputs):
    for data, expected in zip(sequence_exr[:4], cli_outputs, strict=False):
        answer = exr_post(server, "/v1/denoise?pipeline=bilateral", data)
        assert answer.status == 200 and answer.headers["content-type"] == "image/x-exr"
        assert answer.headers["x-frame-index"] == "0" and float(answer.headers["x-step-ms"]) > 0
        out = read_frame(answer.body)
        assert set(out.buffers) == {"color"}
        np.testing.assert_array_equal(out["color"], expected)


def test_png_preview_when_accepted(server, sequence_exr):
    answer = exr_post(server, "/v1/denoise?pipeline=bilateral", sequence_exr[0], Accept="image/png")
    assert answer.status == 200 and answer.headers["content-type"] == "image/png"
    assert answer.body.startswith(b"\x89PNG\r\n\x1a\n")
    width, height = int.from_bytes(answer.body[16:20], "big"), int.from_bytes(answer.body[20:24], "big")
    assert (width, height) == (WIDTH, HEIGHT)
    # EXR wins a tie and is the default for other Accept values
    answer = exr_post(server, "/v1/denoise?pipeline=bilateral", sequence_exr[0], Accept="*/*")
    assert answer.headers["content-type"] == "image/x-exr"


def test_nonfinite_input_is_repaired_and_counted(server):
    color = np.ones((8, 8, 3), np.float32)
    color[0, 0, :] = np.nan
    answer = exr_post(server, "/v1/denoise?pipeline=bilateral", encode_frame({"color": color}))
    assert answer.status == 200 and answer.headers["x-nonfinite-repaired"] == "3"
    assert np.isfinite(read_frame(answer.body)["color"]).all()


def _missing_color() -> bytes:
    return encode_frame({"albedo": np.ones((8, 8, 3), np.float32)})


def _two_channel_albedo() -> bytes:
    channels = {"color.R": np.ones((8, 8), np.float32), "color.G": np.ones((8, 8), np.float32),
                "color.B": np.ones((8, 8), np.float32),
                "albedo.R": np.ones((8, 8), np.float32), "albedo.G": np.ones((8, 8), np.float32)}
    sink = io.BytesIO()
    with OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}, channels) as exr:
        exr.write(sink)
    return sink.getvalue()


BAD_INPUTS = [
    # (case, body or builder, headers, status, code, message prefix or exact, layer)
    ("wrong content type", "frame", {"Content-Type": "application/json"}, 415, "unsupported_media_type",
     "send one OpenEXR frame with Content-Type: image/x-exr (got application/json)", None),
    ("no content type", "frame", {}, 415, "unsupported_media_type",
     "send one OpenEXR frame with Content-Type: image/x-exr (got none)", None),
    ("empty body", b"", None, 400, "invalid_exr", "body is empty; send one OpenEXR frame", None),
    ("not EXR", b"P6 this is not an EXR file" * 10, None, 400, "invalid_exr", "body is not an OpenEXR image (", None),
    ("truncated header", "frame[:200]", None, 400, "invalid_exr", "body is not an OpenEXR image (", None),
    ("truncated pixels", "frame[:-500]", None, 400, "invalid_exr",
     "body is a truncated or corrupt OpenEXR image (", None),
    ("missing layer", _missing_color, None, 422, "invalid_frame",
     "missing layer 'color' required by pipeline 'bilateral' (frame has: albedo)", "color"),
    ("malformed layer", _two_channel_albedo, None, 422, "invalid_frame",
     "layer 'albedo' has 2 channel(s) (G, R); expected 3 (R G B)", "albedo"),
    ("too large frame", lambda: encode_frame({"color": np.ones((8, 65, 3), np.float32)}), None, 413, "too_large",
     "frame is 65x8; this service takes at most 64x64 (width x height)", None),
    ("too large body", lambda: b"\x76\x2f\x31\x01" + bytes(1024 * 1024 + 1), None, 413, "too_large",
     "body is larger than 1 MiB, the most this service takes (MCDENOISE_MAX_BODY_MB)", None),
]


def _body(spec, frame: bytes) -> bytes:
    if callable(spec):
        return spec()
    if spec == "frame":
        return frame
    if spec == "frame[:200]":
        return frame[:200]
    if spec == "frame[:-500]":
        return frame[:-500]
    return spec


@pytest.mark.parametrize(("case", "body", "headers", "status", "code", "message", "layer"), BAD_INPUTS,
                         ids=[c[0] for c in BAD_INPUTS])
def test_bad_input_is_a_4xx_json_error(server, sequence_exr, case, body, headers, status, code, message, layer):
    answer = call(server, "POST", "/v1/denoise?pipeline=bilateral", _body(body, sequence_exr[0]),
                  {"Content-Type": "image/x-exr"} if headers is None else headers)
    assert answer.status == status, answer.body
    assert answer.headers["content-type"] == "application/json"
    error = answer.json()
    assert error["code"] == code
    if message.endswith("("):
        assert error["message"].startswith(message)
    else:
        assert error["message"] == message
    assert error.get("layer") == layer
    # nothing else changed: the next good frame is answered
    assert exr_post(server, "/v1/denoise?pipeline=bilateral", sequence_exr[1]).status == 200


def test_unknown_pipeline_and_bad_query(server, sequence_exr):
    answer = exr_post(server, "/v1/denoise?pipeline=nope", sequence_exr[0])
    assert (answer.status, answer.json()["code"]) == (400, "unknown_pipeline")
    assert answer.json()["message"].startswith("unknown pipeline 'nope'; available: ")
    answer = exr_post(server, "/v1/denoise?exposure=-1", sequence_exr[0], Accept="image/png")
    assert (answer.status, answer.json()["code"]) == (422, "invalid_request")
    assert answer.json()["message"] == "query.exposure: Input should be greater than 0"


def test_unknown_route_and_method_are_json(server):
    answer = call(server, "GET", "/v2/nothing")
    assert (answer.status, answer.json()) == (404, {"code": "not_found", "message": "Not Found"})
    answer = call(server, "GET", "/v1/denoise?pipeline=bilateral")
    assert (answer.status, answer.json()["code"]) == (405, "method_not_allowed")
