"""Fuzzing the served API (issue 22): schemathesis on /openapi.json with a bounded example count, and a seeded
mutation fuzzer of EXR frames on the two EXR routes. Every answer must come (no hang) and be below 500.

Both run against their own `python -m service serve` subprocess, so what they leave behind (sessions,
busy slots) touches no other test. Budget: about 60 s together on 2 cores.
"""

from __future__ import annotations

import io
import json
import os
import sys
from collections.abc import Iterator

import numpy as np
import OpenEXR
import pytest
import schemathesis
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis.errors import Unsatisfiable
from schemathesis import GenerationMode

from service import pipelines
from service.exr import encode_frame
from tests.service.api.conftest import HEIGHT, SERVER_ENV, WIDTH, call, exr_post, start_subprocess_server, stop

pytestmark = pytest.mark.timeout(300)
SCHEMA_EXAMPLES = 50  # per operation and generation mode (9 operations)
EXR_CASES = 600
SEED = 22
# Generated EXR bodies are random bytes (the schema says `format: binary`); the mutation fuzzer below sends
# frames that get past the header.
schemathesis.serializer.alias("image/x-exr", "application/octet-stream")


@pytest.fixture(scope="module")
def fuzz_server(tmp_path_factory) -> Iterator[str]:
    env = {**os.environ, **SERVER_ENV, "PYTHONPATH": str(os.getcwd()), "MCDENOISE_MAX_SESSIONS": "64",
           "MCDENOISE_FRAME_TIMEOUT_S": "30"}
    env.pop("MCDENOISE_API_KEY", None)
    url, proc = start_subprocess_server(sys.executable, env, tmp_path_factory.mktemp("fuzz") / "server.log")
    yield url
    stop(proc)


@pytest.mark.parametrize("mode", [GenerationMode.POSITIVE, GenerationMode.NEGATIVE])
def test_no_generated_request_answers_5xx(fuzz_server, mode):
    """Every operation of the served schema, SCHEMA_EXAMPLES generated requests each (schemathesis strategies
    driven by hypothesis; the schemathesis pytest plugin does not load under pytest 9)."""
    schema = schemathesis.openapi.from_url(f"{fuzz_server}/openapi.json")
    operations = [result.ok() for result in schema.get_all_operations()]
    assert len(operations) >= 8
    for operation in operations:

        @given(case=operation.as_strategy(generation_mode=mode))
        @settings(max_examples=SCHEMA_EXAMPLES, deadline=None, derandomize=True, database=None,
                  suppress_health_check=list(HealthCheck), phases=[Phase.generate])
        def check(case):
            response = case.call(timeout=60)
            assert response.status_code < 500, (case.method, case.path, response.status_code, response.text[:300])

        try:
            check()
        except Unsatisfiable:  # negative mode, and nothing to make invalid (no parameter, no body)
            assert mode == GenerationMode.NEGATIVE, operation.label


def _channels(layers: dict[str, np.ndarray], rng: np.random.Generator) -> dict[str, np.ndarray]:
    """Layer dict -> EXR channel dict, with random damage: a channel dropped or added, junk layers, half or
    uint pixels, extreme values."""
    channels = {}
    for name, value in layers.items():
        spec = "RGB" if value.shape[2] == 3 else ("XY" if value.shape[2] == 2 else "Y")
        for c, chan in enumerate(spec):
            channels[f"{name}.{chan}"] = np.ascontiguousarray(value[:, :, c], np.float32)
    kind = rng.integers(6)
    names = sorted(channels)
    if kind == 0:  # drop a channel: a layer with a wrong channel count
        channels.pop(names[rng.integers(len(names))])
    elif kind == 1:  # extreme values in one channel
        target = names[rng.integers(len(names))]
        value = rng.choice([3e38, -3e38, 1e30, np.inf, -np.inf, np.nan, 65504.0, 1e-45, 0.0])
        mask = rng.random(channels[target].shape) < rng.choice([0.001, 0.1, 1.0])
        channels[target] = np.where(mask, np.float32(value), channels[target]).astype(np.float32)
    elif kind == 2:  # junk layers
        for i in range(int(rng.integers(1, 40))):
            channels[f"junk{i}.Y"] = rng.random(channels[names[0]].shape, dtype=np.float32)
    elif kind == 3:  # half or uint pixels
        target = names[rng.integers(len(names))]
        channels[target] = channels[target].astype(rng.choice([np.float16, np.uint32]))
    elif kind == 4:  # an extra channel in a known layer
        channels[f"{names[0].split('.')[0]}.W"] = channels[names[0]].copy()
    return channels


def _encode(channels: dict[str, np.ndarray]) -> bytes:
    sink = io.BytesIO()
    with OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}, channels) as exr:
        exr.write(sink)
    return sink.getvalue()


def _mutate(body: bytes, rng: np.random.Generator) -> bytes:
    """Byte-level damage: flipped bytes (anywhere or in the header), truncation, a spliced copy, a data window
    that claims another size."""
    data = bytearray(body)
    kind = rng.integers(5)
    if kind == 0:
        for _ in range(int(rng.integers(1, 9))):
            data[rng.integers(len(data))] ^= 1 << int(rng.integers(8))
    elif kind == 1:
        for _ in range(int(rng.integers(1, 4))):
            data[rng.integers(min(len(data), 400))] = int(rng.integers(256))
    elif kind == 2:
        data = data[: rng.integers(1, len(data))]
    elif kind == 3:
        start = int(rng.integers(len(data)))
        data[start:start] = data[rng.integers(len(data)):][: rng.integers(1, 200)]
    else:
        at = data.find(b"dataWindow")
        if at >= 0:
            offset = at + len(b"dataWindow\0box2i\0") + 4 + 4 * int(rng.integers(4))
            value = int(rng.choice([-(2**31), -1, 0, 1, 63, 64, 65, 4096, 2**20, 2**31 - 1]))
            data[offset:offset + 4] = value.to_bytes(4, "little", signed=True)
    return bytes(data)


def test_mutated_exr_frames_never_answer_5xx_nor_hang(fuzz_server, sequence_layers):
    rng = np.random.default_rng(SEED)
    names = pipelines.names()
    sessions = {}
    for name in names:
        answer = call(fuzz_server, "POST", "/v1/sessions", json.dumps(
            {"pipeline": name, "width": WIDTH, "height": HEIGHT}).encode(), {"Content-Type": "application/json"})
        assert answer.status == 201, answer.body
        sessions[name] = f"/v1/sessions/{answer.json()['id']}/frames"
    statuses: dict[int, int] = {}
    for i in range(EXR_CASES):
        layers = sequence_layers[int(rng.integers(len(sequence_layers)))]
        body = _encode(_channels(layers, rng)) if rng.random() < 0.5 else encode_frame(layers)
        if rng.random() < 0.6:
            body = _mutate(body, rng)
        name = names[int(rng.integers(len(names)))]
        path = sessions[name] if i % 2 else f"/v1/denoise?pipeline={name}"
        answer = exr_post(fuzz_server, path, body, timeout=60)  # raises on a hang
        assert answer.status < 500, (i, name, path, answer.status, answer.body[:300])
        statuses[answer.status] = statuses.get(answer.status, 0) + 1
    assert statuses.get(200, 0) > EXR_CASES // 5 and statuses.get(400, 0) > 0 and statuses.get(422, 0) > 0, statuses
    for path in sessions.values():  # every session survived its bad frames
        assert call(fuzz_server, "GET", path.removesuffix("/frames")).status == 200
