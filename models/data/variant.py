"""Which Mitsuba 3 variant renders here: the one place that chooses it and imports mitsuba.

Order of preference: `cuda_ad_rgb` when a CUDA GPU is present, `llvm_ad_rgb` when Dr.Jit can load an
LLVM it supports (LLVM 19 from apt: `apt-get install -y libllvm19`), else `scalar_rgb` (no JIT, about
half the speed of LLVM on simple scenes, much slower for the Python AO integrator). The environment
variable MCDENOISE_MI_VARIANT forces a variant. Dr.Jit reads DRJIT_LIBLLVM_PATH once, when it is first
imported, so `choose_variant` sets it (when unset and LLVM 19 is installed) before importing anything.
"""

from __future__ import annotations

import functools
import os
from pathlib import Path
from types import ModuleType

from models.data.integrators import register

# Where Debian's libllvm19 package puts the library (issue 7: the llvm variant needs LLVM >= 19 here).
LLVM_CANDIDATES = (
    "/usr/lib/x86_64-linux-gnu/libLLVM-19.so",
    "/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1",
    "/usr/lib/aarch64-linux-gnu/libLLVM-19.so",
)
PREFERENCE = ("cuda_ad_rgb", "llvm_ad_rgb", "scalar_rgb")
VARIANT_ENV = "MCDENOISE_MI_VARIANT"  # forces a variant, e.g. scalar_rgb in a test


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

    available = set(mi.variants())
    if "cuda_ad_rgb" in available and dr.has_backend(dr.JitBackend.CUDA):
        return "cuda_ad_rgb"
    if "llvm_ad_rgb" in available and dr.has_backend(dr.JitBackend.LLVM):
        return "llvm_ad_rgb"
    return "scalar_rgb"


def load_mitsuba(variant: str | None = None) -> ModuleType:
    """The `mitsuba` module with `variant` (default: `choose_variant()`) set and our plugins registered."""
    variant = variant or choose_variant()
    import mitsuba as mi

    mi.set_variant(variant)
    register()
    return mi

