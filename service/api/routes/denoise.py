"""POST /v1/denoise: one stateless frame (temporal pipelines run as on a first frame)."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query, Response

from service import pipelines
from service.api.deps import ExrBody, OutputDep, ServicesDep
from service.api.frames import denoise_once
from service.api.routes import FRAME_OPENAPI, FRAME_RESPONSES, frame_response

router = APIRouter(tags=["frames"])


@router.post("/v1/denoise", summary="denoise one EXR frame", response_class=Response,
             openapi_extra=FRAME_OPENAPI, responses=FRAME_RESPONSES)
async def denoise(
    services: ServicesDep,
    body: ExrBody,
    output: OutputDep,
    pipeline: Annotated[str, Query(max_length=64, description="a name from GET /v1/pipelines")] = pipelines.DEFAULT,
) -> Response:
    return frame_response(await denoise_once(services, pipeline, body, output))
