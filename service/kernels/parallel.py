"""How the numba kernels of the stages split a frame between threads."""

from __future__ import annotations

import numba


def rows_per_thread(rows: int) -> int:
    """Rows of each parallel task when a kernel gives every numba thread one band of `rows` rows (frame or
    centre rows): ceil(rows / threads), at least 1. One band per thread keeps the rows each band reads
    twice (its halo) to a minimum."""
    return max(1, -(-rows // numba.get_num_threads()))
