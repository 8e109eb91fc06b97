"""The noise blend's per-pixel weights and its sums over tiles (service/stages/noise_blend.py, whose
docstring says what e, v, the weight and the level are): numba kernels, each a parallel pass over the frame.
`noise_blend_reference` (noise_blend.py) is their numpy twin.
"""

from __future__ import annotations

import numba
import numpy as np

FLOAT32_MAX = float(np.finfo(np.float32).max)  # a level, and the blend of values near it, stay within it
# Rows of the tile sums: weighted e, the input's weighted error, pixels whose halves differ, the weighted floor
# of the input's error, and over the pixels whose halves differ the input (at least 0) and v
SUM_ROWS = 6


@numba.njit(parallel=True, cache=True, error_model="numpy")
def level_kernel(color, e, has_emission, radius, level):  # pragma: no cover - jitted
    """level (H, W): the mean over the in-frame (2 radius + 1)^2 window of the channel means of color (less e
    with `has_emission`), at most float32's largest. A task per row for the channel sums, then per row the
    window's column sums and their sums across it (float64)."""
    height, width, channels = color.shape
    sums = np.empty((height, width), np.float64)  # float64: sums of radiance up to float32's largest
    for y in numba.prange(height):
        for x in range(width):
            s = 0.0
            for c in range(channels):
                s += np.float64(color[y, x, c]) - e[y, x, c] if has_emission else color[y, x, c]
            sums[y, x] = s
    for y in numba.prange(height):
        y0, y1 = max(y - radius, 0), min(y + radius + 1, height)
        column = sums[y0].copy()
        for yy in range(y0 + 1, y1):
            column += sums[yy]
        scale = 1.0 / (channels * (y1 - y0))
        for x in range(width):
            x0, x1 = max(x - radius, 0), min(x + radius + 1, width)
            total = 0.0  # summed afresh at each x: a running sum would carry a 1e20's rounding along the row
            for xx in range(x0, x1):
                total += column[xx]
            level[y, x] = np.float32(min(total * scale / (x1 - x0), FLOAT32_MAX))


@numba.njit(inline="always", cache=True, error_model="numpy")
def _proxy_weight(mean_out, level, eps, floor):  # pragma: no cover - jitted
    """The weight 1 / (proxy^2 + eps) of a pixel (noise_blend's docstring): proxy its output's channel mean mean_out
    (float64, less e), at most its `level` (float32) and at least `floor` (PROXY_FLOOR) times it; float64."""
    proxy = max(min(mean_out, np.float64(level)), floor * np.float64(level), 0.0)
    return 1.0 / (proxy * proxy + eps)


@numba.njit(parallel=True, cache=True, error_model="numpy")
def tile_kernel(out, color, a, b, e, has_emission, level, input_error, input_floor, use, use_tile, has_choice,
                tile, eps, floor, sums):  # pragma: no cover - jitted
    """sums (SUM_ROWS, th, tw): per tile the weighted sums of e and of the input's error, the count of pixels
    whose halves differ, the weighted sum of the input error's floor, and over the pixels whose halves differ
    the sums of the input's channel means (at least 0) and of v's, in float64 (radiance less e); weights
    `_proxy_weight` (eps = REL_L2_EPS, radiance^2; floor PROXY_FLOOR; level (H, W) float32, the 3x3 box mean
    of the colour less e).
    The input's error and its floor are v, or, with `has_choice`, input_error and input_floor ((H, W) float64,
    the accumulated input's and a^2 v, the channels' means) where `use` ((th', tw') bool, per tile of side
    use_tile) takes the accumulated input. tile: side in pixels. A task per row of tiles; per row, its values'
    terms first (`_value_terms`), then each tile's pixels in order."""
    height, width, channels = out.shape
    n = width * channels
    for ty in numba.prange(sums.shape[1]):
        acc = np.zeros((SUM_ROWS, sums.shape[2]))  # this row of tiles' sums
        terms = np.empty((4, n))  # per value of a row: `_value_terms`
        for y in range(ty * tile, min((ty + 1) * tile, height)):
            _value_terms(out, color, a, b, e, has_emission, y, terms)
            less, err, var, lit = terms[0], terms[1], terms[2], terms[3]
            for tx in range(sums.shape[2]):
                s0 = s1 = s2 = s3 = s4 = s5 = 0.0  # this row's part of the tile's sums
                for x in range(tx * tile, min((tx + 1) * tile, width)):
                    i = x * channels
                    mean_out, error, variance, colour = 0.0, 0.0, 0.0, 0.0
                    for c in range(i, i + channels):
                        mean_out += less[c]
                        error += err[c]
                        variance += var[c]
                        colour += lit[c]
                    w = _proxy_weight(mean_out / channels, level[y, x], eps, floor) / channels
                    taken, least = variance, variance
                    if has_choice and use[y // use_tile, x // use_tile]:
                        taken, least = input_error[y, x] * channels, input_floor[y, x] * channels
                    s0 += w * error
                    s1 += w * taken
                    s3 += w * least
                    if variance > 0:
                        s2 += 1.0
                        s4 += max(colour / channels, 0.0)
                        s5 += variance / channels
                acc[0, tx] += s0
                acc[1, tx] += s1
                acc[2, tx] += s2
                acc[3, tx] += s3
                acc[4, tx] += s4
                acc[5, tx] += s5
        sums[:, ty] += acc


@numba.njit(inline="always", cache=True, error_model="numpy")
def _value_terms(out, color, a, b, e, has_emission, y, terms):  # pragma: no cover - jitted
    """terms ((4, W * C) float64): per value of row y of out, color, the halves a, b and e ((H, W, C) float32; e
    only with `has_emission`): less = out - e, err = (out - color)^2 - h^2, var = h^2 with h = (a - b) / 2, and
    lit = color - e (noise_blend's e and v before the sum over channels). Branch-free: vectorises."""
    n = terms.shape[1]
    ro, rc, ra, rb = out[y].reshape(n), color[y].reshape(n), a[y].reshape(n), b[y].reshape(n)
    re = e[y].reshape(n) if has_emission else np.zeros(n, np.float32)
    for i in range(n):
        o, col = np.float64(ro[i]), np.float64(rc[i])
        h = (np.float64(ra[i]) - rb[i]) * 0.5
        terms[0, i] = o - re[i]
        terms[1, i] = (o - col) * (o - col) - h * h
        terms[2, i] = h * h
        terms[3, i] = col - re[i]


@numba.njit(parallel=True, cache=True, error_model="numpy")
def choice_kernel(out, color, a, b, e, has_emission, level, input_error, tile, eps, floor,
                  stats):  # pragma: no cover - jitted
    """stats (3, th, tw) float64: per tile the sum of d, of d^2 and the pixels, d the weight (`_proxy_weight`)
    times input_error ((H, W) float64, the accumulated input's error, the channels' mean) less v's channel
    mean (`takes_accumulated`). A task per row of tiles; per row, its values' terms first (`_value_terms`)."""
    height, width, channels = out.shape
    n = width * channels
    for ty in numba.prange(stats.shape[1]):
        terms = np.empty((4, n))  # per value of a row: `_value_terms`
        for y in range(ty * tile, min((ty + 1) * tile, height)):
            _value_terms(out, color, a, b, e, has_emission, y, terms)
            less, var = terms[0], terms[2]
            for tx in range(stats.shape[2]):
                for x in range(tx * tile, min((tx + 1) * tile, width)):
                    mean_out, variance = 0.0, 0.0
                    for c in range(x * channels, (x + 1) * channels):
                        mean_out += less[c]
                        variance += var[c]
                    d = _proxy_weight(mean_out / channels, level[y, x], eps, floor) * (
                        input_error[y, x] - variance / channels)
                    stats[0, ty, tx] += d
                    stats[1, ty, tx] += d * d
                    stats[2, ty, tx] += 1.0
