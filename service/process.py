"""Process-wide settings the serving side makes once, on `import service`, before any numba kernel loads.

Each setting gives way to an explicit one in the environment.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import hashlib
import os
import sys
from pathlib import Path

STAGES = Path(__file__).resolve().parent / "stages"  # every numba kernel of the package lives here
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3  # glibc mallopt parameters


def numba_cache_dir(sources: Path, root: Path) -> Path:
    """Cache folder for the numba kernels of `sources` (a folder of .py files): root / numba-<digest>,
    the digest over all their contents.

    numba keys each cached kernel on its own file only, yet our kernels inline helpers from other stage
    modules (local_regression's solver, bilateral's weights, ...): after an edit or an upgrade of one of
    those, the old cache would silently run the old code. A folder per version of the sources cannot.
    """
    digest = hashlib.sha256()
    for path in sorted(sources.glob("*.py")):
        digest.update(path.name.encode() + b"\0" + path.read_bytes())
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
    """Apply the settings; called by service/__init__.py."""
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
            os.environ["NUMBA_CACHE_DIR"] = str(numba_cache_dir(STAGES, cache_home / "mcdenoise"))
            numba = sys.modules.get("numba")
            if numba is not None:  # imported before `service`, it has read its environment already: without
                # this the kernels would load from numba's default caches, possibly built from older helpers
                numba.config.CACHE_DIR = os.environ["NUMBA_CACHE_DIR"]
    explicit_malloc = {"MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_"} & set(os.environ)
    if os.environ.get("MCDENOISE_MALLOC_KEEP", "1") != "0" and not explicit_malloc:
        keep_freed_buffers()
