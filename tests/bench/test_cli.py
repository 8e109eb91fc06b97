"""`python -m bench` as a user runs it: exit status and what it prints."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path


def _bench(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "bench", "--threads", "1", *args], capture_output=True, text=True,
                          timeout=300, check=False, cwd=Path(__file__).resolve().parents[2])


def test_stability_prints_the_matrix() -> None:
    done = _bench("stability", "--pipelines", "bilateral", "--cases", "black,size_2x2", "--size", "8x6")
    assert done.returncode == 0, done.stderr
    assert "bilateral" in done.stdout and "size_2x2" in done.stdout and "0 failure(s)" in done.stdout


def test_run_writes_the_report(tiny_sequence_dir: Path, tmp_path: Path) -> None:
    done = _bench("run", "--sequences", str(tiny_sequence_dir), "--pipelines", "bilateral", "bilateral:radius=1",
                  "--anchors", "noisy", "--no-flip", "--out", str(tmp_path / "r"))
    assert done.returncode == 0, done.stderr
    assert {p.name for p in (tmp_path / "r").iterdir()} == {"results.json", "report.md", "pareto.png", "report.html",
                                                           f"curves-{tiny_sequence_dir.name}.png"}
    assert "| bilateral |" in done.stdout and "| bilateral:radius=1 |" in done.stdout


def test_bad_size_is_a_usage_error() -> None:
    done = _bench("stability", "--size", "big")
    assert done.returncode == 2 and "is not WxH" in done.stderr


def test_cold_start_times_a_first_frame_on_an_empty_cache(tiny_sequence_dir: Path) -> None:
    done = subprocess.run([sys.executable, "-m", "bench.cold_start", "--pipelines", "bilateral", "--sample",
                           str(tiny_sequence_dir), "--kernels", "2"], capture_output=True, text=True, timeout=300,
                          check=False, cwd=Path(__file__).resolve().parents[2])  # fmt: skip
    assert done.returncode == 0, done.stderr
    lines = done.stdout.splitlines()
    assert lines[0].startswith("cpus: ") and lines[1].startswith("bilateral: first frame ")
    assert "s  service.stages." in lines[2]  # a kernel compiled: the cache was empty
