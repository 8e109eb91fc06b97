"""The local replicas' environment (service/cluster/replicas.py): a distinct id and a fair CPU share each; the
`cluster` command's option checks."""

from __future__ import annotations

import pytest

from service.cluster.replicas import replica_environment


def test_each_replica_gets_its_id_and_a_fair_share_of_the_cpus():
    env = replica_environment({"PATH": "/bin"}, "r2", replicas=3, cpus=8)
    assert env == {"PATH": "/bin", "MCDENOISE_REPLICA_ID": "r2", "MCDENOISE_WORKER_THREADS": "2",
                   "MCDENOISE_FRAME_THREADS": "1"}
    assert replica_environment({}, "r0", replicas=3, cpus=2)["MCDENOISE_WORKER_THREADS"] == "1"  # at least one


def test_thread_settings_given_by_the_operator_win():
    env = replica_environment({"MCDENOISE_WORKER_THREADS": "1", "MCDENOISE_REPLICA_ID": "x"}, "r0", replicas=2,
                              cpus=8)
    assert (env["MCDENOISE_REPLICA_ID"], env["MCDENOISE_WORKER_THREADS"], env["MCDENOISE_FRAME_THREADS"]) == (
        "r0", "1", "4")
    assert replica_environment({"MCDENOISE_FRAME_THREADS": "3"}, "r0", 2, 8)["MCDENOISE_FRAME_THREADS"] == "3"


@pytest.mark.parametrize(("argv", "message"), [
    (["--replicas", "0"], "--replicas must be 1 to 64, got 0"),
    (["--port", "70000"], "--port must be a TCP port, got 70000"),
    (["--port", "8000", "--stats-port", "8000"], "--stats-port must differ from --port (8000)"),
    (["--host", "::1"], "--host must be an IPv4 address or a host name, got '::1'"),
    (["--start-timeout", "0"], "--start-timeout must be > 0, got 0.0"),
])
def test_bad_cluster_options_exit_2_naming_the_option(argv, message, capsys):
    from service.cli import main

    assert main(["cluster", *argv]) == 2
    assert capsys.readouterr().err.strip() == f"error: {message}"
