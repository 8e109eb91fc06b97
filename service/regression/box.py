"""Box regression: `block_regression` for flat pair weights (FLR, BMFR), from float64 box sums of the
features' products shared between neighbouring centres instead of one weighted sum per centre and pair.
`box_regression(..., reference=True)` is the block regression it equals.
"""

from __future__ import annotations

import numba
import numpy as np

from service.kernels.parallel import rows_per_thread
from service.regression.block import block_regression
from service.regression.planes import from_planes, interleave_row, to_planes
from service.regression.solve import cholesky_ridge_solve
from service.regression.terms import BlockParams, centre_count, plain_terms
from service.stages.albedo import remodulate


def box_regression(
    features: np.ndarray,
    target: np.ndarray,
    params: BlockParams,
    *,
    albedo: np.ndarray | None = None,
    reference: bool = False,
) -> np.ndarray:
    """`block_regression(plain_terms(features), target, params)` for flat weights, from box sums.

    With flat weights (no weight guide, no scaled features, `params.sigma_position` None) every moment of
    Choi eq. 4 is a polynomial in the centre's features and the window's raw sums of [1, x, y] products:
    gram_pq = M_pq - z_p M_0q - z_q M_0p + z_p z_q M_00, rhs_pm = R_pm - z_p R_0m (z: the centre's
    features, z_0 = 0). Those sums are taken in float64, so the expansion loses nothing to cancellation,
    and shared between centres: the window's 2r+1 rows are nb = (2r+1) // s bands of s rows plus the
    first (2r+1) mod s rows of the next band, and a band serves nb consecutive centre rows, so every
    pixel's products are summed once; columns likewise, each frame row split into its s phases (columns
    j s + t) so that a column band's sum is a sum of contiguous vectors. The systems of up to BOX_TILE
    centres are solved at a time (`cholesky_ridge_solve`), and eq. 5 becomes a box sum of the centres' coefficients:
    out_i = mean over c of (alpha_c - beta_c . z_c) + x_i . mean of beta_c. The constant pair weight
    (1 + WEIGHT_FLOOR) cancels in both.

    features: (K, H, W) float32 shared features (standardised); target: (C, H, W) float32 planes;
    albedo: (H, W, C) float32 in [0, 1], or None: the output is remodulated by it (`albedo.remodulate`,
    fused into the last pass) when the target was demodulated. Returns (C, H, W) float32, a view of
    (H, W, C) memory (`from_planes` of it is free). reference: the plain-numpy pair-by-pair path
    (`block_regression`, then `remodulate`).
    """
    if params.sigma_position is not None:
        raise ValueError("box_regression needs flat weights (sigma_position None)")
    if reference:
        out = block_regression(plain_terms(features), target, params, reference=True)
        return out if albedo is None else to_planes(remodulate(from_planes(out), albedo))
    features = np.ascontiguousarray(features, dtype=np.float32)
    target = np.ascontiguousarray(target, dtype=np.float32)
    k, height, width = features.shape
    s = params.sparsity
    centre_rows = centre_count(height, s)
    coefs = np.empty((centre_rows, centre_count(width, s), target.shape[0], 1 + k))
    rows_per_task = rows_per_thread(centre_rows)
    _box_solve_kernel(features, target, params.radius, s, float(params.ridge_relative),
                      float(params.ridge_absolute), rows_per_task, coefs)  # fmt: skip
    out = np.empty((height, width, target.shape[0]), np.float32)
    factor = out if albedo is None else np.ascontiguousarray(albedo, dtype=np.float32)
    _box_reconstruct_kernel(features, coefs, params.radius, s, factor, albedo is not None, out)
    return out.transpose(2, 0, 1)


BOX_TILE = 216  # centre columns per task of `_box_solve_kernel` (1296 pixels at sparsity 6): a 720p row


@numba.njit(inline="always")
def _band_rows(x, y, r0, nr, col0, u0, u1, s, nx, rows):
    """rows[f, r, t nx + j] = plane f of [1, x, y] at frame row r0 + r, column col0 + j s + t, for the
    columns u = j s + t in [u0, u1) inside the frame (the others stay 0); planes 1.. only."""
    k, c = x.shape[0], y.shape[0]
    for r in range(nr):
        for f in range(1, 1 + k + c):
            src = x[f - 1, r0 + r] if f <= k else y[f - 1 - k, r0 + r]
            for t in range(s):
                j0, j1 = (max(u0 - t, 0) + s - 1) // s, (max(u1 - t, 0) + s - 1) // s
                dst, phase = rows[f, r, t * nx + j0 : t * nx + j1], src[col0 + t + j0 * s :]
                for j in range(j1 - j0):
                    dst[j] = phase[j * s]


@numba.njit(inline="always")
def _band_sums(rows, nr, s, part, nx, fa, fb, acc):
    """acc[h, e, j] = sum over rows r < nr and the phases t of column band j (h = 0: t < part, 1: the
    others) of rows[fa[e], r, t nx + j] rows[fb[e], r, t nx + j], float64. Two rows per pass over acc."""
    acc[:, :, :] = 0.0
    for e in range(fa.shape[0]):
        pa, pb = rows[fa[e]], rows[fb[e]]
        for t in range(s):
            dst, lo = acc[0 if t < part else 1, e], t * nx
            r = 0
            while r + 1 < nr:
                a0, b0 = pa[r, lo : lo + nx], pb[r, lo : lo + nx]
                a1, b1 = pa[r + 1, lo : lo + nx], pb[r + 1, lo : lo + nx]
                for j in range(nx):
                    dst[j] += np.float64(a0[j]) * np.float64(b0[j]) + np.float64(a1[j]) * np.float64(b1[j])
                r += 2
            if r < nr:
                a0, b0 = pa[r, lo : lo + nx], pb[r, lo : lo + nx]
                for j in range(nx):
                    dst[j] += np.float64(a0[j]) * np.float64(b0[j])


@numba.njit(inline="always")
def _add_into(dst, src):
    """dst += src, (2, E, n) float64 arrays."""
    for h in range(dst.shape[0]):
        for e in range(dst.shape[1]):
            d, v = dst[h, e], src[h, e]
            for j in range(d.shape[0]):
                d[j] += v[j]


@numba.njit(inline="always")
def _window_sums(head, full, a, nb, nl, win, sums):
    """sums[e, l] = window sum of product e for centre l of centre row a: rows of the full bands
    a .. a+nb-1 (ring `full`) and the head of band a+nb (`head`), columns likewise (h index of `_band_sums`)."""
    ring = nb + 1
    for e in range(sums.shape[0]):
        for h in range(2):
            dst, src = win[h, e], head[(a + nb) % ring, h, e]
            dst[:] = src
            for t in range(nb):
                src = full[(a + t) % ring, h, e]
                for j in range(dst.shape[0]):
                    dst[j] += src[j]
        dst, head_columns = sums[e], win[0, e, nb:]
        for lane in range(nl):
            dst[lane] = head_columns[lane]
        for t in range(nb):  # views, indexed from 0: no negative-index fix-up, so the loops vectorise
            lo, hi = win[0, e, t:], win[1, e, t:]
            for lane in range(nl):
                dst[lane] += lo[lane] + hi[lane]


@numba.njit(inline="always")
def _centre_systems(sums, z, index, nl, gram, rhs):
    """gram[q, p, l] (q >= p), rhs[p, m, l] of centre l from its raw window sums and features z[:, l] (z[0] = 0)."""
    k1, c = gram.shape[0], rhs.shape[1]
    s00 = sums[0]
    for p in range(k1):
        zp, s0p = z[p], sums[index[0, p]]
        for q in range(p, k1):
            spq, s0q, zq = sums[index[p, q]], sums[index[0, q]], z[q]
            for lane in range(nl):
                v = spq[lane] - zp[lane] * s0q[lane] - zq[lane] * s0p[lane] + zp[lane] * zq[lane] * s00[lane]
                gram[q, p, lane] = v  # the lower triangle: all `cholesky_ridge_solve` reads
        for m in range(c):
            spm, s0m = sums[index[p, k1 + m]], sums[index[0, k1 + m]]
            for lane in range(nl):
                rhs[p, m, lane] = spm[lane] - zp[lane] * s0m[lane]


@numba.njit(parallel=True, cache=True, fastmath=True, error_model="numpy")
def _box_solve_kernel(x, y, radius, sparsity, ridge_relative, ridge_absolute, rows_per_task, coefs):
    """coefs[a, b, m] = [alpha_m - beta_m . z, beta_m (K)] of centre (a s, b s), float64. A task per
    `rows_per_task` centre rows x BOX_TILE centre columns; band j (frame rows j s - r ..) is summed in two
    parts, its first (2r+1) mod s rows (`head`) and all of it (`full`), into rings of nb + 1 bands."""
    k, height, width = x.shape
    c = y.shape[0]
    hc, wc = coefs.shape[0], coefs.shape[1]
    k1, n1 = 1 + k, 1 + k + c  # planes [1, x, y]; sums of every product but y y
    ne = k1 * n1 - k * k1 // 2
    fa = np.empty(ne, np.int64)
    fb = np.empty(ne, np.int64)
    index = np.empty((k1, n1), np.int64)  # np.full would be a parallel region of its own
    e = 0
    for p in range(k1):
        for q in range(p, n1):
            fa[e], fb[e], index[p, q] = p, q, e
            e += 1
    s, r = sparsity, radius
    nb = (2 * r + 1) // s
    part = 2 * r + 1 - nb * s
    row_tasks, col_tasks = -(-hc // rows_per_task), -(-wc // BOX_TILE)
    for task in numba.prange(row_tasks * col_tasks):
        a0 = (task // col_tasks) * rows_per_task
        a1 = min(hc, a0 + rows_per_task)
        b0 = (task % col_tasks) * BOX_TILE
        nl = min(wc, b0 + BOX_TILE) - b0  # centres of the tile: the lanes of the solve
        nx = nl + nb  # column bands
        col0 = b0 * s - r  # frame column of u = 0
        u0, u1 = max(0, -col0), min(nx * s, width - col0)  # columns inside the frame
        rows = np.zeros((n1, s, nx * s), np.float32)
        for t in range(s):  # the constant plane: 1 inside the frame, 0 outside
            for j in range(nx):
                rows[0, :, t * nx + j] = 1.0 if u0 <= j * s + t < u1 else 0.0
        head = np.empty((nb + 1, 2, ne, nx))
        full = np.empty((nb + 1, 2, ne, nx))
        win = np.empty((2, ne, nx))
        sums = np.empty((ne, nl))
        z = np.zeros((k1, nl))
        unused = np.empty(0)  # weight sums: the constant column holds them
        gram = np.empty((k1, k1, nl))
        rhs = np.empty((k1, c, nl))
        for j in range(a0, a1 + nb):
            ring, first = j % (nb + 1), j * s - r
            r0, r1 = max(0, first), min(height, first + part)
            _band_rows(x, y, r0, max(0, r1 - r0), col0, u0, u1, s, nx, rows)
            _band_sums(rows, max(0, r1 - r0), s, part, nx, fa, fb, head[ring])
            if j < a1 + nb - 1:  # the last band's head only is used
                r0, r1 = max(0, first + part), min(height, first + s)
                _band_rows(x, y, r0, max(0, r1 - r0), col0, u0, u1, s, nx, rows)
                _band_sums(rows, max(0, r1 - r0), s, part, nx, fa, fb, full[ring])
                _add_into(full[ring], head[ring])
            a = j - nb
            if a < a0:
                continue
            _window_sums(head, full, a, nb, nl, win, sums)
            for i in range(k):
                src = x[i, a * s]
                for lane in range(nl):
                    z[1 + i, lane] = src[(b0 + lane) * s]
            _centre_systems(sums, z, index, nl, gram, rhs)
            cholesky_ridge_solve(gram, rhs, k1, c, ridge_relative, ridge_absolute, True, unused, nl)
            for m in range(c):
                for lane in range(nl):
                    gamma = rhs[0, m, lane]
                    for p in range(1, k1):
                        gamma -= rhs[p, m, lane] * z[p, lane]
                        coefs[a, b0 + lane, m, p] = rhs[p, m, lane]
                    coefs[a, b0 + lane, m, 0] = gamma


@numba.njit(cache=True, error_model="numpy")
def _centre_runs(size, count, radius, sparsity):
    """Along an axis of `size` pixels with `count` centres: the centres [lo, hi) whose window holds each
    pixel, grouped into runs of pixels with the same range. Returns (run of each pixel (size,) uint32,
    lo (n,), hi (n,) int64, first pixel of each run and `size` (n + 1,) int64)."""
    run = np.empty(size, np.uint32)
    lo = np.empty(size, np.int64)
    hi = np.empty(size, np.int64)
    start = np.empty(size + 1, np.int64)
    n = -1
    for i in range(size):
        first, stop = max(0, -((radius - i) // sparsity)), min(count - 1, (i + radius) // sparsity) + 1
        if n < 0 or first != lo[n] or stop != hi[n]:
            n += 1
            lo[n], hi[n], start[n] = first, stop, i
        run[i] = n
    start[n + 1] = size
    return run, lo[: n + 1], hi[: n + 1], start[: n + 2]


@numba.njit(parallel=True, cache=True, fastmath=True, error_model="numpy")
def _box_reconstruct_kernel(x, coefs, radius, sparsity, albedo, modulate, out):
    """out[y, x, m] (H, W, C) = mean over the centres whose window holds the pixel of gamma_m + beta_m . x
    (times the albedo factor when `modulate`: `interleave_row`). The centres' mean coefficients are
    constant over runs of rows and columns (`_centre_runs`): first, per centre row, the mean over each
    column run's centres; then a task per row run averages those over its centre rows, spreads them over
    the pixels and evaluates its rows."""
    k, height, width = x.shape
    hc, wc, c, k1 = coefs.shape
    nq = c * k1
    flat = coefs.reshape(hc, wc, nq)
    col_run, col_lo, col_hi, _ = _centre_runs(width, wc, radius, sparsity)
    _, row_lo, row_hi, row_start = _centre_runs(height, hc, radius, sparsity)
    runs = col_lo.shape[0]
    run_means = np.empty((hc, nq, runs), np.float32)  # per centre row: mean coefficients of each column run
    for a in numba.prange(hc):
        total = np.empty(nq)
        for j in range(runs):
            total[:] = 0.0
            for b in range(col_lo[j], col_hi[j]):
                src = flat[a, b]
                for q in range(nq):
                    total[q] += src[q]
            scale = 1.0 / (col_hi[j] - col_lo[j])
            for q in range(nq):
                run_means[a, q, j] = total[q] * scale
    for g in numba.prange(row_lo.shape[0]):
        means = np.zeros((nq, runs), np.float32)  # over the row run's centre rows
        for a in range(row_lo[g], row_hi[g]):
            src, dst = run_means[a].reshape(nq * runs), means.reshape(nq * runs)
            for i in range(nq * runs):
                dst[i] += src[i]
        coef = np.empty((nq, width), np.float32)
        scale = np.float32(1.0 / (row_hi[g] - row_lo[g]))
        for q in range(nq):
            src, dst = means[q], coef[q]
            for xx in range(width):  # a gather (scalar on znver): once per row run, not per row
                dst[xx] = src[col_run[xx]] * scale
        row = np.empty((c, width), np.float32)
        for yy in range(row_start[g], row_start[g + 1]):
            for m in range(c):  # contiguous along x: vectorises; three features per pass over the row
                dst, base = row[m], m * k1
                dst[:] = coef[base]
                for p in range(1, k1, 3):
                    if p + 2 < k1:
                        c0, c1, c2 = coef[base + p], coef[base + p + 1], coef[base + p + 2]
                        x0, x1, x2 = x[p - 1, yy], x[p, yy], x[p + 1, yy]
                        for xx in range(width):
                            dst[xx] += c0[xx] * x0[xx] + c1[xx] * x1[xx] + c2[xx] * x2[xx]
                    else:
                        for f in range(p, k1):
                            cf, xf = coef[base + f], x[f - 1, yy]
                            for xx in range(width):
                                dst[xx] += cf[xx] * xf[xx]
            interleave_row(row, albedo[yy], modulate, out[yy])
