"""mcdenoise serving side: frames, EXR I/O, classical stages, pipelines, ONNX runtime and HTTP API.

Imports neither torch nor mitsuba."""

import ctypes
import ctypes.util
import os
import sys

# numba's parallel kernels run on OpenMP (thread-safe: the HTTP service steps frames from a thread pool,
# which numba's `workqueue` layer does not allow). OpenMP's default busy-wait between parallel regions
# costs 3-9x on a shared 2-core machine (measured on svgf at 256x256); passive waiting avoids it.
# Set before any numba kernel first loads the OpenMP runtime; an explicit setting by the user wins.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

# glibc malloc hands every freed block above its mmap threshold (frame-sized arrays) back to the kernel,
# so each frame's fresh arrays pay thousands of minor page faults on first touch. Keeping them in the heap
# (mallopt M_MMAP_THRESHOLD = 1 GiB, M_TRIM_THRESHOLD = 2 GiB) removes that: cross-regression at 1280x720
# on 2 cores 251-309 -> 234-244 ms, flr 34 -> 27 ms (median of 5). Memory is reused frame after frame,
# not returned. MCDENOISE_MALLOC_KEEP=0, or an explicit MALLOC_MMAP_THRESHOLD_ / MALLOC_TRIM_THRESHOLD_
# in the environment, leaves malloc as it is.
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3
if (
    sys.platform == "linux"
    and os.environ.get("MCDENOISE_MALLOC_KEEP", "1") != "0"
    and not {"MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_"} & set(os.environ)
):
    try:
        _libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        _libc.mallopt(_M_MMAP_THRESHOLD, ctypes.c_int(1 << 30))
        _libc.mallopt(_M_TRIM_THRESHOLD, ctypes.c_int(2**31 - 1))
    except (OSError, AttributeError):  # not glibc (musl has no mallopt): nothing to tune
        pass
