"""Sessions, one per sequence: open, send the next frame, look, end."""

from __future__ import annotations

from fastapi import APIRouter, Response, status

from service.api.deps import ExrBody, OutputDep, OwnerDep, ServicesDep, SessionDep
from service.api.frames import end_session, open_session, session_frame
from service.api.routes import FRAME_OPENAPI, FRAME_RESPONSES, frame_response
from service.api.schemas import ErrorBody, SessionCreate, SessionInfo
from service.api.sessions import SessionSpec

router = APIRouter(prefix="/v1/sessions", tags=["sessions"])
_NOT_FOUND = {404: {"model": ErrorBody, "description": "unknown, ended or expired session (or another key's)"},
              410: {"model": ErrorBody, "description": "session_lost: the replica that held it stopped"}}


@router.post("", status_code=status.HTTP_201_CREATED, summary="open a session for one sequence",
             responses={400: {"model": ErrorBody}, 429: {"model": ErrorBody, "description": "too many sessions"}})
async def create_session(request: SessionCreate, services: ServicesDep, owner: OwnerDep) -> SessionInfo:
    session = await open_session(services, SessionSpec(**request.model_dump()), owner)
    return SessionInfo(**session.info(services.settings.session_idle_s))


@router.get("/{session_id}", summary="frames done, step latency, online-training state", responses=_NOT_FOUND)
async def get_session(session: SessionDep, services: ServicesDep) -> SessionInfo:
    return SessionInfo(**session.info(services.settings.session_idle_s))


@router.delete("/{session_id}", summary="end a session (answers its final statistics)", responses=_NOT_FOUND)
async def delete_session(session: SessionDep, services: ServicesDep) -> SessionInfo:
    await end_session(services, session)
    return SessionInfo(**session.info(services.settings.session_idle_s))


@router.post("/{session_id}/frames", summary="denoise the session's next frame", response_class=Response,
             openapi_extra=FRAME_OPENAPI, responses={**FRAME_RESPONSES, **_NOT_FOUND})
async def post_frame(session: SessionDep, services: ServicesDep, body: ExrBody, output: OutputDep) -> Response:
    return frame_response(await session_frame(services, session, body, output, route="session"))
