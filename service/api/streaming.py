"""The WebSocket stream of a session: each binary message in is one EXR frame, each binary message out is
its denoised EXR, in the same order. A frame that cannot be denoised is answered by one JSON text
message `{code, message, layer?, frame}` (frame: 0-based index of the message in this stream) in its
place, and the stream goes on. Frames are taken one at a time: a client may send ahead, TCP holds the
rest. A frame waits up to MCDENOISE_QUEUE_WAIT_S for a free slot before a `busy` error.
The stream ends when the client closes it, or with close code 1000 once its session has ended.
"""

from __future__ import annotations

import json
import logging

from starlette.websockets import WebSocket, WebSocketDisconnect

from service.api import codec
from service.api.core.errors import ApiError, UnknownSessionError, report
from service.api.frames import session_frame
from service.api.sessions import Session
from service.api.state import Services

log = logging.getLogger("mcdenoise.api")
_EXR_OUT = codec.Output(codec.EXR)


async def serve_stream(websocket: WebSocket, services: Services, session: Session) -> None:
    """Answer the frames of an accepted WebSocket until the client leaves or the session ends."""
    index = 0
    try:
        while True:
            message = await websocket.receive()
            if message["type"] == "websocket.disconnect":
                return
            if session.ended:
                await _send_error(websocket, UnknownSessionError(session.id), index)
                await websocket.close(code=1000, reason="session ended")
                return
            data = message.get("bytes")
            if data is None:
                error = ApiError(400, "invalid_message", "expected a binary message holding one EXR frame, got text")
                await _send_error(websocket, error, index)
            elif len(data) > services.settings.max_body_bytes:
                error = ApiError(413, "too_large", f"message is larger than {services.settings.max_body_mb} MiB")
                await _send_error(websocket, error, index)
            else:
                try:
                    result = await session_frame(services, session, data, _EXR_OUT, route="stream",
                                                 wait=services.settings.queue_wait_s)
                except Exception as exc:
                    await _send_error(websocket, exc, index)
                else:
                    await websocket.send_bytes(result.body)
            index += 1
    except WebSocketDisconnect:
        return


async def _send_error(websocket: WebSocket, exc: Exception, index: int) -> None:
    await websocket.send_text(json.dumps({**report(exc).body(), "frame": index}))
