"""Deployment settings of the HTTP service: one validated, frozen object built from environment variables.

Every variable is optional; the defaults below are the documented ones (README "HTTP API"). Values
that would make the service unsafe or unable to work (a limit of zero, a short API key, a key with
whitespace, an API key variable that is set but empty) are refused with a `SettingsError` naming the
variable, before the server starts. Auth is off only when MCDENOISE_API_KEY is not set at all.
"""

from __future__ import annotations

import os
import re
import socket
from collections.abc import Mapping
from dataclasses import dataclass, fields
from functools import cached_property
from pathlib import Path

from service import pipelines
from service.dialects import ChannelMap
from service.runtime import WEIGHTS_DIR_ENV

PREFIX = "MCDENOISE_"
MIN_KEY_LENGTH = 16  # characters; shorter keys are guessable
# A replica id: a DNS label without dots (it is the first dot-separated part of a session id), at most 63 characters.
REPLICA_ID = re.compile(r"[A-Za-z0-9](?:[A-Za-z0-9_-]{0,61}[A-Za-z0-9])?")


class SettingsError(ValueError):
    """An environment variable with a value the service refuses."""


def usable_cpus() -> int:
    """The CPUs this process may run on."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        return max(1, os.cpu_count() or 1)


@dataclass(frozen=True)
class Settings:
    """Deployment settings; field `x` is read from `MCDENOISE_X` (upper case)."""

    max_body_mb: int = 256  # largest request body / WebSocket message, MiB
    max_width: int = 4096  # largest frame width, pixels
    max_height: int = 4096  # largest frame height, pixels
    max_sessions: int = 16  # live sessions at once; more answers 429
    session_idle_s: float = 300.0  # a session without a request for this long is ended, seconds
    worker_threads: int = 0  # frames processed at once (thread pool size); 0 = number of CPUs
    frame_threads: int = 0  # threads one frame may use inside ONNX Runtime/numba/BLAS; 0 = CPUs / workers
    max_inflight: int = 0  # frames accepted (running + queued) at once; more answers 503; 0 = 4 x workers
    queue_wait_s: float = 30.0  # how long a streamed frame waits for a free slot before a `busy` error, s
    retry_after_s: int = 1  # Retry-After of a 503 `busy` answer, seconds
    max_frame_mb: int = 8192  # per-frame memory budget, MiB: a larger estimate from the EXR header answers 413
    frame_timeout_s: float = 120.0  # a frame not answered this long after it was accepted answers 504, seconds
    # a request's headers (`serve`: the connection is closed) and body (408) must arrive within this, seconds
    client_timeout_s: float = 60.0
    api_key: str | None = None  # None (variable unset): no auth; one key, or comma-separated keys (one per client)
    warmup: str = ""  # comma-separated pipelines run on generated frames at start (not ready until done);
    # `default` names the API's default pipeline (pipelines.DEFAULT)
    channel_map: str = ""  # a JSON channel map file (service/dialects.py) for frames without one of their session
    view_layer: str = ""  # the Blender view layer to read from files with several, for frames without a session's
    # this replica's id, named by its session ids and X-Replica answers (docs/cluster.md); "" = the host name's
    # first label (a StatefulSet pod's name, a container's id)
    replica_id: str = ""

    def __post_init__(self) -> None:
        if self.channel_map:
            try:
                self.default_channel_map  # noqa: B018 - parsed once here, so that a bad file refuses the start
            except ValueError as err:
                raise SettingsError(f"{PREFIX}CHANNEL_MAP: {err}") from None
        for name in ("max_body_mb", "max_width", "max_height", "max_sessions", "retry_after_s"):
            if getattr(self, name) < 1:
                raise SettingsError(f"{PREFIX}{name.upper()} must be at least 1, got {getattr(self, name)}")
        for name in ("worker_threads", "frame_threads", "max_inflight"):
            if getattr(self, name) < 0:
                raise SettingsError(f"{PREFIX}{name.upper()} must be 0 (automatic) or more, got {getattr(self, name)}")
        if self.session_idle_s <= 0 or self.queue_wait_s < 0:
            raise SettingsError(
                f"{PREFIX}SESSION_IDLE_S must be > 0 and {PREFIX}QUEUE_WAIT_S >= 0, "
                f"got {self.session_idle_s} and {self.queue_wait_s}"
            )
        for name in ("max_frame_mb", "frame_timeout_s", "client_timeout_s"):
            if not getattr(self, name) > 0:
                raise SettingsError(f"{PREFIX}{name.upper()} must be > 0, got {getattr(self, name)}")
        if self.max_body_mb > 4096:
            raise SettingsError(f"{PREFIX}MAX_BODY_MB must be at most 4096, got {self.max_body_mb}")
        for key in self.api_keys:
            if len(key) < MIN_KEY_LENGTH or any(c.isspace() for c in key):
                raise SettingsError(
                    f"{PREFIX}API_KEY: every key must have at least {MIN_KEY_LENGTH} characters and no whitespace"
                )
        if self.api_key is not None and not self.api_keys:
            raise SettingsError(f"{PREFIX}API_KEY holds no key (it is set but empty or blank); set a key of "
                                f"{MIN_KEY_LENGTH}+ characters, or leave the variable unset to run without auth")
        for name in self.warmup_pipelines:
            try:
                pipelines.pipeline_class(name)
            except pipelines.UnknownPipelineError as error:
                raise SettingsError(f"{PREFIX}WARMUP: {error}") from None
        object.__setattr__(self, "replica_id", self.replica_id.strip() or socket.gethostname().split(".")[0])
        if not REPLICA_ID.fullmatch(self.replica_id):
            raise SettingsError(f"{PREFIX}REPLICA_ID must be 1 to 63 letters, digits, '-' or '_' (no '.'), starting "
                                f"and ending with a letter or digit, got {self.replica_id!r}")
        # Resolve the automatic values once, so every reader sees the same numbers.
        workers = self.worker_threads or usable_cpus()
        object.__setattr__(self, "worker_threads", workers)
        object.__setattr__(self, "frame_threads", self.frame_threads or max(1, usable_cpus() // workers))
        object.__setattr__(self, "max_inflight", self.max_inflight or 4 * workers)
        if self.max_inflight < workers:
            raise SettingsError(f"{PREFIX}MAX_INFLIGHT ({self.max_inflight}) must be at least "
                                f"{PREFIX}WORKER_THREADS ({workers})")

    @property
    def api_keys(self) -> tuple[str, ...]:
        """The accepted keys; empty when auth is off."""
        return tuple(k.strip() for k in (self.api_key or "").split(",") if k.strip())

    @property
    def warmup_pipelines(self) -> tuple[str, ...]:
        """The pipelines to warm up at start, in order (`default`: pipelines.DEFAULT)."""
        names = (name.strip() for name in self.warmup.split(","))
        return tuple(pipelines.DEFAULT if name == "default" else name for name in names if name)

    @cached_property
    def default_channel_map(self) -> ChannelMap | None:
        """The parsed MCDENOISE_CHANNEL_MAP file, or None (checked when the settings are made)."""
        return ChannelMap.from_json(self.channel_map) if self.channel_map else None

    @property
    def max_body_bytes(self) -> int:
        return self.max_body_mb * 1024 * 1024

    @classmethod
    def from_env(cls, environ: Mapping[str, str] | None = None) -> Settings:
        """Settings from `MCDENOISE_*` variables of `environ` (default: the process environment)."""
        environ = os.environ if environ is None else environ
        values: dict[str, object] = {}
        for f in fields(cls):
            raw = environ.get(PREFIX + f.name.upper())
            if raw is None or (raw.strip() == "" and f.name != "api_key"):  # a set but empty key is refused
                continue
            kind = str if f.default is None else type(f.default)
            try:
                values[f.name] = raw if kind is str else kind(raw.strip())
            except ValueError:
                raise SettingsError(
                    f"{PREFIX}{f.name.upper()} must be {'an integer' if kind is int else 'a number'}, got {raw!r}"
                ) from None
        # Read by service.runtime.weight_files (the CLI too), checked here so that `serve` refuses a bad one.
        weights_dir = environ.get(WEIGHTS_DIR_ENV, "").strip()
        if weights_dir and not Path(weights_dir).is_dir():
            raise SettingsError(f"{WEIGHTS_DIR_ENV} must name a folder of .onnx weights, got {weights_dir!r}")
        return cls(**values)

    def public(self) -> dict[str, object]:
        """The settings without secrets (for logs and /readyz)."""
        out = {f.name: getattr(self, f.name) for f in fields(self) if f.name != "api_key"}
        out["auth"] = "per-client keys" if len(self.api_keys) > 1 else ("one key" if self.api_keys else "off")
        return out
