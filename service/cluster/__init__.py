"""Scale-out: N replicas of `python -m service serve` behind HAProxy (docs/cluster.md). `haproxy.py` writes
HAProxy's configuration, `replicas.py` starts and stops the local processes; `python -m service cluster`
(service/cli/cluster.py) runs both."""
