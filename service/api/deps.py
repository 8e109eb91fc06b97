"""Annotated dependencies that keep the routes short: services, the caller, the EXR body, the output wanted.

Auth model: with `MCDENOISE_API_KEY` unset the service is open (set but empty, it refuses to start). With
it set (one key, or several
separated by commas, one per client) every route but /healthz and /readyz needs the header
`Authorization: Bearer <key>`; a wrong or missing key is 401. A session belongs to the key that
created it: another key gets 404 for it, as for a session that does not exist. With one shared key all
clients are one owner, and session ids (256 random bits) are what keeps them apart.
"""

from __future__ import annotations

import hashlib
import hmac
from typing import Annotated

from fastapi import Depends, Header, Query, Request
from starlette.requests import HTTPConnection

from service.api import codec
from service.api.core.config import Settings
from service.api.core.errors import ApiError, unauthorized
from service.api.sessions import Session
from service.api.state import Services


def get_services(conn: HTTPConnection) -> Services:
    return conn.app.state.services


ServicesDep = Annotated[Services, Depends(get_services)]


def get_settings(services: ServicesDep) -> Settings:
    return services.settings


SettingsDep = Annotated[Settings, Depends(get_settings)]


def key_fingerprint(key: str) -> str:
    """Who owns a session: a hash of the API key, never the key itself."""
    return hashlib.sha256(key.encode()).hexdigest()[:24]


def authenticate(conn: HTTPConnection, settings: SettingsDep) -> str | None:
    """The caller's owner id (None when auth is off); 401 without a valid `Authorization: Bearer` key."""
    keys = settings.api_keys
    if not keys:
        return None
    scheme, _, token = conn.headers.get("authorization", "").partition(" ")
    if scheme.lower() != "bearer" or not token.strip():
        raise unauthorized("missing API key: send the header 'Authorization: Bearer <key>'")
    token_bytes = token.strip().encode()
    match = None
    for key in keys:  # compare with every key in constant time
        if hmac.compare_digest(token_bytes, key.encode()):
            match = key
    if match is None:
        raise unauthorized("invalid API key")
    return key_fingerprint(match)


OwnerDep = Annotated[str | None, Depends(authenticate)]


def get_session(session_id: str, services: ServicesDep, owner: OwnerDep) -> Session:
    return services.sessions.get(session_id, owner)


SessionDep = Annotated[Session, Depends(get_session)]


async def exr_body(request: Request, settings: SettingsDep) -> bytes:
    """The request body, checked to be declared as EXR (415) and within the size limit (413)."""
    declared = codec.media_type_of(request.headers.get("content-type"))
    if declared != codec.EXR:
        raise ApiError(415, "unsupported_media_type",
                       f"send one OpenEXR frame with Content-Type: {codec.EXR} (got {declared or 'none'})")
    limit = settings.max_body_bytes
    too_large = ApiError(413, "too_large", f"body is larger than {settings.max_body_mb} MiB, "
                                           "the most this service takes (MCDENOISE_MAX_BODY_MB)")
    length = request.headers.get("content-length", "")
    if length.isdigit() and int(length) > limit:
        raise too_large
    chunks, size = [], 0
    async for chunk in request.stream():
        size += len(chunk)
        if size > limit:
            raise too_large
        chunks.append(chunk)
    if not size:
        raise ApiError(400, "invalid_exr", "body is empty; send one OpenEXR frame")
    return b"".join(chunks)


ExrBody = Annotated[bytes, Depends(exr_body)]


def output_format(
    accept: Annotated[str | None, Header()] = None,
    exposure: Annotated[float, Query(gt=0, le=1e6, description="exposure of a PNG preview")] = 1.0,
) -> codec.Output:
    return codec.choose_output(accept, exposure)


OutputDep = Annotated[codec.Output, Depends(output_format)]
