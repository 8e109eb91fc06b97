"""Auth on (per-client keys) and off: health is open, everything else needs a key, sessions belong to their key."""

from __future__ import annotations

import json

import pytest
from websockets.exceptions import InvalidStatus
from websockets.sync.client import connect

from service.client import Client, ServiceError
from tests.service.api.conftest import HEIGHT, WIDTH, call, exr_post

pytestmark = pytest.mark.timeout(120)
KEY_A, KEY_B = "client-a-key-0123456789", "client-b-key-9876543210"


def bearer(key: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {key}"}


@pytest.fixture()
def secured(make_server) -> str:
    return make_server(api_key=f"{KEY_A}, {KEY_B}")


def test_health_is_open_and_everything_else_needs_a_key(secured, sequence_exr):
    assert call(secured, "GET", "/healthz").status == 200
    assert call(secured, "GET", "/readyz").json()["ready"] is True
    for method, path in (("GET", "/v1/pipelines"), ("GET", "/metrics"), ("GET", "/openapi.json"), ("GET", "/docs"),
                         ("POST", "/v1/sessions"), ("GET", "/v1/sessions/x"), ("DELETE", "/v1/sessions/x")):
        answer = call(secured, method, path)
        assert answer.status == 401, path
        assert answer.json() == {"code": "unauthorized",
                                 "message": "missing API key: send the header 'Authorization: Bearer <key>'"}
        assert answer.headers["www-authenticate"] == "Bearer"
    answer = exr_post(secured, "/v1/denoise", sequence_exr[0], Authorization="Bearer not-a-valid-key-at-all")
    assert (answer.status, answer.json()["message"]) == (401, "invalid API key")
    assert exr_post(secured, "/v1/denoise", sequence_exr[0], Authorization=f"Basic {KEY_A}").status == 401
    for key in (KEY_A, KEY_B):
        assert exr_post(secured, "/v1/denoise", sequence_exr[0], **bearer(key)).status == 200
        assert call(secured, "GET", "/metrics", headers=bearer(key)).status == 200
        assert call(secured, "GET", "/openapi.json", headers=bearer(key)).json()["info"]["title"] == "mcdenoise"


def test_a_session_is_reachable_only_with_the_key_that_made_it(secured, sequence_exr):
    with Client(secured, api_key=KEY_A) as a, Client(secured, api_key=KEY_B) as b:
        session = a.session("bilateral", WIDTH, HEIGHT)
        path = f"/v1/sessions/{session.id}"
        with pytest.raises(ServiceError) as caught:
            b.json("GET", path)
        assert (caught.value.status, caught.value.code) == (404, "unknown_session")
        assert exr_post(secured, f"{path}/frames", sequence_exr[0], **bearer(KEY_B)).status == 404
        assert call(secured, "DELETE", path, headers=bearer(KEY_B)).status == 404
        ws_url = secured.replace("http://", "ws://") + f"{path}/stream"
        for headers, status in (({}, 401), (bearer(KEY_B), 404)):
            with pytest.raises(InvalidStatus) as refused:
                connect(ws_url, additional_headers=headers, open_timeout=30)
            assert refused.value.response.status_code == status
        assert [isinstance(x, bytes) for x in session.stream(sequence_exr[:2])] == [True, True]
        assert session.status()["frames"] == 2
        assert session.close()["frames"] == 2


def test_auth_off_needs_no_key(server, sequence_exr):
    assert call(server, "GET", "/v1/pipelines").status == 200
    assert call(server, "GET", "/openapi.json").status == 200
    body = json.dumps({"width": WIDTH, "height": HEIGHT}).encode()
    answer = call(server, "POST", "/v1/sessions", body, {"Content-Type": "application/json"})
    assert answer.status == 201
    # a key sent to an open service is ignored
    other = call(server, "GET", f"/v1/sessions/{answer.json()['id']}", headers=bearer(KEY_A))
    assert other.status == 200
    call(server, "DELETE", f"/v1/sessions/{answer.json()['id']}")
