"""The one place where errors become HTTP answers (and WebSocket error messages).

`ApiError` is what the API's own checks raise; `to_api_error` turns every domain error (FrameError,
UnknownPipelineError, ...) into one, and `install` registers the handlers that answer them as
`{"code", "message", "layer"?}` JSON with the right status and headers. The WebSocket stream sends the
same JSON, plus `frame`, as a text message.
"""

from __future__ import annotations

import logging
from typing import Any

from fastapi import FastAPI
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.requests import ClientDisconnect, HTTPConnection

from service.frame import FrameError
from service.pipelines import UnknownPipelineError

log = logging.getLogger("mcdenoise.api")
MAX_MESSAGE = 500  # characters of an error message; longer ones (echoing client input) are cut


class ApiError(Exception):
    """An answer other than success: HTTP `status`, stable machine-readable `code`, human `message`."""

    def __init__(
        self,
        status: int,
        code: str,
        message: str,
        *,
        layer: str | None = None,
        option: str | None = None,
        retry_after: int | None = None,
        headers: dict[str, str] | None = None,
    ):
        message = message if len(message) <= MAX_MESSAGE else message[:MAX_MESSAGE] + "..."
        super().__init__(message)
        self.status, self.code, self.message, self.layer, self.option = status, code, message, layer, option
        self.headers = dict(headers or {})
        if retry_after is not None:
            self.headers["Retry-After"] = str(retry_after)

    def body(self) -> dict[str, Any]:
        out: dict[str, Any] = {"code": self.code, "message": self.message}
        if self.layer is not None:
            out["layer"] = self.layer
        if self.option is not None:
            out["option"] = self.option
        return out


class InvalidExrError(Exception):
    """Request bytes that are not a readable OpenEXR image (not EXR, truncated)."""


class InvalidOptionsError(Exception):
    """Pipeline options the pipeline refuses, or an `online` flag it cannot honour; `option` names it."""

    def __init__(self, message: str, option: str | None = None):
        super().__init__(message)
        self.option = option


class UnknownSessionError(Exception):
    def __init__(self, session_id: str):
        shown = session_id if len(session_id) <= 64 else session_id[:64] + "..."
        super().__init__(f"unknown session '{shown}' (never created, ended, or expired)")


class SessionLostError(Exception):
    """A session id made by another replica, or by an earlier instance of this one: its state is gone."""

    def __init__(self, session_id: str, holder: str, replica_id: str):
        shown = session_id if len(session_id) <= 64 else session_id[:64] + "..."
        where = "an earlier instance of this replica" if holder == replica_id else f"replica '{holder}'"
        super().__init__(f"session '{shown}' is lost: {where} held it and stopped or restarted (this is replica "
                         f"'{replica_id}'); open a new session, whose history starts afresh")


def to_api_error(exc: Exception) -> ApiError:
    """Map an exception raised while serving a request to the answer it gets (status 500 when unexpected)."""
    if isinstance(exc, ApiError):
        return exc
    if isinstance(exc, InvalidExrError):
        return ApiError(400, "invalid_exr", str(exc))
    if isinstance(exc, FrameError):
        return ApiError(422, "invalid_frame", str(exc), layer=exc.layer)
    if isinstance(exc, UnknownPipelineError):
        return ApiError(400, "unknown_pipeline", str(exc))
    if isinstance(exc, InvalidOptionsError):
        return ApiError(400, "invalid_options", str(exc), option=exc.option)
    if isinstance(exc, UnknownSessionError):
        return ApiError(404, "unknown_session", str(exc))
    if isinstance(exc, SessionLostError):
        return ApiError(410, "session_lost", str(exc))
    if isinstance(exc, ClientDisconnect):  # nobody reads this answer
        return ApiError(400, "client_disconnected", "the client went away before its request was read")
    return ApiError(500, "internal_error", f"internal error: {type(exc).__name__}",
                    headers={"Connection": "close"})  # the server drops the connection after a 500


def report(exc: Exception) -> ApiError:
    """`to_api_error`, logging the traceback of an unexpected error (500) and a client disconnect at info."""
    error = to_api_error(exc)
    if error.status >= 500 and error.code == "internal_error":
        log.error("unexpected error while serving a request", exc_info=exc)
    elif error.code == "client_disconnected":
        log.info("client disconnected before its request was read")
    return error


def unauthorized(message: str) -> ApiError:
    return ApiError(401, "unauthorized", message, headers={"WWW-Authenticate": "Bearer"})


def _respond(error: ApiError) -> JSONResponse:
    return JSONResponse(error.body(), status_code=error.status, headers=error.headers)


async def _domain_error(conn: HTTPConnection, exc: Exception) -> JSONResponse:
    return _respond(report(exc))


async def _validation_error(conn: HTTPConnection, exc: RequestValidationError) -> JSONResponse:
    first = exc.errors()[0] if exc.errors() else {"loc": (), "msg": "invalid request"}
    where = ".".join(str(p) for p in first.get("loc", ()) if p != "body")
    message = f"{where}: {first['msg']}" if where else str(first["msg"])
    return _respond(ApiError(422, "invalid_request", message))


async def _http_error(conn: HTTPConnection, exc: StarletteHTTPException) -> JSONResponse:
    if exc.status_code == 400 and exc.__cause__ is not None:  # FastAPI could not read or parse a JSON body
        return _respond(report(_unparsable(exc.__cause__)))
    codes = {404: "not_found", 405: "method_not_allowed"}
    error = ApiError(exc.status_code, codes.get(exc.status_code, "http_error"), str(exc.detail),
                     headers=dict(exc.headers or {}))
    return _respond(error)


def _unparsable(cause: BaseException) -> Exception:
    """What a JSON body that FastAPI could not read answers: 422 invalid_request, with the reason."""
    if isinstance(cause, ClientDisconnect | ApiError):
        return cause
    reasons = {UnicodeDecodeError: "is not UTF-8", RecursionError: "is nested too deeply"}
    reason = next((text for kind, text in reasons.items() if isinstance(cause, kind)), "is not valid JSON")
    return ApiError(422, "invalid_request", f"the JSON body {reason}")


def install(app: FastAPI) -> None:
    """Register the handlers: domain errors, request validation, plain HTTP errors, anything else (500)."""
    for kind in (ApiError, InvalidExrError, FrameError, UnknownPipelineError, InvalidOptionsError,
                 UnknownSessionError, SessionLostError, ClientDisconnect):
        app.add_exception_handler(kind, _domain_error)
    app.add_exception_handler(RequestValidationError, _validation_error)
    app.add_exception_handler(StarletteHTTPException, _http_error)
    app.add_exception_handler(Exception, _domain_error)  # last resort: a JSON 500, logged
