"""Filled arrays inside numba kernels.

numba's own `np.full` and `np.ones` are overloads compiled once per process and then linked into every
later kernel that uses them, and the kernel that happens to be compiled second with them ran markedly
slower than identical copies compiled before or after it. Which kernel is compiled second depends on
the order a process (the test suite, a first `make demo`) meets them, and the numba cache keeps that
code. `filled` is a loop of its own, inlined into each kernel, so every kernel gets the same code.
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(inline="always")
def filled(n, value, dtype):  # pragma: no cover - jitted
    """np.full(n, value, dtype) for numba code: a new (n,) array of `dtype` with every element `value`."""
    out = np.empty(n, dtype)
    for i in range(n):
        out[i] = value
    return out
