"""Liveness and readiness; the only routes that need no API key."""

from __future__ import annotations

from fastapi import APIRouter
from fastapi.responses import JSONResponse

from service import pipelines
from service.api.deps import ServicesDep

router = APIRouter(tags=["health"])


@router.get("/healthz", summary="the process answers")
async def healthz() -> dict[str, str]:
    return {"status": "ok"}


@router.get("/readyz", summary="the service takes work (503 while starting or stopping)")
async def readyz(services: ServicesDep) -> JSONResponse:
    body = {
        "ready": services.ready,
        "warming_up": list(services.warming),
        "pipelines": len(pipelines.names()),
        "sessions": len(services.sessions),
        "inflight": services.pool.inflight,
    }
    return JSONResponse(body, status_code=200 if services.ready else 503)
