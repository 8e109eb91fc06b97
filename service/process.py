"""Process-wide settings for the programs that run the kernels: `configure()`, called by each entry point
(`python -m service`, the HTTP app's factory, the benchmark's commands, the test session) before its first
frame; importing a module of this package sets nothing. Each setting gives way to an explicit one in the
environment.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import hashlib
import os
import sys
from pathlib import Path

_PACKAGE = Path(__file__).resolve().parent
KERNEL_SOURCES = tuple(_PACKAGE / name for name in ("kernels", "regression", "stages"))  # every numba kernel
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3  # glibc mallopt parameters


def numba_cache_dir(sources: tuple[Path, ...], root: Path) -> Path:
    """Cache folder for the numba kernels of `sources` (folders of .py files): root / numba-<digest>, the
    digest over all their names and contents.

    numba keys each cached kernel on its own file only, yet our kernels inline helpers from other stage
    modules (the regression solver, bilateral's weights, ...): after an edit or an upgrade of one of
    those, the old cache would silently run the old code. A folder per version of the sources cannot.
    """
    digest = hashlib.sha256()
    for folder in sources:
        for path in sorted(folder.glob("*.py")):
            digest.update(f"{folder.name}/{path.name}".encode() + b"\0" + path.read_bytes())
    return root / f"numba-{digest.hexdigest()[:16]}"


def keep_freed_buffers() -> bool:
    """Make glibc malloc keep freed frame-sized blocks in the heap (mallopt M_MMAP_THRESHOLD = 1 GiB,
    M_TRIM_THRESHOLD = 2 GiB) instead of returning them to the kernel, so the next frame's arrays do not
    pay thousands of minor page faults on first touch. Memory is reused frame after frame, not returned.
    Returns whether it applied (Linux with glibc only)."""
    if sys.platform != "linux":
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        return bool(libc.mallopt(_M_MMAP_THRESHOLD, ctypes.c_int(1 << 30))) and bool(
            libc.mallopt(_M_TRIM_THRESHOLD, ctypes.c_int(2**31 - 1))
        )
    except (OSError, AttributeError):  # no libc by that name, or no mallopt (musl)
        return False


def configure() -> None:
    """Apply the settings. Idempotent; call it before the first kernel runs (kernel modules imported
    earlier are pointed at the versioned cache folder here)."""
    # numba's parallel kernels run on OpenMP (thread-safe: the HTTP service steps frames from a thread
    # pool, which numba's `workqueue` layer does not allow). OpenMP's default busy-wait between parallel
    # regions starves the other threads of a shared machine; passive waiting avoids it.
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    if "NUMBA_CACHE_DIR" not in os.environ:
        try:
            cache_home = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
        except RuntimeError:  # no home folder: numba's own default (__pycache__ beside the sources)
            cache_home = None
        if cache_home is not None:
            os.environ["NUMBA_CACHE_DIR"] = str(numba_cache_dir(KERNEL_SOURCES, cache_home / "mcdenoise"))
            if "numba" in sys.modules:  # numba has read its environment already
                _relocate_caches(os.environ["NUMBA_CACHE_DIR"])
    explicit_malloc = {"MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_"} & set(os.environ)
    if os.environ.get("MCDENOISE_MALLOC_KEEP", "1") != "0" and not explicit_malloc:
        keep_freed_buffers()


def _relocate_caches(folder: str) -> None:
    """Point numba, and every cached kernel of this package defined so far, at `folder`: numba fixes a
    kernel's cache location when its module is imported, and its default one (beside the sources, keyed
    on the kernel's own file only) would serve kernels built from older helpers."""
    import numba
    from numba.core.caching import FunctionCache
    from numba.core.dispatcher import Dispatcher

    numba.config.CACHE_DIR = folder
    for name, module in list(sys.modules.items()):
        if name.split(".")[0] != __name__.split(".")[0] or module is None:
            continue
        for value in list(vars(module).values()):
            if isinstance(value, Dispatcher) and isinstance(value._cache, FunctionCache):
                value.enable_caching()
