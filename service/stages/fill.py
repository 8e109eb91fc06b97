"""Filled arrays inside numba kernels.

numba's own `np.full` and `np.ones` are overloads compiled once per process and then linked into every
later kernel that uses them. Measured on `cross_regression`'s packing kernel (1280x720, 2 threads, five
identical copies compiled one after another in one process): the copy compiled second ran 1.5x slower
(11.4 against 7.3 ms; one thread 23.6 against 15.4 ms), the others not, in whatever order the copies were
compiled; with the fill written as a loop of its own every copy ran at 7.4-7.7 ms. Which kernel is compiled
second depends on the order a process (the test suite, a first `make demo`) meets them, and the numba
cache keeps that code. `filled` is the loop, inlined into each kernel.
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
