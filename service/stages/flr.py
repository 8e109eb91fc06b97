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
    clamp_fireflies,
    from_planes,
    solve_ridge,
    standardise,
    to_planes,
)
from service.stages.window import overlap

RIDGE_ABSOLUTE_FLR = 1e-4  # slope ridge floor, in units of a standardised guide's frame variance


@dataclass(frozen=True)
class FlrParams:
    """Options of the fast local regression."""

    scale: int = 2  # box-downsampling factor of the outer-product tensors, pixels (Salmi: "downsampling")
    sigma: float = 1.0  # std of the Gaussian blur on the low-resolution grid, in cells (x scale = pixels)
    truncate: float = 3.0  # Gaussian support radius in sigmas
    firefly_k: float | None = FIREFLY_K  # clamp outliers to k neighbour ranges beyond their neighbours; None: off
    ridge_relative: float = RIDGE_RELATIVE  # Tikhonov on the slopes, relative to each guide's local variance
    ridge_absolute: float = RIDGE_ABSOLUTE_FLR  # Tikhonov floor on the slopes (standardised guide units)

    def __post_init__(self) -> None:
        if self.scale < 1:
            raise ValueError(f"scale must be >= 1, got {self.scale}")
        if not (self.sigma > 0 and self.truncate > 0):
            raise ValueError("sigma and truncate must be > 0")
        if not (self.ridge_relative >= 0 and self.ridge_absolute > 0):
            raise ValueError("ridge_relative must be >= 0 and ridge_absolute > 0")
        if self.firefly_k is not None and not self.firefly_k > 0:
            raise ValueError(f"firefly_k must be > 0 or None, got {self.firefly_k}")

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
    return np.concatenate(parts, axis=-1).astype(np.float32)


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
    x = standardise(to_planes(guides))
    sums = (cell_sums_reference if reference else cell_sums)(x, y, params.scale)
    sums = gaussian_blur(sums, params.sigma, params.truncate)
    slopes, offsets = solve_cells(sums, x.shape[0], y.shape[0], params)
    apply = apply_coefficients_reference if reference else apply_coefficients
    return from_planes(apply(x, slopes, offsets, params.scale))


# ------------------------------------------------------------------------------------------ moments


def moment_count(q: int, c: int) -> int:
    """Number of moment planes for Q guides and C signal channels: 1, x, y, x x^T (upper), x y^T."""
    return 1 + q + c + q * (q + 1) // 2 + q * c


def cell_sums(x: np.ndarray, y: np.ndarray, scale: int) -> np.ndarray:
    """Per low-resolution cell, the sums over its pixels of [1, x, y, x x^T (upper triangle), x y^T].

    x: (Q, H, W) float32 guides; y: (C, H, W) float32 signal. Cells are `scale` x `scale` pixels, the last
    row and column of cells partial. Returns (E, Hs, Ws) float32, E = `moment_count(Q, C)`, in the order
    of `_moment_index`. numba kernel; `cell_sums_reference` is the plain-numpy twin.
    """
    q, height, width = x.shape
    c = y.shape[0]
    hs, ws = -(-height // scale), -(-width // scale)
    out = np.zeros((moment_count(q, c), hs, ws), np.float32)
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
    return padded.reshape(full.shape[0], hs, scale, ws, scale).sum(axis=(2, 4), dtype=np.float32)


@numba.njit(parallel=True, cache=True, fastmath=True)
def _cell_sums_kernel(x, y, scale, out):
    q, height, width = x.shape
    c = y.shape[0]
    hs, ws = out.shape[1], out.shape[2]
    for a in numba.prange(hs):
        for yy in range(a * scale, min(height, a * scale + scale)):
            for b in range(ws):
                for xx in range(b * scale, min(width, b * scale + scale)):
                    out[0, a, b] += 1.0
                    e = 1
                    for i in range(q):
                        out[e + i, a, b] += x[i, yy, xx]
                    e += q
                    for k in range(c):
                        out[e + k, a, b] += y[k, yy, xx]
                    e += c
                    for i in range(q):
                        xi = x[i, yy, xx]
                        for j in range(i, q):
                            out[e, a, b] += xi * x[j, yy, xx]
                            e += 1
                    for i in range(q):
                        xi = x[i, yy, xx]
                        for k in range(c):
                            out[e, a, b] += xi * y[k, yy, xx]
                            e += 1


def gaussian_blur(planes: np.ndarray, sigma: float, truncate: float) -> np.ndarray:
    """Separable Gaussian blur of sums, truncated at the border (no padding, no renormalisation).

    planes: (E, h, w) float32 sums. Returns (E, h, w) float32; the taps are exp(-d^2 / 2 sigma^2), d in
    cells, |d| <= ceil(truncate sigma), centre tap 1: the result is a weighted sum, not an average, so
    the ratios the solver forms are exact weighted least squares near the border too.
    """
    radius = int(np.ceil(truncate * sigma))
    _, height, width = planes.shape
    out = planes
    for axis in (1, 2):
        src, out = out, out.copy()
        for d in range(1, radius + 1):
            tap = np.float32(np.exp(-0.5 * (d / sigma) ** 2))
            for sign in (-1, 1):
                pair = overlap(height, width, sign * d if axis == 1 else 0, sign * d if axis == 2 else 0)
                if pair is None:
                    continue
                (cy, cx), (ny, nx) = pair
                out[:, cy, cx] += tap * src[:, ny, nx]
    return out


def _moment_index(q: int, c: int) -> tuple[int, int, int, dict[tuple[int, int], int], int]:
    """(index of sum x, of sum y, -, {(i, j): index of sum x_i x_j}, index of first sum x y)."""
    xx, e = {}, 1 + q + c
    for i in range(q):
        for j in range(i, q):
            xx[(i, j)] = xx[(j, i)] = e
            e += 1
    return 1, 1 + q, 0, xx, e


def solve_cells(sums: np.ndarray, q: int, c: int, params: FlrParams) -> tuple[np.ndarray, np.ndarray]:
    """Slopes and offsets of every cell's weighted least-squares fit, from its blurred sums.

    sums: (E, h, w) float32 from `gaussian_blur(cell_sums(...))`. Returns slopes (h, w, Q, C) and
    offsets (h, w, C), float32: fit(x) = offsets + x . slopes.
    """
    ix, iy, _, ixx, ixy = _moment_index(q, c)
    s0 = np.maximum(sums[0].astype(np.float64), 1e-30)
    mx = sums[ix : ix + q] / s0  # (Q, h, w)
    my = sums[iy : iy + c] / s0  # (C, h, w)
    if q == 0:
        h, w = s0.shape
        return np.zeros((h, w, 0, c), np.float32), np.ascontiguousarray(np.moveaxis(my, 0, -1), dtype=np.float32)
    cov_xx = np.empty((*s0.shape, q, q))
    for i in range(q):
        for j in range(q):
            cov_xx[..., i, j] = sums[ixx[(i, j)]] / s0 - mx[i] * mx[j]
    cov_xy = (sums[ixy : ixy + q * c].reshape(q, c, *s0.shape) / s0 - mx[:, None] * my[None]).transpose(2, 3, 0, 1)
    slopes = solve_ridge(cov_xx, cov_xy, params.ridge_relative, params.ridge_absolute, weight_sum=np.ones(s0.shape))
    offsets = np.moveaxis(my, 0, -1) - np.einsum("qhw,hwqc->hwc", mx, slopes)
    return slopes, np.ascontiguousarray(offsets, dtype=np.float32)


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
    tx = _bilinear_taps(width, ws, scale)
    out = np.empty((c, height, width), np.float32)
    _apply_kernel(x, coefs, *ty, *tx, out)
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
    c = out.shape[0]
    for yy in numba.prange(height):
        a0, a1, ty = y0[yy], y1[yy], fy[yy]
        for xx in range(width):
            b0, b1, tx = x0[xx], x1[xx], fx[xx]
            w00, w01 = (1 - ty) * (1 - tx), (1 - ty) * tx
            w10, w11 = ty * (1 - tx), ty * tx
            for k in range(c):
                acc = w00 * coefs[a0, b0, 0, k] + w01 * coefs[a0, b1, 0, k]
                acc += w10 * coefs[a1, b0, 0, k] + w11 * coefs[a1, b1, 0, k]
                for i in range(q):
                    coef = w00 * coefs[a0, b0, 1 + i, k] + w01 * coefs[a0, b1, 1 + i, k]
                    coef += w10 * coefs[a1, b0, 1 + i, k] + w11 * coefs[a1, b1, 1 + i, k]
                    acc += coef * x[i, yy, xx]
                out[k, yy, xx] = acc
