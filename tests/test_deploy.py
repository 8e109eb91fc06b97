"""The deployment files agree with the code: compose and Kubernetes files parse, the probes and checks use
the service's routes, the replica id variable is the one Settings reads, and the Kubernetes HAProxy
configuration is what service/cluster/haproxy.py writes for its StatefulSet's pods."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest
import yaml

from service.api.core.config import PREFIX, Settings
from service.cluster.haproxy import READY_PATH, ProxyOptions, Replica, render

ROOT = Path(__file__).resolve().parents[1]
REPLICA_ENV = PREFIX + "REPLICA_ID"


def _documents(path: str) -> dict[str, dict]:
    return {doc["kind"]: doc for doc in yaml.safe_load_all((ROOT / path).read_text())}


def test_kubernetes_replicas_name_themselves_and_haproxy_routes_to_them():
    replicas, proxy = _documents("deploy/k8s/replicas.yaml"), _documents("deploy/k8s/haproxy.yaml")
    spec = replicas["StatefulSet"]["spec"]
    container = spec["template"]["spec"]["containers"][0]
    assert container["readinessProbe"]["httpGet"] == {"path": READY_PATH, "port": 8000}
    assert {"name": REPLICA_ENV, "valueFrom": {"fieldRef": {"fieldPath": "metadata.name"}}} in container["env"]
    assert replicas["Service"]["spec"]["clusterIP"] == "None" and spec["serviceName"] == "mcdenoise"
    pods = [f"mcdenoise-{i}" for i in range(spec["replicas"])]
    expected = render([Replica(pod, f"{pod}.mcdenoise.default.svc.cluster.local:8000") for pod in pods],
                      ProxyOptions(bind=":8000", stats="127.0.0.1:8404", resolve=True))
    assert proxy["ConfigMap"]["data"]["haproxy.cfg"] == expected
    assert all(Settings(replica_id=pod).replica_id == pod for pod in pods)


def test_compose_scales_replicas_behind_haproxy():
    compose = yaml.safe_load((ROOT / "docker/compose.scale.yaml").read_text())
    assert set(compose["services"]) == {"replica", "haproxy"} and "ports" not in compose["services"]["replica"]
    assert compose["services"]["haproxy"]["volumes"] == ["./haproxy.scale.cfg:/usr/local/etc/haproxy/haproxy.cfg:ro"]
    config = (ROOT / "docker/haproxy.scale.cfg").read_text()
    assert f"option httpchk GET {READY_PATH}" in config and "stick store-response res.hdr(X-Replica)" in config
    assert "server-template replica 1-16 replica:8000" in config


@pytest.mark.skipif(shutil.which("haproxy") is None, reason="haproxy is not installed (make haproxy)")
def test_haproxy_accepts_the_compose_configuration():
    checked = subprocess.run(["haproxy", "-c", "-f", str(ROOT / "docker/haproxy.scale.cfg")], capture_output=True,
                             text=True, timeout=30)
    assert checked.returncode == 0, checked.stdout + checked.stderr
