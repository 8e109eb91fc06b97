"""A small Python client of the HTTP service: denoise one frame, or open a session and stream a sequence.

    client = Client("http://127.0.0.1:8000", api_key=None)
    exr_bytes = client.denoise(Path("frame_0000.exr"), pipeline="bilateral")
    with client.session("bilateral", width=256, height=256) as session:
        results = session.stream_folder("in/", "out/")  # WebSocket, in order; errors per frame

Uses only the standard library for HTTP (one keep-alive connection) and `websockets` (installed with
uvicorn[standard]) for the stream. Errors from the service raise `ServiceError` (REST) or are
yielded/returned in a frame's place (stream), carrying the service's code, message and layer.

Behind `python -m service cluster` a session dies with its replica (`410 session_lost`). With
`reopen_lost=True` a session opens a new one with the same request and resends the frame instead of
raising; the history of a temporal pipeline and any online-training state start afresh (`reopens` counts).
"""

from __future__ import annotations

import http.client
import json
import time
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from urllib.parse import quote, urlencode, urlsplit

from service.exr import join_renders, paired_sequence

EXR = "image/x-exr"
PNG = "image/png"
MAX_BUSY_RETRIES = 3  # REST retries of a 503 busy answer, honouring Retry-After
MAX_RETRY_WAIT_S = 5.0  # longest Retry-After the client waits, seconds

FrameSource = bytes | str | Path  # EXR bytes, or the path of an EXR file


class ServiceError(Exception):
    """An error answer: HTTP `status` (0 for an error message on a stream), `code`, `message`, `layer`."""

    def __init__(self, status: int, code: str, message: str, layer: str | None = None, frame: int | None = None):
        super().__init__(f"{code}: {message}" if status == 0 else f"{status} {code}: {message}")
        self.status, self.code, self.message, self.layer, self.frame = status, code, message, layer, frame

    @classmethod
    def from_body(cls, status: int, body: bytes | str) -> ServiceError:
        try:
            data = json.loads(body)
            return cls(status, data["code"], data["message"], data.get("layer"), data.get("frame"))
        except (ValueError, KeyError, TypeError):
            text = body.decode(errors="replace") if isinstance(body, bytes) else body
            return cls(status, "http_error", text[:200] or http.client.responses.get(status, "error"))


def _read(frame: FrameSource) -> bytes:
    return frame if isinstance(frame, bytes | bytearray) else Path(frame).read_bytes()


class Client:
    """The service at `url` (http://host:port), with an optional API key."""

    def __init__(self, url: str = "http://127.0.0.1:8000", api_key: str | None = None, timeout: float = 120.0):
        parts = urlsplit(url)
        if parts.scheme not in ("http", "https") or not parts.hostname:
            raise ValueError(f"service url must look like http://host:port, got '{url}'")
        self.url = url.rstrip("/")
        self.api_key = api_key
        self.timeout = timeout
        self._parts = parts
        self._conn: http.client.HTTPConnection | None = None

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        if self._conn is not None:
            self._conn.close()
            self._conn = None

    # -- plumbing -------------------------------------------------------------------------------------

    def headers(self, **extra: str) -> dict[str, str]:
        out = dict(extra)
        if self.api_key:
            out["Authorization"] = f"Bearer {self.api_key}"
        return out

    def request(self, method: str, path: str, body: bytes | None = None, headers: dict[str, str] | None = None
                ) -> tuple[int, dict[str, str], bytes]:
        """One request (retried on a 503 busy answer, at most MAX_BUSY_RETRIES times); raises ServiceError >= 400."""
        for attempt in range(MAX_BUSY_RETRIES + 1):
            status, got, data = self._send(method, path, body, self.headers(**(headers or {})))
            if status == 503 and attempt < MAX_BUSY_RETRIES:
                time.sleep(min(float(got.get("retry-after", "1") or 1), MAX_RETRY_WAIT_S))
                continue
            break
        if status >= 400:
            raise ServiceError.from_body(status, data)
        return status, got, data

    def _send(self, method: str, path: str, body: bytes | None, headers: dict[str, str]
              ) -> tuple[int, dict[str, str], bytes]:
        while True:
            reused = self._conn is not None
            if self._conn is None:
                kind = http.client.HTTPSConnection if self._parts.scheme == "https" else http.client.HTTPConnection
                self._conn = kind(self._parts.hostname, self._parts.port, timeout=self.timeout)
            try:
                self._conn.request(method, path, body=body, headers=headers)
                response = self._conn.getresponse()
                data = response.read()
            except (http.client.RemoteDisconnected, ConnectionResetError, BrokenPipeError):
                self.close()
                if reused:  # a kept-alive connection the server had closed: once more on a new one
                    continue
                raise
            got = {k.lower(): v for k, v in response.getheaders()}
            if got.get("connection", "").lower() == "close":
                self.close()
            return response.status, got, data

    def json(self, method: str, path: str, payload: Any = None) -> Any:
        body = None if payload is None else json.dumps(payload).encode()
        headers = {"Content-Type": "application/json"} if body is not None else {}
        return json.loads(self.request(method, path, body, headers)[2])

    # -- API ------------------------------------------------------------------------------------------

    def pipelines(self) -> list[dict[str, Any]]:
        """GET /v1/pipelines: name, summary, requires, optional, temporal, options of each pipeline."""
        return self.json("GET", "/v1/pipelines")["pipelines"]

    def denoise(self, frame: FrameSource, pipeline: str | None = None, *, png: bool = False,
                exposure: float = 1.0) -> bytes:
        """One stateless frame: EXR bytes of the `color` layer, or PNG preview bytes with `png`."""
        query = {"pipeline": pipeline} if pipeline else {}
        if png and exposure != 1.0:
            query["exposure"] = str(exposure)
        path = "/v1/denoise" + (f"?{urlencode(query)}" if query else "")
        headers = {"Content-Type": EXR, "Accept": PNG if png else EXR}
        return self.request("POST", path, _read(frame), headers)[2]

    def session(self, pipeline: str, width: int, height: int, *, options: dict[str, Any] | None = None,
                online: bool = False, channel_map: dict[str, Any] | None = None,
                view_layer: str | None = None, reopen_lost: bool = False) -> Session:
        """Open a session for one sequence of `width` x `height` frames; `channel_map` (its JSON object) and
        `view_layer` say how the server reads the frames' channels (service/dialects.py). `reopen_lost`: replace
        a session lost with its replica by a new one (its history restarts) instead of raising."""
        request = {"pipeline": pipeline, "width": width, "height": height, "options": options or {},
                   "online": online, "channel_map": channel_map, "view_layer": view_layer}
        return Session(self, self.json("POST", "/v1/sessions", request), request, reopen_lost=reopen_lost)


@dataclass(frozen=True)
class StreamResult:
    name: str  # input file name (the output has the same name)
    error: ServiceError | None  # None: written to the output folder


class Session:
    """One sequence on the service; frames go in order through REST (`denoise`) or a WebSocket (`stream`)."""

    def __init__(self, client: Client, info: dict[str, Any], request: dict[str, Any], *, reopen_lost: bool = False):
        self.client = client
        self.request = request  # the POST /v1/sessions body that opened it
        self.reopen_lost = reopen_lost
        self.reopens = 0  # sessions opened again after `session_lost`
        self._use(info)

    def _use(self, info: dict[str, Any]) -> None:
        self.id: str = info["id"]
        self.info = info
        self._path = f"/v1/sessions/{quote(self.id, safe='')}"

    def _reopen_after(self, error: ServiceError) -> bool:
        """Whether `error` lost the session and a new one is open now (only with `reopen_lost`). A 502 (the
        replica failed mid-request) is a loss when the session's status answers `session_lost`."""
        if not self.reopen_lost or error.code not in ("session_lost", "replica_failed"):
            return False
        if error.code == "replica_failed":
            try:
                self.status()
                return False
            except ServiceError as again:
                if again.code != "session_lost":
                    return False
        self._use(self.client.json("POST", "/v1/sessions", self.request))
        self.reopens += 1
        return True

    def __enter__(self) -> Session:
        return self

    def __exit__(self, *exc: object) -> None:
        try:
            self.close()
        except ServiceError:  # already ended or expired
            pass

    def status(self) -> dict[str, Any]:
        """GET /v1/sessions/{id}: frames, errors, mean_ms, p95_ms, online_status, ..."""
        self.info = self.client.json("GET", self._path)
        return self.info

    def close(self) -> dict[str, Any]:
        """End the session; returns its final statistics."""
        return self.client.json("DELETE", self._path)

    def denoise(self, frame: FrameSource) -> bytes:
        """The next frame over REST: denoised EXR bytes (raises ServiceError; the session goes on). With
        `reopen_lost`, a lost session is opened again and the frame sent to the new one."""
        data = _read(frame)
        try:
            return self.client.request("POST", f"{self._path}/frames", data, {"Content-Type": EXR})[2]
        except ServiceError as error:
            if not self._reopen_after(error):
                raise
            return self.client.request("POST", f"{self._path}/frames", data, {"Content-Type": EXR})[2]

    def stream(self, frames: Iterable[FrameSource], *, window: int = 4) -> Iterator[bytes | ServiceError]:
        """Send `frames` over the WebSocket, at most `window` ahead of the answers; yields, in order, the
        denoised EXR bytes of each frame or the ServiceError that took its place. With `reopen_lost`, a lost
        session refused at the handshake is opened again; a stream cut by its replica's death raises
        websockets' ConnectionClosed: stream the frames not answered again, and the session reopens then."""
        pending = 0
        source = iter(frames)
        exhausted = False
        with self._connect() as ws:
            while True:
                while not exhausted and pending < max(1, window):
                    frame = next(source, None)
                    if frame is None:
                        exhausted = True
                        break
                    ws.send(_read(frame))
                    pending += 1
                if not pending:
                    return
                message = ws.recv(timeout=self.client.timeout)
                pending -= 1
                yield message if isinstance(message, bytes) else ServiceError.from_body(0, message)

    def _connect(self):
        """The session's WebSocket, open (a lost session reopened first, with `reopen_lost`)."""
        from websockets.exceptions import InvalidStatus
        from websockets.sync.client import connect  # lazily: REST use needs no websockets

        parts = self.client._parts
        scheme = "wss" if parts.scheme == "https" else "ws"

        def open_stream():
            return connect(f"{scheme}://{parts.netloc}{self._path}/stream", additional_headers=self.client.headers(),
                           max_size=None, compression=None, open_timeout=self.client.timeout, close_timeout=5)

        try:
            return open_stream()
        except InvalidStatus as refused:
            answer = refused.response
            if not self._reopen_after(ServiceError.from_body(answer.status_code, answer.body or b"")):
                raise
        return open_stream()

    def stream_folder(self, in_dir: str | Path, out_dir: str | Path, *, window: int = 4,
                      second_half: str | Path | None = None) -> list[StreamResult]:
        """Stream every frame of a sequence folder; write each denoised frame as `out_dir/<same name>`. With
        `second_half`, a folder of a second render of the same frames (another seed), frame i of both goes
        as one two-part EXR (`service.exr.join_renders`): the halves of frame i."""
        pairs = paired_sequence(in_dir, second_half)
        paths = [path for path, _ in pairs]
        out_dir = Path(out_dir)
        out_dir.mkdir(parents=True, exist_ok=True)
        sources: Iterable[FrameSource] = paths
        if second_half is not None:
            sources = (join_renders(a, b) for a, b in pairs)
        results = []
        for path, answer in zip(paths, self.stream(sources, window=window), strict=True):
            if isinstance(answer, ServiceError):
                results.append(StreamResult(path.name, answer))
            else:
                (out_dir / path.name).write_bytes(answer)
                results.append(StreamResult(path.name, None))
        return results
