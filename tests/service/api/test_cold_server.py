"""A server whose kernels are not in the cache compiles them inside a request: the thread limit the
server sets (`service.cli.serve.limit_threads`) must agree with numba's configuration, which numba reads
again at every compile and may not change once its threads run (a 500 RuntimeError before)."""

from __future__ import annotations

import os
import sys

from service.client import Client
from tests.service.api.conftest import ROOT, SERVER_ENV, start_subprocess_server, stop


def test_a_server_on_an_empty_kernel_cache_compiles_inside_its_requests(tmp_path, sequence_exr):
    env = {**os.environ, **SERVER_ENV, "PYTHONPATH": str(ROOT), "NUMBA_CACHE_DIR": str(tmp_path / "numba"),
           "MCDENOISE_WARMUP": "", "MCDENOISE_FRAME_TIMEOUT_S": "290"}  # the first frame compiles every kernel:
    # 2 cores took about 120 s (a 504 at the default deadline in one CI run), below the client's 300
    env.pop("MCDENOISE_API_KEY", None)
    env.pop("NUMBA_NUM_THREADS", None)
    url, proc = start_subprocess_server(sys.executable, env, tmp_path / "server.log")
    try:
        with Client(url, timeout=300) as client:
            for data in sequence_exr[:2]:  # rae: the fewest kernels (its guards'), the network in ONNX Runtime
                assert client.denoise(data, "rae")[:4] == b"\x76\x2f\x31\x01"  # an EXR file
    finally:
        stop(proc)
    assert "RuntimeError" not in (tmp_path / "server.log").read_text()
