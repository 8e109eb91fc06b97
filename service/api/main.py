"""Builds the FastAPI app: settings, lifespan (worker pool, sessions, expiry), routers, auth, error mapping.

`uvicorn service.api.main:create_app --factory` serves it; `python -m service serve` does the same with
the settings checked first.
"""

from __future__ import annotations

from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

from fastapi import Depends, FastAPI

from service.api.core import errors
from service.api.core.config import Settings
from service.api.deadline import BodyDeadline
from service.api.deps import authenticate
from service.api.replica import ReplicaHeader
from service.api.routes import denoise, docs, health, metrics, pipelines, sessions, stream
from service.api.state import Services
from service.process import configure

DESCRIPTION = """Denoises Monte Carlo path-traced frames (OpenEXR in, OpenEXR or PNG out) with every registered
pipeline: single frames over REST, or a session per sequence over REST or a WebSocket stream.
With MCDENOISE_API_KEY set, send `Authorization: Bearer <key>` to every route but /healthz and /readyz."""


def create_app(settings: Settings | None = None) -> FastAPI:
    """The app; `settings` default to the environment (`Settings.from_env`). The server's entry point (uvicorn
calls it in each worker process), so it applies `service.process.configure()`."""
    configure()
    settings = settings or Settings.from_env()

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        app.state.services = Services.start(settings)
        try:
            yield
        finally:
            await app.state.services.stop()

    app = FastAPI(
        title="mcdenoise",
        version="0.1.0",
        description=DESCRIPTION,
        lifespan=lifespan,
        docs_url=None,
        redoc_url=None,
        openapi_url=None,  # served by routes/docs.py, behind the API key
        redirect_slashes=False,  # `/metrics/` is 404, not a redirect before auth with a Location from Host
    )
    errors.install(app)
    app.add_middleware(BodyDeadline, seconds=settings.client_timeout_s)
    app.add_middleware(ReplicaHeader, replica_id=settings.replica_id)  # outermost: on every answer
    app.include_router(health.router)
    protected = [Depends(authenticate)]
    for module in (pipelines, denoise, sessions, stream, metrics, docs):
        app.include_router(module.router, dependencies=protected)
    return app
