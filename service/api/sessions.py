"""Sessions: one pipeline state per sequence, its ordering lock, statistics, owner and idle expiry.

A session is the only place where the service keeps per-sequence state. Its id is
`<replica>.<instance>.<token>`: the replica id (MCDENOISE_REPLICA_ID), 32 random bits drawn when the
server starts (`instance_id`: one for all of `serve`'s worker processes), and 256 random bits (URL-safe
base64), so it cannot be guessed. A load balancer
routes a session's requests by the replica part (docs/cluster.md). An id of another replica or of an
earlier instance of this one names a session this process cannot hold: the replica that held it died
or restarted, and it answers `410 session_lost`. When auth is on a session also records a fingerprint
of the API key that created it and is invisible (404) to any other key. Sessions live in one process:
with several uvicorn workers a client must reach the same process for all requests of a session.

The online-training seam (service/online/, pipeline `crossreg`): a session's `online` flag becomes the
pipeline option `online`, refused for pipelines that have no such option; the state's
`online_status` attribute (a dict, or None), if any, is reported as is; a state with a `close()`
method is closed when its session ends (stops its worker).
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import logging
import os
import secrets
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from service import pipelines
from service.api.core.config import REPLICA_ID
from service.api.core.errors import ApiError, InvalidOptionsError, SessionLostError, UnknownSessionError
from service.dialects import ChannelMap
from service.pipelines import Pipeline, SequenceState

log = logging.getLogger("mcdenoise.api")
LATENCY_WINDOW = 1000  # frames kept for a session's p95


@dataclass(frozen=True)
class SessionSpec:
    """What a client asks for when it opens a session (validated by the route's schema)."""

    pipeline: str
    width: int  # pixels
    height: int  # pixels
    options: dict[str, Any] = field(default_factory=dict)
    online: bool = False
    channel_map: dict[str, Any] | None = None  # as sent; parsed by `build_session`
    view_layer: str | None = None


@dataclass
class Session:
    id: str
    spec: SessionSpec
    pipeline: Pipeline
    state: SequenceState
    owner: str | None  # fingerprint of the creating API key, None when auth is off
    channel_map: ChannelMap | None = None  # how its frames' channels make layers (None: the service's default)
    created_at: float = field(default_factory=time.time)  # unix seconds
    last_used: float = field(default_factory=time.monotonic)  # monotonic seconds
    lock: asyncio.Lock = field(default_factory=asyncio.Lock)  # orders the frames of the sequence
    frames: int = 0  # frames denoised
    errors: int = 0  # frames refused or failed (the session went on)
    step_ms: deque[float] = field(default_factory=lambda: deque(maxlen=LATENCY_WINDOW))
    step_ms_total: float = 0.0
    busy: int = 0  # frames accepted and not yet answered; a busy session does not expire
    ended: bool = False

    @property
    def online_status(self) -> dict[str, Any] | None:
        status = getattr(self.state, "online_status", None)
        return dict(status) if isinstance(status, dict) else None

    def record(self, step_ms: float) -> None:
        self.frames += 1
        self.step_ms.append(step_ms)
        self.step_ms_total += step_ms

    def info(self, idle_timeout_s: float) -> dict[str, Any]:
        """The session's public description (GET /v1/sessions/{id})."""
        idle = time.monotonic() - self.last_used
        recent = np.asarray(self.step_ms, np.float64)
        return {
            "id": self.id,
            "pipeline": self.spec.pipeline,
            "width": self.spec.width,
            "height": self.spec.height,
            "options": dataclasses.asdict(self.pipeline.options),
            "online": self.spec.online,
            "temporal": type(self.pipeline).temporal,
            "frames": self.frames,
            "errors": self.errors,
            "mean_ms": round(self.step_ms_total / self.frames, 3) if self.frames else None,
            "p95_ms": round(float(np.percentile(recent, 95)), 3) if recent.size else None,
            "created_at": self.created_at,
            "idle_s": round(idle, 3),
            "expires_in_s": round(max(0.0, idle_timeout_s - idle), 3),
            "online_status": self.online_status,
        }


def build_session(spec: SessionSpec, owner: str | None, session_id: str) -> Session:
    """A new session: the pipeline with its options and a fresh state (CPU work: run it in the pool).

    Raises UnknownPipelineError, or InvalidOptionsError for options the pipeline refuses or a channel map
    that is not one (option `channel_map`).
    """
    cls = pipelines.pipeline_class(spec.pipeline)
    try:
        mapping = None if spec.channel_map is None else ChannelMap.from_json(spec.channel_map)
    except ValueError as err:
        raise InvalidOptionsError(str(err), "channel_map") from err
    options = dict(spec.options)
    if "online" in options:
        raise InvalidOptionsError("ask for online training with the session's 'online' field, not an option")
    has_online = "online" in cls.describe()["options"]
    if spec.online and not has_online:
        raise InvalidOptionsError(f"pipeline '{spec.pipeline}' does not support online training")
    if has_online:
        options["online"] = spec.online
    try:
        pipeline = cls(**options)
        state = pipeline.start(spec.height, spec.width)
    except ValueError as err:  # OptionError: a value outside its declared range, or weights that do not load
        raise InvalidOptionsError(str(err).splitlines()[0], getattr(err, "option", None)) from err
    return Session(session_id, spec, pipeline, state, owner, mapping)


def replica_of(session_id: str) -> str | None:
    """The replica id a session id names (its part before the first '.'), or None for an id of another form."""
    replica, instance, token = (session_id.split(".", 2) + ["", ""])[:3]
    return replica if REPLICA_ID.fullmatch(replica) and instance and token else None


INSTANCE_ENV = "MCDENOISE_INSTANCE_ID"  # set by `serve` for its worker processes (service/cli/serve.py)


def instance_id() -> str:
    """This server's instance: $MCDENOISE_INSTANCE_ID when it is 8 hex digits (`serve` draws one for all its
    worker processes, so that a session reaching a sibling worker answers 404, not session_lost), else 32
    random bits drawn now."""
    given = os.environ.get(INSTANCE_ENV, "")
    return given if len(given) == 8 and all(c in "0123456789abcdef" for c in given) else secrets.token_hex(4)


def close_state(session: Session) -> None:
    """Let the state release what it holds (an online worker); errors are logged, never raised."""
    try:
        session.state.close()
    except Exception:
        log.exception("closing the state of session %s failed", session.id[:8])


class SessionStore:
    """The live sessions of this process, bounded in number, expiring when idle."""

    def __init__(self, max_sessions: int, idle_timeout_s: float, replica_id: str):
        self.max_sessions = max_sessions
        self.idle_timeout_s = idle_timeout_s
        self.replica_id = replica_id
        self.prefix = f"{replica_id}.{instance_id()}."  # of every id this store makes
        self._sessions: dict[str, Session] = {}
        self._reserved = 0  # sessions being built
        self.rejected = 0  # creations answered 429 since start

    def __len__(self) -> int:
        return len(self._sessions)

    def all(self) -> list[Session]:
        return list(self._sessions.values())

    @contextlib.contextmanager
    def reserve(self):
        """Hold a place for a session being built; raises 429 when every place is taken."""
        if len(self._sessions) + self._reserved >= self.max_sessions:
            self.rejected += 1
            raise ApiError(429, "too_many_sessions",
                           f"{self.max_sessions} sessions are live, the most this service keeps; "
                           "end one (DELETE /v1/sessions/{id}) or retry after an idle one expires",
                           retry_after=self._retry_after())
        self._reserved += 1
        try:
            yield
        finally:
            self._reserved -= 1

    def new_id(self) -> str:
        """A fresh session id: this store's prefix and 256 random bits."""
        return self.prefix + secrets.token_urlsafe(32)

    def add(self, session: Session) -> None:
        self._sessions[session.id] = session

    def get(self, session_id: str, owner: str | None) -> Session:
        """The live session `session_id` of `owner`; SessionLostError for an id made by another replica or an
        earlier instance of this one, UnknownSessionError otherwise (also for another owner)."""
        session = self._sessions.get(session_id)
        if session is None and not session_id.startswith(self.prefix) and replica_of(session_id):
            raise SessionLostError(session_id, replica_of(session_id), self.replica_id)
        if session is None or session.ended or session.owner != owner:
            raise UnknownSessionError(session_id)
        session.last_used = time.monotonic()
        return session

    def pop(self, session_id: str, owner: str | None) -> Session:
        session = self.get(session_id, owner)
        self._remove(session)
        return session

    def expire(self) -> list[Session]:
        """End the sessions idle for longer than the timeout (never one with a frame in progress, including a
        frame whose request timed out while its step runs on, holding the lock)."""
        now = time.monotonic()
        idle = [s for s in self._sessions.values()
                if not s.busy and not s.lock.locked() and now - s.last_used > self.idle_timeout_s]
        for session in idle:
            self._remove(session)
        return idle

    def _remove(self, session: Session) -> None:
        session.ended = True
        self._sessions.pop(session.id, None)

    def _retry_after(self) -> int:
        """Seconds until the next idle session expires, at least 1."""
        now = time.monotonic()
        waits = [self.idle_timeout_s - (now - s.last_used) for s in self._sessions.values() if not s.busy]
        return max(1, int(np.ceil(min(waits, default=self.idle_timeout_s))))
