"""Fast local regression (FLR, Salmi et al., "Fast local neural regression for low-cost global
illumination denoising"): per-pixel least squares of noisy radiance on guide images.

For every pixel k, A_k = argmin |X_k A - Y_k|^2 over a window (Salmi's equation; X_k has a constant
column and the Q guides, Y_k the RGB radiance), weighted by a Gaussian (weighted least squares, their
ref. [3]), and I_k = x_k A_k. As the paper describes, the per-pixel matrices X^T X and X^T Y are not
built per window: the outer-product tensors of every pixel are summed, downsampled (box, `scale` x
`scale` cells) and blurred with a separable Gaussian at the low resolution. As in the Fast Guided Filter
(He and Sun 2015, Salmi's ref. [2]) the systems are solved on the low-resolution grid and the
coefficients are bilinearly upsampled before I_k = x_k A_k is evaluated at full resolution.

The systems are solved in centred form, cov(x, x) a = cov(x, y), b = mean(y) - a . mean(x), which is the
same least-squares solution as with the constant column, better conditioned, with a ridge on the slopes
only (`regression.solve.solve_ridge`). Guides are standardised per frame first, so any guide images work:
the G-buffers here, or the guides a network learns (FLNR) later, through `local_linear_regression`.
The Gaussian is truncated at the frame border and the sums are weights, not averages, so border pixels
get an exact weighted fit over the pixels that exist (no padding).
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from service.kernels.fill import filled
from service.kernels.parallel import rows_per_thread
from service.kernels.window import overlap
from service.regression.planes import (
    channel_planes,
    channel_planes_reference,
    from_planes,
    interleave_row,
    standardise,
    to_planes,
)
from service.regression.solve import RIDGE_RELATIVE, cholesky_ridge_solve, solve_ridge_reference
from service.stages.albedo import remodulate
from service.stages.bilateral import log_depth
from service.stages.outliers import FIREFLY_K, check_firefly_k, clamp_outlier_planes

RIDGE_ABSOLUTE_FLR = 1e-4  # slope ridge floor, in units of a standardised guide's frame variance


@dataclass(frozen=True)
class FlrParams:
    """Options of the fast local regression."""

    scale: int = 4  # box-downsampling factor of the outer-product tensors, pixels (Salmi: "downsampling")
    sigma: float = 0.5  # std of the Gaussian blur on the low-resolution grid, in cells (x scale = pixels)
    truncate: float = 3.0  # Gaussian support radius in sigmas
    firefly_k: float | None = FIREFLY_K  # clamp outliers to k neighbour ranges beyond their neighbours; None: off
    robust_clamp: bool = True  # sigma-clipped clamp of outlier clusters (outliers.clamp_outlier_clusters)
    ridge_relative: float = RIDGE_RELATIVE  # Tikhonov on the slopes, relative to each guide's local variance
    ridge_absolute: float = RIDGE_ABSOLUTE_FLR  # Tikhonov floor on the slopes (standardised guide units)

    def __post_init__(self) -> None:
        if self.scale < 1:
            raise ValueError(f"scale must be >= 1, got {self.scale}")
        if not (self.sigma > 0 and self.truncate > 0):
            raise ValueError("sigma and truncate must be > 0")
        if not (self.ridge_relative >= 0 and self.ridge_absolute > 0):
            raise ValueError("ridge_relative must be >= 0 and ridge_absolute > 0")
        check_firefly_k(self.firefly_k)

    @property
    def window(self) -> int:
        """Side of the region a pixel's fit draws on, pixels: Gaussian support plus one cell each side."""
        return (2 * int(np.ceil(self.truncate * self.sigma)) + 3) * self.scale


def gbuffer_guides(
    normal: np.ndarray | None = None, depth: np.ndarray | None = None, ao: np.ndarray | None = None
) -> np.ndarray:
    """FLR guides from G-buffers (Salmi: normals, depth, ambient occlusion), those that are present.

    normal: (H, W, 3) float32 unit normal; depth: (H, W, 1) float32 camera distance (scene units; its log
    is used); ao: (H, W, 1) float32 in [0, 1]. Returns (H, W, Q) float32, Q in 0..5 (0: a box filter), a
    view of (Q, H, W) memory: `to_planes` of it is free. `gbuffer_guides_reference` is the numpy twin.
    """
    parts = [part for part in (normal, depth, ao) if part is not None]
    if not parts:
        raise ValueError("gbuffer_guides needs at least one guide layer")
    planes = np.empty((sum(part.shape[2] for part in parts), *parts[0].shape[:2]), np.float32)
    q = 0
    if normal is not None:
        channel_planes(normal, out=planes[: normal.shape[2]])
        q = normal.shape[2]
    if depth is not None:
        log_depth(depth[..., 0], out=planes[q])
        q += 1
    if ao is not None:
        planes[q] = ao[..., 0]
    return planes.transpose(1, 2, 0)


def gbuffer_guides_reference(
    normal: np.ndarray | None = None, depth: np.ndarray | None = None, ao: np.ndarray | None = None
) -> np.ndarray:
    """Plain-numpy twin of `gbuffer_guides` (an (H, W, Q) array of its own layout)."""
    parts = []
    if normal is not None:
        parts.append(normal)
    if depth is not None:
        parts.append(log_depth(depth))
    if ao is not None:
        parts.append(ao)
    if not parts:
        raise ValueError("gbuffer_guides needs at least one guide layer")
    return np.concatenate(parts, axis=-1).astype(np.float32, copy=False)


def local_linear_regression(
    radiance: np.ndarray,
    guides: np.ndarray,
    params: FlrParams | None = None,
    *,
    albedo: np.ndarray | None = None,
    reference: bool = False,
) -> np.ndarray:
    """FLR of `radiance` on `guides`: I_k = x_k A_k with A_k the Gaussian-weighted local fit.

    radiance: (H, W, C) float32 linear radiance (any sign). guides: (H, W, Q) float32, any units
    (standardised here; Q may be 0). albedo: (H, W, C) float32 in [0, 1], or None: the regression runs on
    radiance / (albedo + eps) and its result is multiplied back (`albedo.demodulate` / `remodulate`, fused
    into the first and last passes). Returns (H, W, C) float32 linear radiance.
    reference: plain-numpy kernels instead of numba (slow; for tests).
    """
    params = params or FlrParams()
    y = (channel_planes_reference if reference else channel_planes)(radiance, albedo)
    y = clamp_outlier_planes(y, params.firefly_k, params.robust_clamp)
    x = standardise(to_planes(guides))
    sums = (cell_sums_reference if reference else cell_sums)(x, y, params.scale)
    sums = (gaussian_blur_reference if reference else gaussian_blur)(sums, params.sigma, params.truncate)
    coefs = (solve_cells_reference if reference else solve_cells)(sums, x.shape[0], y.shape[0], params)
    apply = apply_coefficients_reference if reference else apply_coefficients
    return from_planes(apply(x, coefs, params.scale, albedo))


# ------------------------------------------------------------------------------------------ moments


def moment_count(q: int, c: int) -> int:
    """Number of moment planes for Q guides and C signal channels: 1, x, y, x x^T (upper), x y^T."""
    return 1 + q + c + q * (q + 1) // 2 + q * c


def cell_sums(x: np.ndarray, y: np.ndarray, scale: int) -> np.ndarray:
    """Per low-resolution cell, the sums over its pixels of [1, x, y, x x^T (upper triangle), x y^T].

    x: (Q, H, W) float32 guides; y: (C, H, W) float32 signal. Cells are `scale` x `scale` pixels, the last
    row and column of cells partial. Returns (Hs, E, Ws) float32, E = `moment_count(Q, C)` moment planes
    per cell row, in the order of `_moment_index`. numba kernel; `cell_sums_reference` is the plain-numpy
    twin.
    """
    q, height, width = x.shape
    c = y.shape[0]
    hs, ws = -(-height // scale), -(-width // scale)
    out = np.empty((hs, moment_count(q, c), ws), np.float32)
    _cell_sums_kernel(x, y, scale, out)
    return out


def cell_sums_reference(x: np.ndarray, y: np.ndarray, scale: int) -> np.ndarray:
    """Plain-numpy twin of `cell_sums`."""
    q, height, width = x.shape
    c = y.shape[0]
    hs, ws = -(-height // scale), -(-width // scale)
    ones = np.ones((1, height, width), np.float32)
    planes = [ones, x, y]
    planes += [x[i : i + 1] * x[j : j + 1] for i in range(q) for j in range(i, q)]
    planes += [x[i : i + 1] * y[k : k + 1] for i in range(q) for k in range(c)]
    full = np.concatenate(planes, axis=0)
    padded = np.zeros((full.shape[0], hs * scale, ws * scale), np.float32)
    padded[:, :height, :width] = full
    sums = padded.reshape(full.shape[0], hs, scale, ws, scale).sum(axis=(2, 4), dtype=np.float32)
    return np.ascontiguousarray(sums.transpose(1, 0, 2))


@numba.njit(parallel=True, cache=True, fastmath=True, error_model="numpy")
def _cell_sums_kernel(x, y, scale, out):
    """Per cell row: every moment's product summed over the cell row's pixel rows into a (E, W) buffer
    (contiguous along x, so it vectorises), then over each cell's `scale` columns: `scale` shifted adds
    of the buffer row, read at every `scale`-th column."""
    q, height, width = x.shape
    c = y.shape[0]
    ne, ws = out.shape[1], out.shape[2]
    fa = np.empty(ne, np.int64)  # moment e is the product of planes fa[e] and fb[e] of [1, x, y]
    fb = np.empty(ne, np.int64)
    for e in range(1 + q + c):
        fa[e], fb[e] = 0, e
    e = 1 + q + c
    for i in range(q):
        for j in range(i, q):
            fa[e], fb[e] = 1 + i, 1 + j
            e += 1
    for i in range(q):
        for k in range(c):
            fa[e], fb[e] = 1 + i, 1 + q + k
            e += 1
    whole = width // scale  # cells with all their columns
    for a in numba.prange(out.shape[0]):
        acc = np.zeros((ne, width), np.float32)
        planes = np.empty((2, 1 + q + c, width), np.float32)  # two pixel rows per pass over acc
        planes[:, 0, :] = 1.0
        last = min(height, a * scale + scale)
        for y0 in range(a * scale, last, 2):
            pair = y0 + 1 < last
            for r in range(2 if pair else 1):
                for i in range(q):
                    planes[r, 1 + i, :] = x[i, y0 + r]
                for k in range(c):
                    planes[r, 1 + q + k, :] = y[k, y0 + r]
            for e in range(ne):
                a0, b0, dst = planes[0, fa[e]], planes[0, fb[e]], acc[e]
                if pair:
                    a1, b1 = planes[1, fa[e]], planes[1, fb[e]]
                    for xx in range(width):
                        dst[xx] += a0[xx] * b0[xx] + a1[xx] * b1[xx]
                else:
                    for xx in range(width):
                        dst[xx] += a0[xx] * b0[xx]
        window = np.empty(width, np.float32)  # window[u] = sum of acc[e, u .. u + scale - 1]
        span = width - scale + 1
        for e in range(ne):
            src, dst = acc[e], out[a, e]
            if whole:
                window[:span] = src[:span]
                for t in range(1, scale):
                    shifted = src[t:]
                    for u in range(span):
                        window[u] += shifted[u]
                for b in range(whole):
                    dst[b] = window[b * scale]
            if whole < ws:
                total = np.float32(0.0)
                for xx in range(whole * scale, width):
                    total += src[xx]
                dst[whole] = total


def gaussian_blur(sums: np.ndarray, sigma: float, truncate: float) -> np.ndarray:
    """Separable Gaussian blur of cell sums over the cell grid, truncated at the border (no padding, no
    renormalisation).

    sums: (h, E, w) float32 (`cell_sums`). Returns (h, E, w) float32; the taps are exp(-d^2 / 2 sigma^2),
    d in cells, |d| <= ceil(truncate sigma), centre tap 1: the result is a weighted sum, not an average, so
    the ratios the solver forms are exact weighted least squares near the border too. numba kernel
    (parallel over cell rows, no transposes); `gaussian_blur_reference` is the plain-numpy twin.
    """
    sums = np.ascontiguousarray(sums, dtype=np.float32)
    rows, out = np.empty_like(sums), np.empty_like(sums)
    _blur_kernel(sums, gaussian_taps(sigma, truncate), rows, out)
    return out


def gaussian_blur_reference(sums: np.ndarray, sigma: float, truncate: float) -> np.ndarray:
    """Plain-numpy twin of `gaussian_blur`."""
    taps = gaussian_taps(sigma, truncate)
    out = sums.transpose(0, 2, 1)  # (h, w, E): the blur runs over the first two axes
    height, width = out.shape[:2]
    for axis in (0, 1):
        src, out = out, out.copy()
        for d in range(1, len(taps)):
            for sign in (-1, 1):
                pair = overlap(height, width, sign * d if axis == 0 else 0, sign * d if axis == 1 else 0)
                if pair is not None:
                    (cy, cx), (ny, nx) = pair
                    out[cy, cx] += taps[d] * src[ny, nx]
    return np.ascontiguousarray(out.transpose(0, 2, 1))


def gaussian_taps(sigma: float, truncate: float) -> np.ndarray:
    """Taps 0..R of the Gaussian, R = ceil(truncate sigma), tap 0 = 1. (R+1,) float32."""
    d = np.arange(int(np.ceil(truncate * sigma)) + 1, dtype=np.float64)
    return np.exp(-0.5 * (d / sigma) ** 2).astype(np.float32)


@numba.njit(parallel=True, cache=True, fastmath=True, error_model="numpy")
def _blur_kernel(src, taps, rows, out):
    """src, rows, out: (h, E, w). rows[y] = sum over |d| <= R of taps[|d|] src[y + d] (inside only), then
    out[:, :, x] likewise over rows[:, :, x + d]: both passes on contiguous vectors."""
    height, ne, width = src.shape
    radius = taps.shape[0] - 1
    for y in numba.prange(height):
        dst = rows[y].reshape(ne * width)
        dst[:] = src[y].reshape(ne * width)
        for d in range(1, radius + 1):
            for yy in (y - d, y + d):
                if 0 <= yy < height:
                    t, other = taps[d], src[yy].reshape(ne * width)
                    for i in range(ne * width):
                        dst[i] += t * other[i]
    for y in numba.prange(height):
        for e in range(ne):
            line, dst = rows[y, e], out[y, e]
            dst[:] = line
            for d in range(1, min(radius, width - 1) + 1):
                t, n = taps[d], width - d
                right, left = dst[d:], line[d:]  # dst[x + d] += t line[x]; dst[x] += t line[x + d]
                for i in range(n):
                    right[i] += t * line[i]
                for i in range(n):
                    dst[i] += t * left[i]


def _moment_index(q: int, c: int) -> tuple[int, int, dict[tuple[int, int], int], int]:
    """(index of sum x, of sum y, {(i, j): index of sum x_i x_j}, index of first sum x y); sum 1 is at 0."""
    xx, e = {}, 1 + q + c
    for i in range(q):
        for j in range(i, q):
            xx[(i, j)] = xx[(j, i)] = e
            e += 1
    return 1, 1 + q, xx, e


def solve_cells(sums: np.ndarray, q: int, c: int, params: FlrParams) -> np.ndarray:
    """Coefficients of every cell's weighted least-squares fit, from its blurred sums.

    sums: (h, E, w) float32 from `gaussian_blur(cell_sums(...))`. Returns (h, 1 + Q, C, w) float32:
    fit(x) = coefs[:, 0] + sum over i of x_i coefs[:, 1 + i] (offsets, then the slope of each guide).
    One fused numba kernel (covariances, ridge Cholesky on all cells of a row at once, offsets);
    `solve_cells_reference` is the plain-numpy twin.
    """
    ixx = _moment_index(q, c)[2]
    pick = np.array([[ixx[(i, j)] for j in range(q)] for i in range(q)], np.int64).reshape(q, q)
    coefs = np.empty((sums.shape[0], 1 + q, c, sums.shape[2]), np.float32)
    _solve_cells_kernel(np.ascontiguousarray(sums, dtype=np.float32), pick, float(params.ridge_relative),
                        float(params.ridge_absolute), coefs)  # fmt: skip
    return coefs


def solve_cells_reference(sums: np.ndarray, q: int, c: int, params: FlrParams) -> np.ndarray:
    """Plain-numpy twin of `solve_cells` (float64 covariances, `solve_ridge_reference`)."""
    ix, iy, ixx, ixy = _moment_index(q, c)
    sums = np.asarray(sums, np.float64).transpose(0, 2, 1)  # (h, w, E)
    s0 = np.maximum(sums[..., 0], 1e-30)[..., None]
    mean_x, mean_y = sums[..., ix : ix + q] / s0, sums[..., iy : iy + c] / s0
    pick = np.array([[ixx[(i, j)] for j in range(q)] for i in range(q)], np.int64).reshape(q, q)
    cov_xx = sums[..., pick] / s0[..., None] - mean_x[..., :, None] * mean_x[..., None, :]
    sum_xy = sums[..., ixy : ixy + q * c].reshape(*sums.shape[:2], q, c)
    cov_xy = sum_xy / s0[..., None] - mean_x[..., :, None] * mean_y[..., None, :]
    if q == 0:
        slopes = np.zeros((*sums.shape[:2], 0, c))
    else:
        slopes = solve_ridge_reference(cov_xx, cov_xy, params.ridge_relative, params.ridge_absolute,
                                       weight_sum=np.ones(sums.shape[:2])).astype(np.float64)  # fmt: skip
    offsets = mean_y - np.einsum("hwq,hwqc->hwc", mean_x, slopes)
    coefs = np.concatenate([offsets[:, :, None, :], slopes], axis=2)  # (h, w, 1 + Q, C)
    return np.ascontiguousarray(coefs.transpose(0, 2, 3, 1), dtype=np.float32)


@numba.njit(parallel=True, cache=True, fastmath=True, error_model="numpy")
def _solve_cells_kernel(sums, pick, ridge_relative, ridge_absolute, coefs):
    """Per cell row, its cells as the lanes, in float64: weighted means and covariances from the sums
    (order of `_moment_index`), cov(x, x) a = cov(x, y) with the slope ridge (`cholesky_ridge_solve`,
    weight sum 1), b = mean(y) - a . mean(x)."""
    h, nf, c, w = coefs.shape
    q = nf - 1
    ixy = 1 + q + c + q * (q + 1) // 2
    for a in numba.prange(h):
        cell = sums[a]
        inv = np.empty(w)
        mean_x = np.empty((q, w))
        mean_y = np.empty((c, w))
        cov = np.empty((q, q, w))
        rhs = np.empty((q, c, w))
        ones = np.ones(w)  # weight sum 1: covariances are already normalised
        for lane in range(w):
            inv[lane] = 1.0 / max(np.float64(cell[0, lane]), 1e-30)
        for i in range(q):
            for lane in range(w):
                mean_x[i, lane] = cell[1 + i, lane] * inv[lane]
        for k in range(c):
            for lane in range(w):
                mean_y[k, lane] = cell[1 + q + k, lane] * inv[lane]
        for i in range(q):
            for j in range(i + 1):  # the lower triangle: all `cholesky_ridge_solve` reads
                src = cell[pick[i, j]]
                for lane in range(w):
                    cov[i, j, lane] = src[lane] * inv[lane] - mean_x[i, lane] * mean_x[j, lane]
            for k in range(c):
                src = cell[ixy + i * c + k]
                for lane in range(w):
                    rhs[i, k, lane] = src[lane] * inv[lane] - mean_x[i, lane] * mean_y[k, lane]
        if q > 0:
            cholesky_ridge_solve(cov, rhs, q, c, ridge_relative, ridge_absolute, False, ones, w)
        for k in range(c):
            offset = coefs[a, 0, k]
            for lane in range(w):
                offset[lane] = mean_y[k, lane]
            for i in range(q):
                slope = coefs[a, 1 + i, k]
                for lane in range(w):
                    slope[lane] = rhs[i, k, lane]
                    offset[lane] -= mean_x[i, lane] * rhs[i, k, lane]


# ------------------------------------------------------------------------------------------- apply


def bilinear_taps(size: int, cells: int, scale: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For each of `size` pixels: the two cells to interpolate between and the weight of the second."""
    u = np.clip((np.arange(size, dtype=np.float64) + 0.5) / scale - 0.5, 0.0, cells - 1)
    i0 = np.floor(u).astype(np.int64)
    i1 = np.minimum(i0 + 1, cells - 1)
    return i0, i1, (u - i0).astype(np.float32)


def apply_coefficients(x: np.ndarray, coefs: np.ndarray, scale: int, albedo: np.ndarray | None = None) -> np.ndarray:
    """I = coefs[0] + x . coefs[1:] with the coefficients bilinearly upsampled from the cell grid (Fast
    Guided Filter).

    x: (Q, H, W) float32 standardised guides; coefs: (h, 1 + Q, C, w) float32 from `solve_cells`;
    albedo: (H, W, C) float32 in [0, 1], or None: I is remodulated by it (`albedo.remodulate`, fused).
    Returns (C, H, W) float32, a view of (H, W, C) memory (`from_planes` of it is free). numba kernel;
    `apply_coefficients_reference` is the plain-numpy twin.
    """
    q, height, width = x.shape
    hs, _, c, ws = coefs.shape
    ty = bilinear_taps(height, hs, scale)
    x0, x1, fx = bilinear_taps(width, ws, scale)
    out = np.empty((height, width, c), np.float32)
    factor = out if albedo is None else np.ascontiguousarray(albedo, dtype=np.float32)
    rows_per_task = rows_per_thread(height)
    # Unsigned column indices: numba skips the negative-index fix-up (LLVM still keeps gathers scalar on znver).
    _apply_kernel(x, np.ascontiguousarray(coefs, dtype=np.float32), *ty, x0.astype(np.uint32),
                  x1.astype(np.uint32), fx, rows_per_task, factor, albedo is not None, out)  # fmt: skip
    return out.transpose(2, 0, 1)


def apply_coefficients_reference(
    x: np.ndarray, coefs: np.ndarray, scale: int, albedo: np.ndarray | None = None
) -> np.ndarray:
    """Plain-numpy twin of `apply_coefficients`."""
    q, height, width = x.shape
    hs, _, c, ws = coefs.shape
    cells = coefs.transpose(0, 3, 1, 2)  # (h, w, 1 + Q, C)
    y0, y1, fy = bilinear_taps(height, hs, scale)
    x0, x1, fx = bilinear_taps(width, ws, scale)
    rows = cells[y0] * (1 - fy)[:, None, None, None] + cells[y1] * fy[:, None, None, None]  # (H, w, 1+Q, C)
    full = rows[:, x0] * (1 - fx)[None, :, None, None] + rows[:, x1] * fx[None, :, None, None]  # (H, W, 1+Q, C)
    feats = np.concatenate([np.ones((1, height, width), np.float32), x], axis=0)
    out = np.einsum("hwqc,qhw->chw", full, feats).astype(np.float32)
    return out if albedo is None else to_planes(remodulate(from_planes(out), albedo))


@numba.njit(inline="always")
def _upsample_row(coefs, a, x0, x1, fx, dst):
    """dst[f, k, x] = cell row a's coefficient (f, k) interpolated along the row at pixel column x."""
    for f in range(coefs.shape[1]):
        for k in range(coefs.shape[2]):
            src, row = coefs[a, f, k], dst[f, k]
            for xx in range(row.shape[0]):  # float32 throughout ((1 - fx) would be float64): vectorises
                lo = src[x0[xx]]
                row[xx] = lo + fx[xx] * (src[x1[xx]] - lo)


@numba.njit(parallel=True, cache=True, fastmath=True, error_model="numpy")
def _apply_kernel(x, coefs, y0, y1, fy, x0, x1, fx, rows_per_task, albedo, modulate, out):
    """out: (H, W, C). A task per `rows_per_task` pixel rows: each cell row's coefficients are upsampled
    along x once (two slots: the cell rows above and below the current pixel row), then per pixel row
    the vertical interpolation of the two, dotted with [1, x], contiguous along x; stored by
    `interleave_row` (remodulated when `modulate`)."""
    q, height, width = x.shape
    c = coefs.shape[2]
    for task in numba.prange(-(-height // rows_per_task)):
        rows = np.empty((2, 1 + q, c, width), np.float32)
        held = filled(2, -1, np.int64)  # cell row in each slot
        line = np.empty((c, width), np.float32)
        for yy in range(task * rows_per_task, min(height, task * rows_per_task + rows_per_task)):
            for a, other in ((y0[yy], y1[yy]), (y1[yy], y0[yy])):
                if held[0] != a and held[1] != a:
                    slot = 1 if held[0] == other else 0
                    _upsample_row(coefs, a, x0, x1, fx, rows[slot])
                    held[slot] = a
            s0, s1, t = 0 if held[0] == y0[yy] else 1, 0 if held[0] == y1[yy] else 1, fy[yy]
            for k in range(c):
                dst, lo, hi = line[k], rows[s0, 0, k], rows[s1, 0, k]
                for xx in range(width):
                    dst[xx] = lo[xx] + t * (hi[xx] - lo[xx])
                for i in range(q):
                    lo, hi, feat = rows[s0, 1 + i, k], rows[s1, 1 + i, k], x[i, yy]
                    for xx in range(width):
                        dst[xx] += (lo[xx] + t * (hi[xx] - lo[xx])) * feat[xx]
            interleave_row(line, albedo[yy], modulate, out[yy])
