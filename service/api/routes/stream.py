"""WebSocket /v1/sessions/{id}/stream: EXR frames in, denoised EXR frames out, strictly in order."""

from __future__ import annotations

from fastapi import APIRouter, WebSocket

from service.api.deps import ServicesDep, SessionDep
from service.api.streaming import serve_stream

router = APIRouter()


@router.websocket("/v1/sessions/{session_id}/stream")
async def stream(websocket: WebSocket, session: SessionDep, services: ServicesDep) -> None:
    await websocket.accept()
    await serve_stream(websocket, services, session)
