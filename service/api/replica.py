"""`X-Replica`: every answer names the replica that gave it (MCDENOISE_REPLICA_ID), HTTP and WebSocket
handshakes alike, 4xx and 5xx errors of the service's own included, so a client or a load balancer's log
can tell the replicas apart. An unexpected exception's 500 is built by Starlette's outermost middleware,
outside this one, and carries no `X-Replica`."""

from __future__ import annotations

from starlette.types import ASGIApp, Message, Receive, Scope, Send

HEADER = "X-Replica"
# ASGI messages that start an answer and carry its headers: an HTTP response, a WebSocket accept, the
# HTTP response that refuses a WebSocket handshake.
_STARTS = ("http.response.start", "websocket.accept", "websocket.http.response.start")


class ReplicaHeader:
    """ASGI middleware adding `X-Replica: <replica_id>` to every answer."""

    def __init__(self, app: ASGIApp, replica_id: str):
        self.app = app
        self.header = (HEADER.lower().encode(), replica_id.encode())

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] not in ("http", "websocket"):
            await self.app(scope, receive, send)
            return

        async def send_with_header(message: Message) -> None:
            if message["type"] in _STARTS:
                message = {**message, "headers": [*message.get("headers", []), self.header]}
            await send(message)

        await self.app(scope, receive, send_with_header)
