"""3x3 ranges over interleaved rows, for numba kernels that take their rows in bands.

A kernel that needs, for every value of an (H, W, C) frame, the min and max of its channel over the 3x3
window around it takes the frame's rows in bands of `BAND_ROWS`, one task per band, and keeps each row's
source values once, in three rolling slots (row y in slot y % 3): a row's sources are made once per band
instead of three times, and every loop over a row is branch-free. A value that takes no part in its
neighbours' ranges (a light, a NaN, a row outside the frame) has source +inf in `lo` and -inf in `hi`
(`put_source`): the ranges' min and max take no NaN.
"""

from __future__ import annotations

import numba
import numpy as np

BAND_ROWS = 16  # rows per task


@numba.njit(inline="always")
def put_source(src_lo, src_hi, i, value, left_out):  # pragma: no cover - jitted
    """Source i of a row (src_lo, src_hi: (n,) float32): value (float32), or no part (+inf, -inf) where
    `left_out` or value is NaN, so that a NaN neighbour is ignored as a running min from +inf ignores it."""
    out = left_out or value != value
    src_lo[i] = np.inf if out else value
    src_hi[i] = -np.inf if out else value


@numba.njit(inline="always")
def no_sources(src_lo, src_hi):  # pragma: no cover - jitted
    """Sources of a row that takes no part (outside the frame): src_lo +inf, src_hi -inf, (n,) float32."""
    for i in range(src_lo.shape[0]):
        src_lo[i] = np.inf
        src_hi[i] = -np.inf


@numba.njit(inline="always")
def band_scratch(n):  # pragma: no cover - jitted
    """A band's scratch: (src_lo, src_hi) (3, n) float32, the rolling slots, and lo, hi, all_lo, all_hi (n,)
    float32 for `three_row_ranges`."""
    return (np.empty((3, n), np.float32), np.empty((3, n), np.float32), np.empty(n, np.float32),
            np.empty(n, np.float32), np.empty(n, np.float32), np.empty(n, np.float32))


@numba.njit(inline="always")
def three_row_ranges(src_lo, src_hi, y, channels, centre, lo, hi, all_lo, all_hi):  # pragma: no cover - jitted
    """lo, hi ((n,) float32, n = W C): per value of row y, the min and max of the sources of its channel over the
    3x3 window (with `centre`) or its 8 neighbours (without), from the rolling slots src_lo, src_hi ((3, n)
    float32) of rows y - 1, y and y + 1; +inf > -inf where no value takes part. all_lo, all_hi: (n,) float32
    scratch (the three rows' ranges per column)."""
    n = lo.shape[0]
    up_lo, up_hi = src_lo[(y + 2) % 3], src_hi[(y + 2) % 3]
    mid_lo, mid_hi = src_lo[y % 3], src_hi[y % 3]
    down_lo, down_hi = src_lo[(y + 1) % 3], src_hi[(y + 1) % 3]
    for i in range(n):  # over the rows above and below, and over all three; vectorises
        other_lo, other_hi = min(up_lo[i], down_lo[i]), max(up_hi[i], down_hi[i])
        all_lo[i], all_hi[i] = min(other_lo, mid_lo[i]), max(other_hi, mid_hi[i])
        lo[i] = all_lo[i] if centre else other_lo
        hi[i] = all_hi[i] if centre else other_hi
    for i in range(channels, n):  # the columns left and right
        lo[i] = min(lo[i], all_lo[i - channels])
        hi[i] = max(hi[i], all_hi[i - channels])
    for i in range(n - channels):
        lo[i] = min(lo[i], all_lo[i + channels])
        hi[i] = max(hi[i], all_hi[i + channels])
