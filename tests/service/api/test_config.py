"""Settings from the environment: documented defaults, automatic values, refusal of unsafe values."""

from __future__ import annotations

import socket

import pytest

from service import pipelines
from service.api.core.config import Settings, SettingsError


def test_defaults_and_automatic_values():
    s = Settings.from_env({})
    assert (s.max_body_mb, s.max_width, s.max_height, s.max_sessions, s.session_idle_s) == (256, 4096, 4096, 16, 300.0)
    assert s.worker_threads >= 1 and s.frame_threads >= 1 and s.max_inflight == 4 * s.worker_threads
    assert s.api_keys == () and s.public()["auth"] == "off" and "api_key" not in s.public()
    assert s.replica_id == socket.gethostname().split(".")[0] and Settings(replica_id=" r7 ").replica_id == "r7"


def test_values_from_the_environment():
    s = Settings.from_env({"MCDENOISE_MAX_SESSIONS": "3", "MCDENOISE_SESSION_IDLE_S": "2.5",
                           "MCDENOISE_WORKER_THREADS": "2", "MCDENOISE_MAX_INFLIGHT": "",
                           "MCDENOISE_API_KEY": "abcdefghijklmnop, qrstuvwxyz012345"})
    assert (s.max_sessions, s.session_idle_s, s.worker_threads, s.max_inflight) == (3, 2.5, 2, 8)
    assert s.api_keys == ("abcdefghijklmnop", "qrstuvwxyz012345") and s.public()["auth"] == "per-client keys"


@pytest.mark.parametrize(("env", "message"), [
    ({"MCDENOISE_MAX_SESSIONS": "0"}, "MCDENOISE_MAX_SESSIONS must be at least 1, got 0"),
    ({"MCDENOISE_MAX_WIDTH": "wide"}, "MCDENOISE_MAX_WIDTH must be an integer, got 'wide'"),
    ({"MCDENOISE_SESSION_IDLE_S": "0"}, "MCDENOISE_SESSION_IDLE_S must be > 0"),
    ({"MCDENOISE_API_KEY": "short"}, "MCDENOISE_API_KEY: every key must have at least 16 characters"),
    ({"MCDENOISE_API_KEY": " , "}, "MCDENOISE_API_KEY holds no key"),
    ({"MCDENOISE_WORKER_THREADS": "4", "MCDENOISE_MAX_INFLIGHT": "2"},
     "MCDENOISE_MAX_INFLIGHT (2) must be at least MCDENOISE_WORKER_THREADS (4)"),
    ({"MCDENOISE_MAX_BODY_MB": "5000"}, "MCDENOISE_MAX_BODY_MB must be at most 4096, got 5000"),
    ({"MCDENOISE_REPLICA_ID": "r.1"}, "MCDENOISE_REPLICA_ID must be 1 to 63 letters, digits, '-' or '_' (no '.')"),
    ({"MCDENOISE_REPLICA_ID": "-r1"}, "MCDENOISE_REPLICA_ID must be 1 to 63 letters"),
    ({"MCDENOISE_WARMUP": "flr, nope"}, "MCDENOISE_WARMUP: unknown pipeline 'nope'; available: auto, bilateral"),
])
def test_unsafe_values_are_refused(env, message):
    with pytest.raises(SettingsError) as caught:
        Settings.from_env(env)
    assert str(caught.value).startswith(message)


def test_serve_refuses_bad_settings_before_binding(monkeypatch, capsys):
    from service.cli import main

    monkeypatch.setenv("MCDENOISE_MAX_SESSIONS", "-1")
    assert main(["serve", "--port", "1"]) == 2
    assert capsys.readouterr().err.strip() == "error: MCDENOISE_MAX_SESSIONS must be at least 1, got -1"


def test_warmup_lists_pipelines_in_order():
    settings = Settings.from_env({"MCDENOISE_WARMUP": " crossregression, flr ,"})
    assert settings.warmup_pipelines == ("crossregression", "flr")
    assert Settings().warmup_pipelines == ()
    assert Settings.from_env({"MCDENOISE_WARMUP": "default,flr"}).warmup_pipelines == (pipelines.DEFAULT, "flr")
