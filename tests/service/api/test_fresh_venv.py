"""What the Docker image does, without a Docker engine: install the package with only its serving
dependencies into a fresh virtual environment (no torch, no dev tools), start the server from it outside
the source tree, and denoise a frame through it."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

from service.exr import read_frame
from tests.service.api.conftest import ROOT, call, exr_post, start_subprocess_server, stop

# What docker/Dockerfile.dockerignore lets into the image before `pip install .`.
IMAGE_SOURCES = ("pyproject.toml", "README.md", "service", "models")
IMAGE_EXCLUDED = ROOT / "models" / "data" / "samples"
INSTALL_TIMEOUT_S = 540


def copy_sources(dest: Path) -> None:
    def ignore(folder: str, names: list[str]) -> set[str]:
        skip = {n for n in names if n == "__pycache__" or n.endswith((".pyc", ".egg-info"))}
        return skip | {n for n in names if Path(folder, n) == IMAGE_EXCLUDED}

    for name in IMAGE_SOURCES:
        src = ROOT / name
        if src.is_dir():
            shutil.copytree(src, dest / name, ignore=ignore)
        elif src.is_file():
            shutil.copy2(src, dest / name)


# 35 s on a quiet 2-core machine, 100 s on a busy one (mostly pip unpacking wheels): slow, not in `make test`.
@pytest.mark.slow
@pytest.mark.timeout(INSTALL_TIMEOUT_S + 120)
def test_serving_install_in_a_fresh_venv_starts_and_denoises(tmp_path, sequence_exr):
    started = time.monotonic()
    src, venv = tmp_path / "src", tmp_path / "venv"
    src.mkdir()
    copy_sources(src)
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True, timeout=120)
    python = str(venv / "bin" / "python")
    install = subprocess.run([python, "-m", "pip", "install", "-q", "--disable-pip-version-check", str(src)],
                             capture_output=True, text=True, timeout=INSTALL_TIMEOUT_S, check=False)
    assert install.returncode == 0, install.stderr[-3000:]
    installed = subprocess.run([python, "-m", "pip", "list", "--format=freeze"], capture_output=True, text=True,
                               check=True).stdout.lower()
    for absent in ("torch==", "mitsuba==", "pytest==", "httpx=="):
        assert absent not in installed
    site = Path(subprocess.run([python, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                               capture_output=True, text=True, check=True).stdout.strip())
    for weights in (ROOT / "models" / "weights").glob("**/*.onnx"):  # the shipped weights are inside
        assert (site / weights.relative_to(ROOT)).is_file(), weights
    env = {k: v for k, v in os.environ.items() if not k.startswith(("MCDENOISE_", "PYTHONPATH", "VIRTUAL_ENV"))}
    run_dir = tmp_path / "run"  # outside the source tree: `service` must come from the installed package
    run_dir.mkdir()
    where = subprocess.run([python, "-c", "import service; print(service.__file__)"], cwd=run_dir, env=env,
                           capture_output=True, text=True, check=True).stdout
    assert str(venv) in where
    url, proc = start_subprocess_server(python, env, tmp_path / "server.log", cwd=run_dir)
    try:
        assert call(url, "GET", "/readyz").json()["ready"] is True
        answer = exr_post(url, "/v1/denoise", sequence_exr[0])
        assert answer.status == 200 and read_frame(answer.body)["color"].shape == (32, 48, 3)
    finally:
        stop(proc)
    print(f"fresh serving venv: install + start + one frame in {time.monotonic() - started:.1f} s")


def test_docker_files_install_what_the_fresh_venv_test_installs():
    dockerfile = (ROOT / "docker" / "Dockerfile").read_text()
    for needed in ("USER mcdenoise", "HEALTHCHECK", "/healthz", "pip install .", 'WITH_TORCH" = "1"', '".[train]"'):
        assert needed in dockerfile
    # every pipeline's kernels compiled at build time, for one CPU class that the image's runtime names too
    assert "python -m service warm" in dockerfile and dockerfile.count("NUMBA_CPU_NAME=${NUMBA_CPU_NAME}") == 2
    allowed = [line[1:].rstrip("/") for line in (ROOT / "docker" / "Dockerfile.dockerignore").read_text().splitlines()
               if line.startswith("!")]
    assert allowed == list(IMAGE_SOURCES)
    assert f"{IMAGE_EXCLUDED.relative_to(ROOT)}/" in (ROOT / "docker" / "Dockerfile.dockerignore").read_text()
    compose = (ROOT / "docker" / "compose.yaml").read_text()
    for needed in ("dockerfile: docker/Dockerfile", "context: ..", "healthcheck:", '"127.0.0.1:${MCDENOISE_PORT'):
        assert needed in compose
