"""HAProxy's configuration (service/cluster/haproxy.py): routing rules per replica, checks, refusals, and
HAProxy's own verdict on it where HAProxy is installed."""

from __future__ import annotations

import shutil
import subprocess

import pytest

from service.cluster.haproxy import ProxyOptions, Replica, render

REPLICAS = [Replica("r0", "127.0.0.1:9001"), Replica("r1", "127.0.0.1:9002")]


def test_sessions_go_to_their_named_replica_and_the_rest_to_the_least_loaded():
    lines = render(REPLICAS, ProxyOptions(bind="0.0.0.0:8000")).splitlines()
    assert "    bind 0.0.0.0:8000" in lines and "    balance leastconn" in lines
    assert "    http-request set-var(txn.replica) path,field(4,/),field(1,.) if { path_beg /v1/sessions/ }" in lines
    assert [line for line in lines if "use-server" in line] == [
        "    use-server r0 if { var(txn.replica) -m str r0 }", "    use-server r1 if { var(txn.replica) -m str r1 }"]
    assert [line for line in lines if line.startswith("    server ")] == [
        "    server r0 127.0.0.1:9001 check", "    server r1 127.0.0.1:9002 check"]
    assert "    option httpchk GET /readyz" in lines and "    option redispatch 1" in lines
    assert "    default-server inter 1000ms fall 3 rise 2" in lines and "    timeout check 2000ms" in lines
    assert not any("stats" in line or "resolvers" in line for line in lines)


def test_stats_page_and_run_time_name_resolution():
    text = render(REPLICAS, ProxyOptions(stats="127.0.0.1:8404", resolve=True))
    assert "frontend stats\n    bind 127.0.0.1:8404\n    stats enable\n    stats uri /stats\n" in text
    assert "resolvers system\n    parse-resolv-conf\n" in text
    assert "    server r1 127.0.0.1:9002 check resolvers system init-addr none\n" in text


@pytest.mark.parametrize(("make", "message"), [
    (lambda: render([], ProxyOptions()), "at least one replica is needed"),
    (lambda: render([REPLICAS[0], REPLICAS[0]], ProxyOptions()), "replica ids must be distinct, got ['r0', 'r0']"),
    (lambda: Replica("r.0", "127.0.0.1:1"), "replica id 'r.0' is not a valid MCDENOISE_REPLICA_ID"),
    (lambda: Replica("r0", "127.0.0.1"), "replica address must be host:port, got '127.0.0.1'"),
    (lambda: Replica("r0", "h:70000"), "replica address must be host:port, got 'h:70000'"),
    (lambda: ProxyOptions(fall=0), "fall must be at least 1, got 0"),
])
def test_bad_replicas_and_options_are_refused(make, message):
    with pytest.raises(ValueError) as caught:
        make()
    assert str(caught.value) == message


@pytest.mark.skipif(shutil.which("haproxy") is None, reason="haproxy is not installed (make haproxy)")
@pytest.mark.parametrize("options", [ProxyOptions(stats="127.0.0.1:8404"), ProxyOptions(resolve=True)])
def test_haproxy_accepts_the_configuration(tmp_path, options):
    path = tmp_path / "haproxy.cfg"
    path.write_text(render(REPLICAS, options))
    checked = subprocess.run(["haproxy", "-c", "-f", str(path)], capture_output=True, text=True, timeout=30)
    assert checked.returncode == 0, checked.stdout + checked.stderr
