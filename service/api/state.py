"""What one app instance holds while it runs: settings, worker pool, sessions, metrics, shared pipelines."""

from __future__ import annotations

import asyncio
import logging
from dataclasses import dataclass, field

from service import pipelines
from service.api.core.config import Settings
from service.api.sessions import SessionStore, close_state
from service.api.telemetry import Metrics
from service.api.workers import WorkerPool
from service.pipelines import Pipeline
from service.warmup import warm_up

log = logging.getLogger("mcdenoise.api")


@dataclass
class Services:
    settings: Settings
    pool: WorkerPool
    sessions: SessionStore
    metrics: Metrics = field(default_factory=Metrics)
    ready: bool = False
    warming: list[str] = field(default_factory=list)  # pipelines still warming up (not ready until empty)
    # One shared pipeline object per name for stateless REST frames (its state is per request).
    _stateless: dict[str, Pipeline] = field(default_factory=dict)
    _expiry: asyncio.Task | None = None
    _warmup: asyncio.Task | None = None

    @classmethod
    def start(cls, settings: Settings) -> Services:
        """Build the services and start the idle-expiry loop (call inside the running event loop)."""
        services = cls(
            settings,
            WorkerPool(settings.worker_threads, settings.max_inflight, settings.retry_after_s),
            SessionStore(settings.max_sessions, settings.session_idle_s, settings.replica_id),
        )
        loop = asyncio.get_running_loop()
        services._expiry = loop.create_task(services._expire_forever())
        services.warming = list(settings.warmup_pipelines)
        if services.warming:
            services._warmup = loop.create_task(services._warm_up())
        else:
            services._become_ready()
        return services

    def _become_ready(self) -> None:
        self.ready = True
        log.info("mcdenoise service ready: %s", self.settings.public())

    async def _warm_up(self) -> None:
        """Warm the configured pipelines one after another in the default executor, then become ready.
        A pipeline that fails to warm up is logged and skipped: its real frames will report the error."""
        loop = asyncio.get_running_loop()
        while self.warming:
            name = self.warming[0]
            try:
                seconds = await loop.run_in_executor(None, warm_up, self.stateless_pipeline(name))
                log.info("warmed up pipeline %s in %.1f s", name, seconds)
            except Exception:
                log.exception("warm-up of pipeline %s failed", name)
            self.warming.pop(0)
        self._become_ready()

    async def stop(self) -> None:
        self.ready = False
        for task in (self._expiry, self._warmup):
            if task is not None:
                task.cancel()
        for session in self.sessions.all():
            self.sessions.pop(session.id, session.owner)
            close_state(session)
        self.pool.shutdown()

    def stateless_pipeline(self, name: str) -> Pipeline:
        """The shared pipeline `name` with default options (raises UnknownPipelineError)."""
        if name not in self._stateless:
            self._stateless[name] = pipelines.get(name)
        return self._stateless[name]

    async def _expire_forever(self) -> None:
        period = min(5.0, self.settings.session_idle_s / 4)
        while True:
            await asyncio.sleep(period)
            expired = self.sessions.expire()
            if expired:
                self.metrics.session_expired(len(expired))
                log.info("expired %d idle session(s)", len(expired))
                for session in expired:
                    await asyncio.get_running_loop().run_in_executor(None, close_state, session)

