"""The Python client and `python -m service stream` against the served process."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from service.client import Client, ServiceError
from service.exr import read_frame
from tests.service.api.conftest import HEIGHT, ROOT, WIDTH

pytestmark = pytest.mark.timeout(120)


def test_client_denoises_one_frame_and_reports_errors(server, sequence_dir, cli_outputs):
    with Client(server) as client:
        assert "bilateral" in [p["name"] for p in client.pipelines()]
        out = client.denoise(sequence_dir / "frame_0002.exr", pipeline="bilateral")
        np.testing.assert_array_equal(read_frame(out)["color"], cli_outputs[2])
        assert client.denoise(sequence_dir / "frame_0002.exr", png=True, exposure=2.0).startswith(b"\x89PNG")
        with pytest.raises(ServiceError) as caught:
            client.denoise(b"nonsense" * 40)
        assert (caught.value.status, caught.value.code) == (400, "invalid_exr")


def test_session_streams_a_folder_and_writes_the_results(server, sequence_dir, cli_outputs, tmp_path):
    with Client(server) as client, client.session("bilateral", WIDTH, HEIGHT) as session:
        results = session.stream_folder(sequence_dir, tmp_path / "out", window=3)
        assert [r.error for r in results] == [None] * 10
        assert session.status()["frames"] == 10
    outputs = sorted((tmp_path / "out").glob("*.exr"))
    assert [p.name for p in outputs] == [f"frame_{t:04d}.exr" for t in range(10)]
    for path, expected in zip(outputs, cli_outputs, strict=True):
        np.testing.assert_array_equal(read_frame(path)["color"], expected)


def test_stream_command_equals_the_denoise_command(server, sequence_dir, cli_outputs, tmp_path):
    out = tmp_path / "streamed"
    run = subprocess.run([sys.executable, "-m", "service", "stream", "--pipeline", "bilateral", str(sequence_dir),
                          str(out), "--url", server], capture_output=True, text=True, cwd=ROOT, timeout=90, check=False)
    assert run.returncode == 0, run.stderr
    assert run.stdout.splitlines()[0].split() == ["frame_0000.exr", "ok"]
    assert "bilateral: 10/10 frames" in run.stdout
    for t, expected in enumerate(cli_outputs):
        np.testing.assert_array_equal(read_frame(out / f"frame_{t:04d}.exr")["color"], expected)


def test_stream_command_reports_a_refused_session(server, sequence_dir, tmp_path):
    run = subprocess.run([sys.executable, "-m", "service", "stream", "--pipeline", "nope", str(sequence_dir),
                          str(tmp_path / "o"), "--url", server], capture_output=True, text=True, cwd=ROOT,
                         timeout=90, check=False)
    assert run.returncode == 2
    assert run.stderr.startswith("error: 400 unknown_pipeline: unknown pipeline 'nope'")
