"""Windowed helpers without padding (service/kernels/window.py): the window range on hand-computed frames."""

import numpy as np

from service.kernels.window import window_range


def test_window_range_with_and_without_the_centre_and_exclusions():
    values = np.array([[1.0, 5.0, 2.0], [7.0, 0.0, 3.0]])
    lo, hi = window_range(values)
    np.testing.assert_array_equal(lo, [[0, 0, 0], [0, 0, 0]])
    np.testing.assert_array_equal(hi, [[7, 7, 5], [7, 7, 5]])
    lo, hi = window_range(values, centre=False)  # the 8 neighbours: the 0 leaves its own range
    np.testing.assert_array_equal(lo[1, 1], 1.0)
    np.testing.assert_array_equal(hi[1, 1], 7.0)
    excluded = values == 7.0  # a light left out of its neighbours' ranges, and of its own
    lo, hi = window_range(values, excluded=excluded)
    np.testing.assert_array_equal(hi, [[5, 5, 5], [5, 5, 5]])
    lo, hi = window_range(values[:1, :1], centre=False)  # a 1x1 frame: no neighbour left
    assert lo[0, 0] == np.inf and hi[0, 0] == -np.inf
    planes = np.stack([values, -values], axis=-1)  # trailing axes are taken per element
    lo, hi = window_range(planes)
    np.testing.assert_array_equal(lo[..., 1], -window_range(values)[1])
