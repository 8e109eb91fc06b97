"""Run the renderer in a child process, so that a native abort fails one test instead of the suite.

Mitsuba and Dr.Jit abort the whole process when their JIT backend fails in native code (for example
"LLVM ERROR: Cannot select ... fminimum" from an LLVM older than 19). Tests that render therefore call
`run_isolated(func, *args)`: `func` (a module-level function, pickled by name) runs in a fresh
interpreter with this process's environment, and its return value comes back pickled. When the child
dies, `run_isolated` fails the calling test (or fixture) with the signal or exit status, the Mitsuba
environment and the tail of the child's stderr.
"""

from __future__ import annotations

import os
import pickle
import subprocess
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from models.data.variant import VARIANT_ENV, exit_description

ROOT = Path(__file__).resolve().parents[3]
STDERR_TAIL_LINES = 15

CHILD = """
import faulthandler, pickle, sys
faulthandler.enable()
with open(sys.argv[1], "rb") as f:
    func, args = pickle.load(f)
result = func(*args)
with open(sys.argv[2], "wb") as f:
    pickle.dump(result, f)
"""


class RenderCrashed(AssertionError):
    """A child process that rendered died or raised; the message says how."""


def crash_message(what: str, returncode: int, stderr: str) -> str:
    """'<what> was killed by SIGABRT (...environment...)', the first LLVM ERROR line and stderr's tail."""
    env = ", ".join(f"{k}={os.environ.get(k, '(unset)')}" for k in (VARIANT_ENV, "DRJIT_LIBLLVM_PATH"))
    lines = stderr.splitlines()
    llvm = [line for line in lines if line.startswith("LLVM ERROR")][:1]
    tail = [line for line in lines if line.strip() and not line.startswith("Extension modules:")][-STDERR_TAIL_LINES:]
    return "\n".join([f"{what} {exit_description(returncode)} ({env})", *llvm,
                      "--- last lines of its stderr ---", *tail])


def run_isolated(func: Callable[..., Any], *args: Any, timeout: float = 600.0) -> Any:
    """func(*args) in a child interpreter; fails the test with a clear message when the child dies."""
    name = f"{func.__module__}.{func.__qualname__}"
    with tempfile.TemporaryDirectory(prefix="isolated-") as tmp:
        call, result = Path(tmp) / "call.pkl", Path(tmp) / "result.pkl"
        call.write_bytes(pickle.dumps((func, args)))
        try:
            run = subprocess.run([sys.executable, "-c", CHILD, str(call), str(result)], cwd=ROOT,
                                 capture_output=True, text=True, timeout=timeout, check=False)
        except subprocess.TimeoutExpired:
            raise RenderCrashed(f"render subprocess {name} did not finish in {timeout:.0f} s") from None
        if run.returncode != 0 or not result.is_file():
            raise RenderCrashed(crash_message(f"render subprocess {name}", run.returncode, run.stderr))
        return pickle.loads(result.read_bytes())


def render_or_fail(func: Callable[..., Any], *args: Any, timeout: float = 600.0) -> Any:
    """run_isolated for fixtures and tests: a crash becomes pytest.fail (one failed test or errored fixture)."""
    try:
        return run_isolated(func, *args, timeout=timeout)
    except RenderCrashed as crash:
        message = str(crash)
    pytest.fail(message, pytrace=False)
