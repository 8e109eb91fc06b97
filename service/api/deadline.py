"""ASGI middleware that bounds how long a client may take to send a request body (slow clients).

A body (EXR frame or JSON) not fully received within MCDENOISE_CLIENT_TIMEOUT_S of the request's start is
answered `408 timeout` with `Connection: close`, so a client trickling bytes cannot hold a connection, a
frame slot's wait or memory for long. Idle keep-alive connections are closed by uvicorn after
`timeout_keep_alive` (5 s). What this does not bound: a client that never finishes its request *headers*
never reaches the app; put a reverse proxy with a header timeout in front of a public deployment.
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
