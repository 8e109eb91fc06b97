"""Many small weighted least-squares systems (X^T W X + R) beta = X^T W Y at once, Tikhonov-regularised so
that singular systems (constant G-buffers, black frames) give finite, zero-slope solutions: `solve_ridge`
(numba, `SOLVE_LANES` systems together) and its numpy twin `solve_ridge_reference`, and
`cholesky_ridge_solve`, the in-register Cholesky solve that the regression kernels inline.
"""

from __future__ import annotations

import numba
import numpy as np

RIDGE_RELATIVE = 1e-3  # Tikhonov: fraction of each feature's own weighted second moment added to its diagonal


RIDGE_ABSOLUTE = 1e-6  # Tikhonov floor, x sum of weights: keeps features that never vary (constant G-buffer) at 0


def solve_ridge(
    gram: np.ndarray,
    rhs: np.ndarray,
    ridge_relative: float = RIDGE_RELATIVE,
    ridge_absolute: float = RIDGE_ABSOLUTE,
    weight_sum: np.ndarray | None = None,
) -> np.ndarray:
    """Solve many small symmetric systems (gram + R) beta = rhs with a Tikhonov term R.

    gram: (..., k, k) float32/64, symmetric positive semi-definite (X^T W X). rhs: (..., k, m) (X^T W Y).
    weight_sum: (...) sum of weights of each system. Default: column 0 of X is the constant, so
    weight_sum = gram[..., 0, 0] > 0, and the constant is left unregularised (a constant signal is then
    fitted exactly). R_jj = ridge_relative * gram_jj + ridge_absolute * weight_sum on the other columns
    (on all when weight_sum is given): relative to each feature's own scale, so it is the same ridge in
    any feature units, and never zero. A feature that does not vary in a window has gram_jj = 0 and
    rhs_j = 0, hence beta_j = 0. A pivot that rounding drives below the ridge floor is clamped to it.
    Returns beta: (..., k, m) float32, finite. Cholesky in float64, SOLVE_LANES systems at a time (numba, parallel);
    `solve_ridge_reference` is the plain-numpy twin.
    """
    lead, k, m = gram.shape[:-2], gram.shape[-1], rhs.shape[-1]
    count = int(np.prod(lead))
    # float32 input stays float32 (the kernel widens each value to float64 as it reads it, the same values).
    dtype = np.float32 if gram.dtype == np.float32 and rhs.dtype == np.float32 else np.float64
    flat_gram = np.ascontiguousarray(gram.reshape(count, k, k), dtype=dtype)
    flat_rhs = np.ascontiguousarray(rhs.reshape(count, k, m), dtype=dtype)
    constant = weight_sum is None
    sums = np.zeros(count) if constant else np.ascontiguousarray(np.broadcast_to(weight_sum, lead), np.float64).ravel()
    out = np.empty((count, k, m), np.float32)
    _solve_kernel(flat_gram, flat_rhs, float(ridge_relative), float(ridge_absolute), constant, sums, out)
    return out.reshape(*lead, k, m)


@numba.njit(inline="always")
def cholesky_ridge_solve(a, b, k, m, ridge_relative, ridge_absolute, constant, weight_sum, n):
    """numba-callable core of `solve_ridge`: n systems at once, the system index last so every step
    vectorises across systems. In place: a (k, k, L) float64 scratch holding X^T W X of system l in
    a[:, :, l] (only its lower triangle and diagonal are read; overwritten); b (k, m, L) float64 holding
    X^T W Y -> beta; lanes l < n <= L are solved.
    constant, weight_sum (L,) float64 (read only when not constant): see `solve_ridge`. The diagonal of
    `a` ends up holding 1 / L_jj: one division per pivot. `solve_ridge_reference` is the numpy twin."""
    scale = np.empty(n)
    for lane in range(n):
        scale[lane] = max(a[0, 0, lane] if constant else weight_sum[lane], 1e-30)
        if constant:
            a[0, 0, lane] = scale[lane]
    for j in range(1 if constant else 0, k):
        for lane in range(n):
            a[j, j, lane] += ridge_relative * max(a[j, j, lane], 0.0) + ridge_absolute * scale[lane]
    inv = np.empty(n)
    for j in range(k):
        for lane in range(n):
            inv[lane] = a[j, j, lane]
        for p in range(j):
            for lane in range(n):
                inv[lane] -= a[j, p, lane] * a[j, p, lane]
        for lane in range(n):
            inv[lane] = 1.0 / np.sqrt(max(inv[lane], ridge_absolute * scale[lane]))
            a[j, j, lane] = inv[lane]
        for i in range(j + 1, k):
            for p in range(j):
                for lane in range(n):
                    a[i, j, lane] -= a[i, p, lane] * a[j, p, lane]
            for lane in range(n):
                a[i, j, lane] *= inv[lane]
    for c in range(m):
        for i in range(k):
            for p in range(i):
                for lane in range(n):
                    b[i, c, lane] -= a[i, p, lane] * b[p, c, lane]
            for lane in range(n):
                b[i, c, lane] *= a[i, i, lane]
        for i in range(k - 1, -1, -1):
            for p in range(i + 1, k):
                for lane in range(n):
                    b[i, c, lane] -= a[p, i, lane] * b[p, c, lane]
            for lane in range(n):
                b[i, c, lane] *= a[i, i, lane]


SOLVE_LANES = 64  # systems `_solve_kernel` solves together


@numba.njit(parallel=True, cache=True, error_model="numpy")
def _solve_kernel(gram, rhs, ridge_relative, ridge_absolute, constant, sums, out):
    count, k, m = rhs.shape
    for first in numba.prange((count + SOLVE_LANES - 1) // SOLVE_LANES):
        n0 = first * SOLVE_LANES
        n = min(SOLVE_LANES, count - n0)
        a = np.empty((k, k, SOLVE_LANES))
        b = np.empty((k, m, SOLVE_LANES))
        for lane in range(n):
            for i in range(k):
                for j in range(k):
                    a[i, j, lane] = gram[n0 + lane, i, j]
                for c in range(m):
                    b[i, c, lane] = rhs[n0 + lane, i, c]
        cholesky_ridge_solve(a, b, k, m, ridge_relative, ridge_absolute, constant, sums[n0 : n0 + n], n)
        for lane in range(n):
            for i in range(k):
                for c in range(m):
                    out[n0 + lane, i, c] = b[i, c, lane]


def solve_ridge_reference(
    gram: np.ndarray,
    rhs: np.ndarray,
    ridge_relative: float = RIDGE_RELATIVE,
    ridge_absolute: float = RIDGE_ABSOLUTE,
    weight_sum: np.ndarray | None = None,
) -> np.ndarray:
    """Plain-numpy twin of `solve_ridge` (same arguments and result): Cholesky vectorised over systems."""
    a = np.moveaxis(np.asarray(gram, np.float64), (-2, -1), (0, 1)).copy()  # (k, k, ...)
    b = np.moveaxis(np.asarray(rhs, np.float64), (-2, -1), (0, 1)).copy()  # (k, m, ...)
    k = a.shape[0]
    constant = weight_sum is None
    scale = np.maximum(a[0, 0] if constant else np.asarray(weight_sum, np.float64), 1e-30)
    if constant:
        a[0, 0] = scale
    for j in range(1 if constant else 0, k):
        a[j, j] += ridge_relative * np.maximum(a[j, j], 0.0) + ridge_absolute * scale
    # Cholesky a = L L^T, L stored in the lower triangle of `a`.
    for j in range(k):
        for p in range(j):
            a[j, j] -= a[j, p] * a[j, p]
        # Rounding may eat the pivot of a near-singular system; the ridge term is its floor.
        a[j, j] = np.sqrt(np.maximum(a[j, j], ridge_absolute * scale))
        for i in range(j + 1, k):
            for p in range(j):
                a[i, j] -= a[i, p] * a[j, p]
            a[i, j] /= a[j, j]
    for i in range(k):  # forward: L z = b
        for p in range(i):
            b[i] -= a[i, p] * b[p]
        b[i] /= a[i, i]
    for i in reversed(range(k)):  # backward: L^T beta = z
        for p in range(i + 1, k):
            b[i] -= a[p, i] * b[p]
        b[i] /= a[i, i]
    return np.ascontiguousarray(np.moveaxis(b, (0, 1), (-2, -1)), dtype=np.float32)
