"""Deadlines for slow clients, both MCDENOISE_CLIENT_TIMEOUT_S.

- `BodyDeadline` (ASGI middleware): a request body (EXR frame or JSON) not fully received within the
  timeout of the request's start is answered `408 timeout` with `Connection: close`.
- `header_deadline_protocol` (uvicorn HTTP protocol, used by `python -m service serve`): a connection that
  has not completed a request's headers within the timeout of opening (or of its previous answer) is
  closed, so a client trickling header bytes cannot hold a connection; uvicorn itself only times out
  idle keep-alive connections (`timeout_keep_alive`, 5 s).
So a client trickling bytes cannot hold a connection, a frame slot's wait or memory for long.
"""

from __future__ import annotations

import asyncio

from starlette.types import ASGIApp, Message, Receive, Scope, Send

from service.api.core.errors import ApiError


class BodyDeadline:
    def __init__(self, app: ASGIApp, seconds: float):
        self.app = app
        self.seconds = seconds

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        loop = asyncio.get_running_loop()
        end = loop.time() + self.seconds
        complete = False

        async def receive_by_deadline() -> Message:
            nonlocal complete
            if complete:  # the body is in: later calls wait for a disconnect, which takes as long as it takes
                return await receive()
            try:
                message = await asyncio.wait_for(receive(), max(0.0, end - loop.time()))
            except TimeoutError:
                message = f"the request body did not arrive within {self.seconds:g} s (MCDENOISE_CLIENT_TIMEOUT_S)"
                raise ApiError(408, "timeout", message, headers={"Connection": "close"}) from None
            complete = message["type"] != "http.request" or not message.get("more_body", False)
            return message

        await self.app(scope, receive_by_deadline, send)


def header_deadline_protocol(seconds: float) -> type | str:
    """uvicorn's httptools protocol, closing a connection whose request headers take longer than `seconds`
    (from the connection's start or its previous answer); "auto" (no header deadline) without httptools."""
    try:
        from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol
    except ImportError:  # uvicorn[standard] brings httptools; without it uvicorn picks h11
        return "auto"

    class HeaderDeadline(HttpToolsProtocol):
        _header_timer: asyncio.TimerHandle | None = None

        def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
            super().connection_made(transport)
            self._arm()

        def on_headers_complete(self) -> None:
            self._disarm()
            super().on_headers_complete()

        def on_response_complete(self) -> None:
            super().on_response_complete()
            if self.timeout_keep_alive_task is not None:  # idle, waiting for the next request
                self._arm()

        def connection_lost(self, exc: Exception | None) -> None:
            self._disarm()
            super().connection_lost(exc)

        def _arm(self) -> None:
            self._disarm()
            self._header_timer = self.loop.call_later(seconds, self._headers_late)

        def _disarm(self) -> None:
            if self._header_timer is not None:
                self._header_timer.cancel()
                self._header_timer = None

        def _headers_late(self) -> None:
            self._header_timer = None
            if not self.transport.is_closing():
                self.transport.close()

    return HeaderDeadline
