"""HAProxy's configuration for N replicas: a pure function of the replicas' ids and addresses.

Routing (docs/cluster.md): a session id is `<replica>.<instance>.<token>` (service/api/sessions.py), so a
request under `/v1/sessions/<id>` goes to the server named `<replica>`, by a `use-server` rule per
replica; nothing depends on a stick table, which a reload would empty. Everything else (session
creation, `/v1/denoise`, `/v1/pipelines`) goes to the replica with the fewest connections. A replica
whose `/readyz` fails `fall` times in a row (dead, warming up or stopping) takes no new work; the
requests of its sessions then reach another replica, which answers `410 session_lost`. A request that
cannot connect (a dead replica refuses at once) is retried on another replica at once (`option
redispatch`), never left waiting. Connections a replica still serves are not cut when it is marked down:
a stopping replica finishes its frames.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from service.api.core.config import REPLICA_ID

READY_PATH = "/readyz"  # health check: 200 ready, 503 starting, warming up or stopping (routes/health.py)
SESSIONS_PATH = "/v1/sessions/"  # prefix of every route of one session (routes/sessions.py, routes/stream.py)


@dataclass(frozen=True)
class Replica:
    name: str  # replica id (MCDENOISE_REPLICA_ID), also the HAProxy server name
    address: str  # host:port it serves on (a DNS name with `ProxyOptions.resolve`)

    def __post_init__(self) -> None:
        if not REPLICA_ID.fullmatch(self.name):
            raise ValueError(f"replica id {self.name!r} is not a valid MCDENOISE_REPLICA_ID")
        host, _, port = self.address.rpartition(":")
        if not host or not port.isdigit() or not 0 < int(port) < 65536:
            raise ValueError(f"replica address must be host:port, got {self.address!r}")


@dataclass(frozen=True)
class ProxyOptions:
    bind: str = "127.0.0.1:8000"  # address:port HAProxy serves clients on
    stats: str | None = None  # address:port of HAProxy's stats page (/stats); None: no stats page
    check_interval_ms: int = 1000  # /readyz of each replica every this, milliseconds
    check_timeout_ms: int = 2000  # a check answered later than this fails, milliseconds
    fall: int = 3  # failed checks in a row before a replica is out: a busy replica answers a check late, and
    # marking a live one down would answer its sessions `session_lost`; a dead one refuses connections, and
    # those requests are redispatched at once anyway
    rise: int = 2  # passed checks in a row before it takes work again
    server_timeout_s: int = 150  # longest answer of a replica, s: above MCDENOISE_FRAME_TIMEOUT_S
    tunnel_timeout_s: int = 3600  # an idle WebSocket stream is closed after this, seconds
    resolve: bool = False  # replica addresses are DNS names, resolved at run time (/etc/resolv.conf)

    def __post_init__(self) -> None:
        for name in ("check_interval_ms", "check_timeout_ms", "fall", "rise", "server_timeout_s", "tunnel_timeout_s"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be at least 1, got {getattr(self, name)}")


# HAProxy's own answers (no replica reached), in the service's error format: {code, message}.
_ERRORS = (
    (502, "replica_failed", "the replica serving this request failed before it answered; retry"),
    (503, "no_replica", "no replica is ready to take this request; retry shortly"),
    (504, "replica_timeout", "the replica did not answer in time"),
)


def render(replicas: Sequence[Replica], options: ProxyOptions) -> str:
    """haproxy.cfg text for `replicas` (at least one, distinct names) behind `options.bind`."""
    if not replicas:
        raise ValueError("at least one replica is needed")
    names = [r.name for r in replicas]
    if len(set(names)) != len(names):
        raise ValueError(f"replica ids must be distinct, got {names}")
    server_flags = "check" + (" resolvers system init-addr none" if options.resolve else "")
    lines = [
        "# Written by service/cluster/haproxy.py; docs/cluster.md explains it.",
        "global",
        "    maxconn 4096",
        "",
        *(["resolvers system", "    parse-resolv-conf", "    hold valid 10s", ""] if options.resolve else []),
        "defaults",
        "    mode http",
        "    timeout connect 2s",
        "    timeout client 75s",
        f"    timeout server {options.server_timeout_s}s",
        f"    timeout tunnel {options.tunnel_timeout_s}s",
        "    timeout http-request 75s",
        f"    timeout check {options.check_timeout_ms}ms",
        "    retries 2",
        "    option redispatch 1",
        *(f"    http-error status {status} content-type application/json "
          f"string '{{\"code\": \"{code}\", \"message\": \"{message}\"}}'"
          + (" hdr Retry-After 1" if status == 503 else "") for status, code, message in _ERRORS),
        "",
        "frontend mcdenoise",
        f"    bind {options.bind}",
        "    default_backend replicas",
        "",
        "backend replicas",
        "    balance leastconn",
        f"    option httpchk GET {READY_PATH}",
        "    http-check expect status 200",
        f"    default-server inter {options.check_interval_ms}ms fall {options.fall} rise {options.rise}",
        f"    http-request set-var(txn.replica) path,field(4,/),field(1,.) if {{ path_beg {SESSIONS_PATH} }}",
        *(f"    use-server {r.name} if {{ var(txn.replica) -m str {r.name} }}" for r in replicas),
        *(f"    server {r.name} {r.address} {server_flags}" for r in replicas),
    ]
    if options.stats:
        lines += ["", "frontend stats", f"    bind {options.stats}", "    stats enable", "    stats uri /stats",
                  "    stats refresh 5s"]
    return "\n".join(lines) + "\n"
