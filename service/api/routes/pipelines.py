"""GET /v1/pipelines: what every registered pipeline needs and does."""

from __future__ import annotations

from fastapi import APIRouter

from service import pipelines
from service.api.schemas import PipelineList

router = APIRouter(tags=["pipelines"])


@router.get("/v1/pipelines", summary="registered pipelines: layers required and used, temporal, options")
async def list_pipelines() -> PipelineList:
    return PipelineList(default=pipelines.DEFAULT, pipelines=pipelines.describe())
