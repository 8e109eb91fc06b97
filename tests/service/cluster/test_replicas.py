"""The local replicas' environment (service/cluster/replicas.py): a distinct id and a fair CPU share each."""

from __future__ import annotations

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
