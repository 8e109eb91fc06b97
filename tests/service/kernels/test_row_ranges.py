"""3x3 ranges over interleaved rows in bands (service/kernels/row_ranges.py) against the numpy window range."""

import numba
import numpy as np
import pytest

from service.kernels.row_ranges import BAND_ROWS, band_scratch, no_sources, put_source, three_row_ranges
from service.kernels.window import window_range
from service.stages.exact import EXACT_RTOL
from service.stages.noise_blend import _clip_kernel


@numba.njit
def _banded_ranges(values, excluded, centre, lo_out, hi_out):
    """lo_out, hi_out (H, W, C): the ranges as a kernel takes them, one band of BAND_ROWS rows after another."""
    height, width, channels = values.shape
    n = width * channels

    def sources(y, src_lo, src_hi):
        if y < 0 or y >= height:
            no_sources(src_lo, src_hi)
            return
        row, out = values[y].reshape(n), excluded[y].reshape(n)
        for i in range(n):
            put_source(src_lo, src_hi, i, row[i], out[i])

    for band in range(-(-height // BAND_ROWS)):
        y0, y1 = band * BAND_ROWS, min((band + 1) * BAND_ROWS, height)
        src_lo, src_hi, lo, hi, all_lo, all_hi = band_scratch(n)
        for yy in (y0 - 1, y0):
            sources(yy, src_lo[yy % 3], src_hi[yy % 3])
        for y in range(y0, y1):
            sources(y + 1, src_lo[(y + 1) % 3], src_hi[(y + 1) % 3])
            three_row_ranges(src_lo, src_hi, y, channels, centre, lo, hi, all_lo, all_hi)
            lo_out[y].reshape(n)[:] = lo
            hi_out[y].reshape(n)[:] = hi


@pytest.mark.parametrize("shape", [(1, 1, 3), (1, 5, 3), (5, 1, 1), (BAND_ROWS + 3, 7, 3), (2 * BAND_ROWS, 4, 2)])
@pytest.mark.parametrize("centre", [True, False])
def test_banded_ranges_match_the_window_range_across_bands_and_borders(shape, centre):
    rng = np.random.default_rng(sum(shape))
    values = rng.normal(size=shape).astype(np.float32)
    values[rng.random(shape) < 0.1] = np.nan  # a NaN takes no part, as a light does not
    excluded = rng.random(shape) < 0.2  # lights, left out of every range
    lo, hi = np.empty_like(values), np.empty_like(values)
    _banded_ranges(values, excluded, centre, lo, hi)
    want_lo, want_hi = window_range(values, centre=centre, excluded=excluded | np.isnan(values))
    np.testing.assert_array_equal(lo, want_lo)
    np.testing.assert_array_equal(hi, want_hi)


@pytest.mark.parametrize("nan_row", [0, 2])
def test_the_blends_clip_ignores_a_nan_neighbour_above_as_below(nan_row):
    color = np.array([1.0, 1.0, 1.0], np.float32).reshape(3, 1, 1)
    color[1] = 100.0  # a firefly between two values of 1
    color[nan_row] = np.nan
    a, b = color + 0.5, color - 0.5  # the halves differ: the clip applies
    clipped, admitted = np.empty_like(color), np.empty_like(color)
    _clip_kernel(color, a, b, color, False, np.float32(2.0), np.float32(EXACT_RTOL), np.float32(5.0), clipped,
                 admitted)
    assert clipped[1, 0, 0] == 1.0  # clipped to the one neighbour left
    assert admitted[1, 0, 0] == 100.0  # 99 from the colour, beyond 5 |a - b|: not admitted
