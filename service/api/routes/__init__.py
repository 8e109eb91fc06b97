"""One small module per resource; `frame_response` is the answer every frame route shares."""

from __future__ import annotations

from typing import Any

from fastapi import Response

from service.api import codec
from service.api.frames import Denoised
from service.api.schemas import ErrorBody

FRAME_HEADERS = {
    "X-Frame-Index": "index of the frame in its sequence (0 for a stateless frame)",
    "X-Step-Ms": "time in the pipeline step, milliseconds",
    "X-Nonfinite-Repaired": "NaN/Inf input values that were repaired",
    "X-Error-Mean": "mean of the frame's `error` layer (auto: the estimated relative squared error of its "
                    "chosen denoisers at half the samples)",
}
# OpenAPI description of a route that takes one EXR frame and answers one frame.
FRAME_OPENAPI: dict[str, Any] = {
    "requestBody": {
        "required": True,
        "description": "one frame as an OpenEXR file (channels LAYER.CHANNEL, see FRAME_FORMAT.md)",
        "content": {codec.EXR: {"schema": {"type": "string", "format": "binary"}}},
    }
}
FRAME_RESPONSES: dict[int | str, dict[str, Any]] = {
    200: {
        "description": "the denoised frame: EXR with layer `color` (and `error` from auto), or a PNG preview "
                       "with Accept: image/png",
        "content": {codec.EXR: {"schema": {"type": "string", "format": "binary"}},
                    codec.PNG: {"schema": {"type": "string", "format": "binary"}}},
        "headers": {name: {"description": text, "schema": {"type": "string"}} for name, text in FRAME_HEADERS.items()},
    },
    **{status: {"model": ErrorBody, "description": text} for status, text in (
        (400, "not EXR, truncated, unknown pipeline"),
        (401, "missing or wrong API key"),
        (408, "the body did not arrive within MCDENOISE_CLIENT_TIMEOUT_S"),
        (413, "body or frame too large, or the frame's memory estimate over MCDENOISE_MAX_FRAME_MB"),
        (415, "Content-Type is not image/x-exr"),
        (422, "missing or malformed layer (named), values beyond a layer's limit or that the pipeline could not "
              "process (layer named), or a size other than the session's"),
        (503, "every frame slot is taken; see Retry-After"),
        (504, "the frame was not done within MCDENOISE_FRAME_TIMEOUT_S"),
    )},
}


def frame_response(result: Denoised) -> Response:
    headers = {
        "X-Frame-Index": str(result.frame_index),
        "X-Step-Ms": f"{result.step_ms:.3f}",
        "X-Nonfinite-Repaired": str(result.nonfinite),
    }
    if result.error_mean is not None:
        headers["X-Error-Mean"] = f"{result.error_mean:.6g}"
    return Response(result.body, media_type=result.media_type, headers=headers)
