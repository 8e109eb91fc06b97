"""Thread settings and the machine/version record every benchmark result carries.

`configure_threads` must run before numpy, numba, ONNX Runtime or OIDN are imported: each reads its
thread count from the environment once, when it loads. The benchmark CLI calls it first, so every
pipeline and every anchor in one run works under the same settings, and `describe` records them.
"""

from __future__ import annotations

import os
import platform
import subprocess
import sys
from importlib import metadata
from typing import Any

# Environment variables that fix the worker-thread count of each numeric library we load.
THREAD_VARIABLES = (
    "OMP_NUM_THREADS",  # OpenMP (ONNX Runtime's MLAS on some builds, numpy's BLAS)
    "MKL_NUM_THREADS",
    "OPENBLAS_NUM_THREADS",
    "NUMBA_NUM_THREADS",  # numba parallel loops
    "OIDN_NUM_THREADS",  # Open Image Denoise CPU device; overrides its numThreads parameter
    "MCDENOISE_ORT_THREADS",  # ONNX Runtime intra-op threads of every session (service/runtime.py)
)
# Distributions whose versions a result records.
PACKAGES = ("numpy", "onnxruntime", "pyoidn", "numba", "OpenEXR", "flip-evaluator", "matplotlib", "mcdenoise")


def configure_threads(threads: int | None) -> int:
    """Set every thread variable to `threads` (default: the CPUs this process may use).

    Variables already set in the environment are overwritten, so one run has one setting. Returns the
    thread count used.
    """
    count = threads or len(os.sched_getaffinity(0))
    if count < 1:
        raise ValueError(f"threads must be >= 1, got {count}")
    for name in THREAD_VARIABLES:
        os.environ[name] = str(count)
    return count


def cpu_model() -> str:
    """CPU model name from /proc/cpuinfo (Linux), else what `platform` knows."""
    try:
        with open("/proc/cpuinfo") as handle:
            for line in handle:
                if line.lower().startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def versions() -> dict[str, str | None]:
    """Installed versions of Python and the packages that decide speed and error."""
    found: dict[str, str | None] = {"python": sys.version.split()[0]}
    for name in PACKAGES:
        try:
            found[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            found[name] = None
    try:
        from pyoidn import version as oidn_version

        found["oidn"] = oidn_version.oidn_version
    except ImportError:
        found["oidn"] = None
    return found


def git_revision() -> str | None:
    """Commit of the checkout this code runs from, with '+dirty' when files differ; None outside git."""
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    try:
        head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=root, capture_output=True, text=True,
                              timeout=10, check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=root,
                               capture_output=True, text=True, timeout=30, check=True).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return None
    return head + ("+dirty" if dirty else "")


def describe() -> dict[str, Any]:
    """Machine, thread settings and versions, as stored in results.json."""
    threads: dict[str, Any] = {name: os.environ.get(name) for name in THREAD_VARIABLES}
    try:
        import numba

        threads["numba (effective)"] = numba.config.NUMBA_NUM_THREADS
    except ImportError:
        pass
    return {
        "machine": {
            "cpu": cpu_model(),
            "logical_cpus": os.cpu_count(),
            "usable_cpus": len(os.sched_getaffinity(0)),
            "platform": platform.platform(),
            "load_average_1m": os.getloadavg()[0],
        },
        "threads": threads,
        "versions": versions(),
        "git": git_revision(),
    }
