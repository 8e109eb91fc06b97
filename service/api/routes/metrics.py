"""GET /metrics: Prometheus text."""

from __future__ import annotations

from fastapi import APIRouter
from fastapi.responses import PlainTextResponse

from service.api.deps import ServicesDep

router = APIRouter(tags=["metrics"])


@router.get("/metrics", summary="Prometheus metrics (text format 0.0.4)", response_class=PlainTextResponse)
async def metrics(services: ServicesDep) -> PlainTextResponse:
    text = services.metrics.render(
        live_sessions=len(services.sessions),
        max_sessions=services.sessions.max_sessions,
        inflight=services.pool.inflight,
        max_inflight=services.pool.max_inflight,
        rejected_busy=services.pool.rejected,
        rejected_sessions=services.sessions.rejected,
        online_states=[
            str(status.get("state", "unknown"))
            for status in (s.online_status for s in services.sessions.all()) if status is not None
        ],
    )
    return PlainTextResponse(text, media_type="text/plain; version=0.0.4; charset=utf-8")
