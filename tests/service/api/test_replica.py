"""Replicas (docs/cluster.md): session ids name their replica and its instance, an id of another one answers
410 session_lost, every answer carries X-Replica, and the client reopens a lost session when asked to."""

from __future__ import annotations

import warnings

import pytest

with warnings.catch_warnings():  # starlette's test client still runs on httpx, and says it will not forever
    warnings.filterwarnings("ignore", message="Using `httpx` with `starlette.testclient` is deprecated")
    from fastapi.testclient import TestClient
    from starlette.testclient import WebSocketDenialResponse

from service.api.core.config import Settings
from service.api.main import create_app
from service.api.sessions import SessionStore, replica_of
from service.client import Client, ServiceError
from tests.service.api.conftest import HEIGHT, WIDTH

SPEC = {"pipeline": "bilateral", "width": WIDTH, "height": HEIGHT}


@pytest.fixture(scope="module")
def app_client():
    with TestClient(create_app(Settings(replica_id="r1", max_sessions=4))) as client:
        yield client


def test_session_ids_name_the_replica_and_the_instance():
    store = SessionStore(4, 60.0, "r1")
    first, again = store.new_id(), SessionStore(4, 60.0, "r1").new_id()
    assert first.startswith(store.prefix) and replica_of(first) == replica_of(again) == "r1"
    assert first.split(".")[1] != again.split(".")[1] and len(first.split(".")[2]) == 43  # 256 bits, base64
    assert [replica_of(i) for i in ("r1", "r1.ab", "nonsense", ".ab.cd", "r..x", "-a.b.c")] == [None] * 6
    assert replica_of("r2.x.y.z") == "r2"


def test_every_answer_names_the_replica(app_client):
    created = app_client.post("/v1/sessions", json=SPEC)
    assert created.status_code == 201 and created.json()["id"].startswith("r1.")
    for answer in (created, app_client.get("/healthz"), app_client.get("/nope"),
                   app_client.post("/v1/sessions", json={**SPEC, "width": 0})):
        assert answer.headers["x-replica"] == "r1", answer.status_code
    with app_client.websocket_connect(f"/v1/sessions/{created.json()['id']}/stream") as ws:
        assert (b"x-replica", b"r1") in ws.extra_headers  # the accept message's headers
    with pytest.raises(WebSocketDenialResponse) as denied:
        with app_client.websocket_connect("/v1/sessions/r2.0a0b0c0d.token/stream"):
            pass
    assert denied.value.status_code == 410 and denied.value.headers["x-replica"] == "r1"


@pytest.mark.parametrize(("forge", "holder"), [
    (lambda sid: "r2." + sid.split(".", 1)[1], "replica 'r2'"),
    (lambda sid: "r1.00000000." + sid.split(".", 2)[2], "an earlier instance of this replica"),
])
def test_a_session_of_another_replica_or_instance_is_lost(app_client, forge, holder):
    sid = forge(app_client.post("/v1/sessions", json=SPEC).json()["id"])
    for answer in (app_client.get(f"/v1/sessions/{sid}"), app_client.delete(f"/v1/sessions/{sid}")):
        assert answer.status_code == 410
        assert answer.json() == {"code": "session_lost", "message": (
            f"session '{sid}' is lost: {holder} held it and stopped or restarted (this is replica 'r1'); "
            "open a new session, whose history starts afresh")}
    assert app_client.get("/v1/sessions/r1-no-dots").json()["code"] == "unknown_session"


def test_the_client_reopens_a_lost_session_only_when_asked(make_server, sequence_exr):
    url = make_server(replica_id="r1")
    with Client(url) as client:
        plain, reopening = client.session(**SPEC), client.session(**SPEC, reopen_lost=True)
        for session in (plain, reopening):
            session.denoise(sequence_exr[0])
            session._use({"id": "r9." + session.id.split(".", 1)[1]})  # as if its replica had died
        with pytest.raises(ServiceError) as caught:
            plain.denoise(sequence_exr[1])
        assert (caught.value.status, caught.value.code) == (410, "session_lost")
        assert reopening.denoise(sequence_exr[1])[:4] == b"\x76\x2f\x31\x01" and reopening.reopens == 1
        assert reopening.id.startswith("r1.") and reopening.status()["frames"] == 1  # history restarted
        reopening._use({"id": "r9." + reopening.id.split(".", 1)[1]})
        assert sum(not isinstance(out, ServiceError) for out in reopening.stream(sequence_exr[:3])) == 3
        assert reopening.reopens == 2 and reopening.status()["frames"] == 3


def test_worker_processes_of_one_server_share_its_instance(monkeypatch):
    """`serve` draws one instance for its worker processes: a session reaching a sibling worker is unknown
    there (404), not lost (410)."""
    from service.api.core.errors import UnknownSessionError
    from service.api.sessions import INSTANCE_ENV

    monkeypatch.setenv(INSTANCE_ENV, "0123abcd")
    first, sibling = SessionStore(4, 60.0, "r1"), SessionStore(4, 60.0, "r1")
    assert first.prefix == sibling.prefix == "r1.0123abcd."
    with pytest.raises(UnknownSessionError):
        sibling.get(first.new_id(), None)
    monkeypatch.setenv(INSTANCE_ENV, "not hex!")
    assert SessionStore(4, 60.0, "r1").prefix != first.prefix  # a malformed value: drawn afresh


def test_the_schema_documents_session_lost_on_every_session_route():
    paths = create_app(Settings(replica_id="r1")).openapi()["paths"]
    for path, method in (("/v1/sessions/{session_id}", "get"), ("/v1/sessions/{session_id}", "delete"),
                         ("/v1/sessions/{session_id}/frames", "post")):
        assert "410" in paths[path][method]["responses"], (path, method)
