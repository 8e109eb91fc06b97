"""Which Mitsuba 3 variant renders here: the one place that chooses it and imports mitsuba.

Order of preference: `cuda_ad_rgb` when a CUDA GPU is present, `llvm_ad_rgb` when Dr.Jit loads an LLVM
that can compile Mitsuba's kernels, else `scalar_rgb` (no JIT, about half the speed of LLVM on simple
scenes, much slower for the Python AO integrator). The environment variable MCDENOISE_MI_VARIANT forces
a variant and skips every check.

The llvm variant needs LLVM >= 19 (`apt-get install -y libllvm19`). Dr.Jit itself accepts LLVM 15 and
up, so on Debian 12 or Ubuntu 22.04 (LLVM 14 and 15 only) it loads LLVM 15, and the first render aborts
the whole process in native code: "LLVM ERROR: Cannot select: ... fminimum". `choose_variant` therefore
asks Dr.Jit which LLVM it loaded and takes the llvm variant only for LLVM >= MIN_LLVM; when Dr.Jit cannot
say, it renders a tiny probe in a subprocess (an abort then kills only the probe). Falling back, it logs
one warning line that says why.

Dr.Jit reads DRJIT_LIBLLVM_PATH once, when it is first imported, so `choose_variant` sets it (when unset
and LLVM 19 is installed at a known path) before importing anything.
"""

from __future__ import annotations

import functools
import logging
import os
import signal
import subprocess
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType

from models.data.integrators import register

log = logging.getLogger(__name__)

# Where Debian's libllvm19 package puts the library (issue 7: the llvm variant needs LLVM >= 19 here).
LLVM_CANDIDATES = (
    "/usr/lib/x86_64-linux-gnu/libLLVM-19.so",
    "/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1",
    "/usr/lib/aarch64-linux-gnu/libLLVM-19.so",
)
MIN_LLVM = 19  # oldest LLVM major version that compiles Mitsuba's llvm kernels (15 aborts, see above)
PREFERENCE = ("cuda_ad_rgb", "llvm_ad_rgb", "scalar_rgb")
VARIANT_ENV = "MCDENOISE_MI_VARIANT"  # forces a variant, e.g. scalar_rgb in a test
PROBE_TIMEOUT_S = 300.0

# One path-traced 8x8 frame of the Cornell box: enough to make an unusable LLVM abort.
PROBE_CODE = """
import sys
import mitsuba as mi
mi.set_variant(sys.argv[1])
scene = mi.cornell_box()
scene["sensor"]["film"].update(width=8, height=8)
image = mi.TensorXf(mi.render(mi.load_dict(scene), spp=1))
assert image.shape == (8, 8, 3), image.shape
print("probe ok")
"""


@dataclass(frozen=True)
class ProbeResult:
    """How a probe render in a subprocess ended."""

    ok: bool
    detail: str  # empty when ok; else the exit status or signal and the last line of stderr


def probe_variant(variant: str, timeout: float = PROBE_TIMEOUT_S) -> ProbeResult:
    """Render PROBE_CODE with `variant` in a subprocess of this interpreter, in this environment."""
    try:
        run = subprocess.run([sys.executable, "-c", PROBE_CODE, variant], capture_output=True, text=True,
                             timeout=timeout, check=False)
    except subprocess.TimeoutExpired:
        return ProbeResult(False, f"the probe render did not finish in {timeout:.0f} s")
    if run.returncode == 0 and "probe ok" in run.stdout:
        return ProbeResult(True, "")
    return ProbeResult(False, f"the probe render {exit_description(run.returncode)}: {last_line(run.stderr)}")


def exit_description(returncode: int) -> str:
    """'was killed by SIGABRT' for a negative return code (a signal), else 'exited with status N'."""
    if returncode < 0:
        try:
            name = signal.Signals(-returncode).name
        except ValueError:
            name = f"signal {-returncode}"
        return f"was killed by {name}"
    return f"exited with status {returncode}"


def last_line(text: str) -> str:
    """The first 'LLVM ERROR' line of `text`, else its last non-empty line (or '(no output)')."""
    lines = [line.strip() for line in text.splitlines() if line.strip()]
    llvm = [line for line in lines if line.startswith("LLVM ERROR")]
    line = (llvm or lines or ["(no output)"])[0 if llvm else -1]
    return line if len(line) <= 200 else line[:197] + "..."


def decide(available: set[str], has_cuda: bool, has_llvm: bool, llvm: tuple[int, int, int] | None,
           probe: Callable[[str], ProbeResult]) -> tuple[str, str]:
    """(variant, why the preferred one was not taken or '') from what Dr.Jit reports.

    `llvm` is the version of the LLVM library Dr.Jit loaded, None when it cannot say; `probe` is called
    only then (see probe_variant).
    """
    if "cuda_ad_rgb" in available and has_cuda:
        return "cuda_ad_rgb", ""
    if "llvm_ad_rgb" not in available:
        return "scalar_rgb", ""
    if not has_llvm:
        return "scalar_rgb", "Dr.Jit found no usable LLVM library"
    if llvm is not None:
        if llvm[0] >= MIN_LLVM:
            return "llvm_ad_rgb", ""
        return "scalar_rgb", (f"Dr.Jit loads LLVM {'.'.join(map(str, llvm))}, and Mitsuba's llvm variant needs "
                              f"LLVM >= {MIN_LLVM}")
    result = probe("llvm_ad_rgb")
    if result.ok:
        return "llvm_ad_rgb", ""
    return "scalar_rgb", f"llvm_ad_rgb does not render here ({result.detail})"


def loaded_llvm_version(dr: ModuleType) -> tuple[int, int, int] | None:
    """(major, minor, patch) of the LLVM library Dr.Jit loaded; None when none is loaded or it cannot say."""
    query = getattr(getattr(dr, "detail", None), "llvm_version", None)
    if query is None:
        return None
    try:
        version = tuple(int(v) for v in query())
    except Exception:  # an older or newer Dr.Jit with another signature: let the probe decide
        return None
    if len(version) != 3 or version[0] <= 0:
        return None
    return version  # type: ignore[return-value]


@functools.cache
def choose_variant() -> str:
    """Name of the best Mitsuba variant this machine can run (see module docstring); cached per process."""
    forced = os.environ.get(VARIANT_ENV)
    if forced:
        return forced
    if "DRJIT_LIBLLVM_PATH" not in os.environ:
        found = next((p for p in LLVM_CANDIDATES if Path(p).is_file()), None)
        if found:
            os.environ["DRJIT_LIBLLVM_PATH"] = found
    import drjit as dr  # lazy: the environment variable must be set first
    import mitsuba as mi

    has_llvm = bool(dr.has_backend(dr.JitBackend.LLVM))
    variant, why = decide(set(mi.variants()), bool(dr.has_backend(dr.JitBackend.CUDA)), has_llvm,
                          loaded_llvm_version(dr) if has_llvm else None, probe_variant)
    if why:
        log.warning("Mitsuba renders with %s (slower): %s; install libllvm%d or set DRJIT_LIBLLVM_PATH to it "
                    "(%s=%s silences this)", variant, why, MIN_LLVM, VARIANT_ENV, variant)
    return variant


def load_mitsuba(variant: str | None = None) -> ModuleType:
    """The `mitsuba` module with `variant` (default: `choose_variant()`) set and our plugins registered."""
    variant = variant or choose_variant()
    import mitsuba as mi

    mi.set_variant(variant)
    register()
    return mi
