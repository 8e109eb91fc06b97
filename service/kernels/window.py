"""Windowed filters without padding: the overlapping sub-rectangles of an image and its shifted copy.

For an offset (dy, dx), pixel (y, x) pairs with neighbour (y + dy, x + dx). `overlap` returns the
slices that select, for every pair whose neighbour lies inside the image, the centre pixels and the
neighbour pixels, so a windowed filter accumulates `out[centre] += w * img[neighbour]` with whole-array
operations and never reads outside the frame (no padding, no replicated borders).
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np

Slice2 = tuple[slice, slice]


def window_offsets(radius: int, *, half: bool = False) -> Iterator[tuple[int, int]]:
    """Offsets (dy, dx) of a (2r+1)^2 window in raster order.

    half: only one offset of every pair {o, -o}, and not (0, 0): for symmetric weights, where
    the pair's weight is computed once and applied in both directions.
    """
    for dy in range(-radius, radius + 1):
        for dx in range(-radius, radius + 1):
            if half and (dy < 0 or (dy == 0 and dx <= 0)):
                continue
            yield dy, dx


def overlap(height: int, width: int, dy: int, dx: int) -> tuple[Slice2, Slice2] | None:
    """(centre slices, neighbour slices) of the pixels whose neighbour at (dy, dx) is inside the
    image, or None when no pixel has one (the offset exceeds the frame)."""
    y0, y1 = max(0, -dy), min(height, height - dy)
    x0, x1 = max(0, -dx), min(width, width - dx)
    if y0 >= y1 or x0 >= x1:
        return None
    return (slice(y0, y1), slice(x0, x1)), (slice(y0 + dy, y1 + dy), slice(x0 + dx, x1 + dx))


def window_range(values: np.ndarray, radius: int = 1, *, centre: bool = True,
                 excluded: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi): per pixel the smallest and largest of `values` ((H, W, ...) any real dtype) over its in-frame
    (2 radius + 1)^2 window, the pixel itself with `centre` only, leaving out the values `excluded` marks
    ((H, W, ...) bool, or None); +inf and -inf where none is left. numpy, for the kernels' twins."""
    height, width = values.shape[:2]
    lo, hi = np.full_like(values, np.inf), np.full_like(values, -np.inf)
    for dy, dx in window_offsets(radius):
        pair = None if dy == dx == 0 and not centre else overlap(height, width, dy, dx)
        if pair is None:
            continue
        (cy, cx), (ny, nx) = pair
        src = values[ny, nx]
        out = np.zeros(src.shape, bool) if excluded is None else excluded[ny, nx]
        lo[cy, cx] = np.minimum(lo[cy, cx], np.where(out, np.inf, src))
        hi[cy, cx] = np.maximum(hi[cy, cx], np.where(out, -np.inf, src))
    return lo, hi
