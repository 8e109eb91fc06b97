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
only (`local_regression.solve_ridge`). Guides are standardised per frame first, so any guide images work:
the G-buffers here, or the guides a network learns (FLNR) later, through `local_linear_regression`.
The Gaussian is truncated at the frame border and the sums are weights, not averages, so border pixels
get an exact weighted fit over the pixels that exist (no padding).
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from service.stages.bilateral import DEPTH_FLOOR
from service.stages.local_regression import (
    FIREFLY_K,
    RIDGE_RELATIVE,
    check_firefly_k,
    cholesky_ridge_solve,
    clamp_fireflies,
    clamp_outlier_clusters,
    from_planes,
    solve_ridge_reference,
    standardise,
    to_planes,
)
from service.stages.window import overlap

RIDGE_ABSOLUTE_FLR = 1e-4  # slope ridge floor, in units of a standardised guide's frame variance


@dataclass(frozen=True)
class FlrParams:
    """Options of the fast local regression."""

    scale: int = 4  # box-downsampling factor of the outer-product tensors, pixels (Salmi: "downsampling")
    sigma: float = 0.5  # std of the Gaussian blur on the low-resolution grid, in cells (x scale = pixels)
    truncate: float = 3.0  # Gaussian support radius in sigmas
    firefly_k: float | None = FIREFLY_K  # clamp outliers to k neighbour ranges beyond their neighbours; None: off
    robust_clamp: bool = True  # sigma-clipped clamp of outlier clusters (local_regression.clamp_outlier_clusters)
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
    is used); ao: (H, W, 1) float32 in [0, 1]. Returns (H, W, Q) float32, Q in 0..5 (0: a box filter).
    """
    parts = []
    if normal is not None:
        parts.append(normal)
    if depth is not None:
        parts.append(np.log(np.maximum(depth, DEPTH_FLOOR)))
    if ao is not None:
        parts.append(ao)
    if not parts:
        raise ValueError("gbuffer_guides needs at least one guide layer")
    return np.concatenate(parts, axis=-1).astype(np.float32, copy=False)


def local_linear_regression(
    radiance: np.ndarray, guides: np.ndarray, params: FlrParams | None = None, *, reference: bool = False
) -> np.ndarray:
    """FLR of `radiance` on `guides`: I_k = x_k A_k with A_k the Gaussian-weighted local fit.

    radiance: (H, W, C) float32 linear radiance (any sign; demodulated or not). guides: (H, W, Q) float32,
    any units (standardised here; Q may be 0). Returns (H, W, C) float32.
    reference: plain-numpy kernels instead of numba (slow; for tests).
    """
    params = params or FlrParams()
    y = to_planes(radiance)
    if params.firefly_k is not None:
        y = clamp_fireflies(y, params.firefly_k)
    if params.robust_clamp:  # clusters of outliers, which the 3x3 clamp cannot see
        y = clamp_outlier_clusters(y)
    x = standardise(to_planes(guides))
    sums = (cell_sums_reference if reference else cell_sums)(x, y, params.scale)
    sums = (gaussian_blur_reference if reference else gaussian_blur)(sums, params.sigma, params.truncate)
    slopes, offsets = (solve_cells_reference if reference else solve_cells)(sums, x.shape[0], y.shape[0], params)
    apply = apply_coefficients_reference if reference else apply_coefficients
    return from_planes(apply(x, slopes, offsets, params.scale))


# ------------------------------------------------------------------------------------------ moments


def moment_count(q: int, c: int) -> int:
    """Number of moment planes for Q guides and C signal channels: 1, x, y, x x^T (upper), x y^T."""
    return 1 + q + c + q * (q + 1) // 2 + q * c


def cell_sums(x: np.ndarray, y: np.ndarray, scale: int) -> np.ndarray:
    """Per low-resolution cell, the sums over its pixels of [1, x, y, x x^T (upper triangle), x y^T].

    x: (Q, H, W) float32 guides; y: (C, H, W) float32 signal. Cells are `scale` x `scale` pixels, the last
    row and column of cells partial. Returns (Hs, Ws, E) float32, E = `moment_count(Q, C)`, in the order
    of `_moment_index`. numba kernel; `cell_sums_reference` is the plain-numpy twin.
    """
    q, height, width = x.shape
    c = y.shape[0]
    hs, ws = -(-height // scale), -(-width // scale)
    out = np.zeros((hs, ws, moment_count(q, c)), np.float32)
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
    return np.ascontiguousarray(sums.transpose(1, 2, 0))


@numba.njit(parallel=True, cache=True, fastmath=True)
def _cell_sums_kernel(x, y, scale, out):
    """Per cell row: every moment's product summed over the cell row's pixel rows into a (E, W) buffer
    (contiguous along x, so it vectorises), then over each cell's `scale` columns."""
    q, height, width = x.shape
    c = y.shape[0]
    ne, ws = out.shape[2], out.shape[1]
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
    for a in numba.prange(out.shape[0]):
        acc = np.zeros((ne, width), np.float32)
        planes = np.empty((1 + q + c, width), np.float32)
        planes[0, :] = 1.0
        for yy in range(a * scale, min(height, a * scale + scale)):
            for i in range(q):
                planes[1 + i, :] = x[i, yy]
            for k in range(c):
                planes[1 + q + k, :] = y[k, yy]
            for e in range(ne):
                pa, pb, dst = planes[fa[e]], planes[fb[e]], acc[e]
                for xx in range(width):
                    dst[xx] += pa[xx] * pb[xx]
        for b in range(ws):
            for e in range(ne):
                total = np.float32(0.0)
                for xx in range(b * scale, min(width, b * scale + scale)):
                    total += acc[e, xx]
                out[a, b, e] = total


def gaussian_blur(sums: np.ndarray, sigma: float, truncate: float) -> np.ndarray:
    """Separable Gaussian blur of cell sums, truncated at the border (no padding, no renormalisation).

    sums: (h, w, E) float32. Returns (h, w, E) float32; the taps are exp(-d^2 / 2 sigma^2), d in cells,
    |d| <= ceil(truncate sigma), centre tap 1: the result is a weighted sum, not an average, so the
    ratios the solver forms are exact weighted least squares near the border too. numba kernel;
    `gaussian_blur_reference` is the plain-numpy twin.
    """
    taps = _gaussian_taps(sigma, truncate)
    rows = np.empty_like(sums, dtype=np.float32)
    _blur_rows_kernel(np.ascontiguousarray(sums, dtype=np.float32), taps, rows)
    cols = np.ascontiguousarray(rows.transpose(1, 0, 2))
    out = np.empty_like(cols)
    _blur_rows_kernel(cols, taps, out)
    return np.ascontiguousarray(out.transpose(1, 0, 2))


def gaussian_blur_reference(sums: np.ndarray, sigma: float, truncate: float) -> np.ndarray:
    """Plain-numpy twin of `gaussian_blur`."""
    taps = _gaussian_taps(sigma, truncate)
    height, width = sums.shape[:2]
    out = sums
    for axis in (0, 1):
        src, out = out, out.copy()
        for d in range(1, len(taps)):
            for sign in (-1, 1):
                pair = overlap(height, width, sign * d if axis == 0 else 0, sign * d if axis == 1 else 0)
                if pair is not None:
                    (cy, cx), (ny, nx) = pair
                    out[cy, cx] += taps[d] * src[ny, nx]
    return out


def _gaussian_taps(sigma: float, truncate: float) -> np.ndarray:
    """Taps 0..R of the Gaussian, R = ceil(truncate sigma), tap 0 = 1. (R+1,) float32."""
    d = np.arange(int(np.ceil(truncate * sigma)) + 1, dtype=np.float64)
    return np.exp(-0.5 * (d / sigma) ** 2).astype(np.float32)


@numba.njit(cache=True, fastmath=True)
def _blur_rows_kernel(src, taps, out):
    """Blur along axis 0 of (h, w, E): out[y] = sum over |d| <= R of taps[|d|] src[y + d], inside only."""
    height = src.shape[0]
    radius = taps.shape[0] - 1
    for y in range(height):
        row = out[y]
        row[:, :] = src[y]
        for d in range(1, radius + 1):
            t = taps[d]
            if y - d >= 0:
                other = src[y - d]
                for i in range(row.shape[0]):
                    for e in range(row.shape[1]):
                        row[i, e] += t * other[i, e]
            if y + d < height:
                other = src[y + d]
                for i in range(row.shape[0]):
                    for e in range(row.shape[1]):
                        row[i, e] += t * other[i, e]


def _moment_index(q: int, c: int) -> tuple[int, int, dict[tuple[int, int], int], int]:
    """(index of sum x, of sum y, {(i, j): index of sum x_i x_j}, index of first sum x y); sum 1 is at 0."""
    xx, e = {}, 1 + q + c
    for i in range(q):
        for j in range(i, q):
            xx[(i, j)] = xx[(j, i)] = e
            e += 1
    return 1, 1 + q, xx, e


def solve_cells(sums: np.ndarray, q: int, c: int, params: FlrParams) -> tuple[np.ndarray, np.ndarray]:
    """Slopes and offsets of every cell's weighted least-squares fit, from its blurred sums.

    sums: (h, w, E) float32 from `gaussian_blur(cell_sums(...))`. Returns slopes (h, w, Q, C) and
    offsets (h, w, C), float32: fit(x) = offsets + x . slopes. One fused numba kernel (covariances, ridge
    Cholesky, offsets); `solve_cells_reference` is the plain-numpy twin.
    """
    h, w = sums.shape[:2]
    ixx = _moment_index(q, c)[2]
    pick = np.array([[ixx[(i, j)] for j in range(q)] for i in range(q)], np.int64).reshape(q, q)
    slopes = np.empty((h, w, q, c), np.float32)
    offsets = np.empty((h, w, c), np.float32)
    _solve_cells_kernel(np.ascontiguousarray(sums, dtype=np.float32), pick, float(params.ridge_relative),
                        float(params.ridge_absolute), slopes, offsets)  # fmt: skip
    return slopes, offsets


def solve_cells_reference(sums: np.ndarray, q: int, c: int, params: FlrParams) -> tuple[np.ndarray, np.ndarray]:
    """Plain-numpy twin of `solve_cells` (float64 covariances, `solve_ridge_reference`)."""
    ix, iy, ixx, ixy = _moment_index(q, c)
    sums = np.asarray(sums, np.float64)
    s0 = np.maximum(sums[..., 0], 1e-30)[..., None]
    mean_x, mean_y = sums[..., ix : ix + q] / s0, sums[..., iy : iy + c] / s0
    pick = np.array([[ixx[(i, j)] for j in range(q)] for i in range(q)], np.int64).reshape(q, q)
    cov_xx = sums[..., pick] / s0[..., None] - mean_x[..., :, None] * mean_x[..., None, :]
    sum_xy = sums[..., ixy : ixy + q * c].reshape(*sums.shape[:2], q, c)
    cov_xy = sum_xy / s0[..., None] - mean_x[..., :, None] * mean_y[..., None, :]
    if q == 0:
        return np.zeros((*sums.shape[:2], 0, c), np.float32), mean_y.astype(np.float32)
    slopes = solve_ridge_reference(cov_xx, cov_xy, params.ridge_relative, params.ridge_absolute,
                                   weight_sum=np.ones(sums.shape[:2]))  # fmt: skip
    offsets = mean_y - np.einsum("hwq,hwqc->hwc", mean_x, slopes.astype(np.float64))
    return slopes, offsets.astype(np.float32)


@numba.njit(parallel=True, cache=True)
def _solve_cells_kernel(sums, pick, ridge_relative, ridge_absolute, slopes, offsets):
    """Per cell, in float64: weighted means and covariances from its sums (order of `_moment_index`),
    cov(x, x) a = cov(x, y) with the slope ridge (`cholesky_ridge_solve`, weight sum 1), b = mean(y) - a . mean(x)."""
    h, w, q, c = slopes.shape
    ixy = 1 + q + c + q * (q + 1) // 2
    for a in numba.prange(h):
        mean_x = np.empty(q)
        mean_y = np.empty(c)
        cov = np.empty((q, q))
        rhs = np.empty((q, c))
        for b in range(w):
            cell = sums[a, b]
            s0 = max(np.float64(cell[0]), 1e-30)
            for i in range(q):
                mean_x[i] = cell[1 + i] / s0
            for k in range(c):
                mean_y[k] = cell[1 + q + k] / s0
            for i in range(q):
                for j in range(q):
                    cov[i, j] = cell[pick[i, j]] / s0 - mean_x[i] * mean_x[j]
                for k in range(c):
                    rhs[i, k] = cell[ixy + i * c + k] / s0 - mean_x[i] * mean_y[k]
            if q > 0:
                cholesky_ridge_solve(cov, rhs, q, c, ridge_relative, ridge_absolute, False, 1.0)
            for k in range(c):
                off = mean_y[k]
                for i in range(q):
                    slopes[a, b, i, k] = rhs[i, k]
                    off -= mean_x[i] * rhs[i, k]
                offsets[a, b, k] = off


# ------------------------------------------------------------------------------------------- apply


def _bilinear_taps(size: int, cells: int, scale: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For each of `size` pixels: the two cells to interpolate between and the weight of the second."""
    u = np.clip((np.arange(size, dtype=np.float64) + 0.5) / scale - 0.5, 0.0, cells - 1)
    i0 = np.floor(u).astype(np.int64)
    i1 = np.minimum(i0 + 1, cells - 1)
    return i0, i1, (u - i0).astype(np.float32)


def apply_coefficients(x: np.ndarray, slopes: np.ndarray, offsets: np.ndarray, scale: int) -> np.ndarray:
    """I = b + x . A with A, b bilinearly upsampled from the cell grid (Fast Guided Filter).

    x: (Q, H, W) float32 standardised guides; slopes: (h, w, Q, C); offsets: (h, w, C) float32.
    Returns (C, H, W) float32. numba kernel; `apply_coefficients_reference` is the plain-numpy twin.
    """
    q, height, width = x.shape
    hs, ws, c = offsets.shape
    coefs = np.ascontiguousarray(np.concatenate([offsets[:, :, None, :], slopes], axis=2), dtype=np.float32)
    ty = _bilinear_taps(height, hs, scale)
    x0, x1, fx = _bilinear_taps(width, ws, scale)
    # (C, H, W) view of (H, W, C) memory: `from_planes` of the result is then free.
    out = np.empty((height, width, c), np.float32).transpose(2, 0, 1)
    # Unsigned column indices: numba skips the negative-index fix-up, so the row loops vectorise (gathers).
    _apply_kernel(x, coefs, *ty, x0.astype(np.uint32), x1.astype(np.uint32), fx, out)
    return out


def apply_coefficients_reference(x: np.ndarray, slopes: np.ndarray, offsets: np.ndarray, scale: int) -> np.ndarray:
    """Plain-numpy twin of `apply_coefficients`."""
    q, height, width = x.shape
    hs, ws, c = offsets.shape
    coefs = np.concatenate([offsets[:, :, None, :], slopes], axis=2)  # (h, w, 1+Q, C)
    y0, y1, fy = _bilinear_taps(height, hs, scale)
    x0, x1, fx = _bilinear_taps(width, ws, scale)
    rows = coefs[y0] * (1 - fy)[:, None, None, None] + coefs[y1] * fy[:, None, None, None]  # (H, w, 1+Q, C)
    full = rows[:, x0] * (1 - fx)[None, :, None, None] + rows[:, x1] * fx[None, :, None, None]  # (H, W, 1+Q, C)
    feats = np.concatenate([np.ones((1, height, width), np.float32), x], axis=0)
    return np.einsum("hwqc,qhw->chw", full, feats).astype(np.float32)


@numba.njit(parallel=True, cache=True, fastmath=True)
def _apply_kernel(x, coefs, y0, y1, fy, x0, x1, fx, out):
    q, height, width = x.shape
    ws, nf, c = coefs.shape[1], coefs.shape[2], coefs.shape[3]
    for yy in numba.prange(height):
        # Coefficients of this row, interpolated vertically once per cell column: (nf, c, ws).
        a0, a1, ty = y0[yy], y1[yy], fy[yy]
        row = np.empty((nf, c, ws), np.float32)
        for b in range(ws):
            for f in range(nf):
                for k in range(c):
                    row[f, k, b] = (1 - ty) * coefs[a0, b, f, k] + ty * coefs[a1, b, f, k]
        for k in range(c):  # then along the row, one feature plane at a time (contiguous in x)
            dst, r = out[k, yy], row[0, k]
            for xx in range(width):
                dst[xx] = (1 - fx[xx]) * r[x0[xx]] + fx[xx] * r[x1[xx]]
            for i in range(q):
                r, feat = row[1 + i, k], x[i, yy]
                for xx in range(width):
                    dst[xx] += ((1 - fx[xx]) * r[x0[xx]] + fx[xx] * r[x1[xx]]) * feat[xx]
