"""Weighted local linear regression: the one solver behind cross-regression, BMFR and FLR.

Three pieces, each a pure function on arrays:

- `solve_ridge`: many small normal equations (X^T W X + R) beta = X^T W Y at once, Tikhonov-regularised
  so that singular systems (constant G-buffers, black frames) give finite, zero-slope solutions.
- `block_regression` (= `block_solve` -> `block_reconstruct`): block-wise regression
  of Choi et al. 2024 (sec. 3, eqs. 3-5, after Koskela et al. 2019 and Moon et al. 2015). Normal equations
  are solved only at centre pixels on every `sparsity`-th row and column; each centre fits a linear
  function of pair features x_i - x_c over its (2r+1)^2 window, and every pixel averages the predictions
  of the centres whose window holds it (eq. 5). Pair weights have the form of Choi eq. 7.
- `clamp_fireflies`: clips each value to the range of its 8 neighbours widened by k times that range,
  before any regression, so a single 1e6 sample cannot leak through a whole window of fits (our
  addition, not in the papers).

Layout: the solver works on channel-first planes, (K, H, W) float32, so the numba kernels stream along x.
Every fast numba kernel has a plain-numpy `*_reference` twin with the same signature; tests hold them
together. Windows are clipped at the frame border (no padding), as in `service.stages.window`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from service.stages.albedo import albedo_factor, demodulate, remodulate
from service.stages.fill import filled
from service.stages.parallel import rows_per_thread
from service.stages.simd import (
    EXP_NEG_LIMIT,
    LANES,
    LN2,
    LOG2E,
    bits_to_float32,
    exp_poly,
    float32_to_bits,
    load,
    phase_blocks,
    store_phases,
)
from service.stages.window import overlap, window_offsets

RIDGE_RELATIVE = 1e-3  # Tikhonov: fraction of each feature's own weighted second moment added to its diagonal
RIDGE_ABSOLUTE = 1e-6  # Tikhonov floor, x sum of weights: keeps features that never vary (constant G-buffer) at 0
WEIGHT_FLOOR = 1e-7  # added to every pair weight, as the Choi 2024 code does (ops/regression.cu)
EPS_VARIANCE = 1e-4  # Choi 2024 eq. 7 epsilon (value of their code), colour^2 units
EPS_SIGMA = 1e-2  # Choi 2024 eq. 6 epsilon (value of their code), colour units
FIREFLY_K = 2.0  # clamp_fireflies: neighbour ranges (max - min) a value may lie beyond its neighbours


@dataclass(frozen=True)
class BlockParams:
    """Geometry and regularisation of a block regression."""

    radius: int = 8  # window half-size in pixels: 8 gives the 17x17 window of Choi 2024 sec. 3
    sparsity: int = 4  # centres on every `sparsity`-th row and column (Choi 2024 sec. 3: 1/16 of the pixels)
    ridge_relative: float = RIDGE_RELATIVE  # see module constant
    ridge_absolute: float = RIDGE_ABSOLUTE  # see module constant
    sigma_position: float | None = None  # pixels; Gaussian falloff of the pair weight with distance, None: flat

    def __post_init__(self) -> None:
        if self.sparsity < 1:
            raise ValueError(f"sparsity must be >= 1, got {self.sparsity}")
        if self.radius < self.sparsity - 1:
            raise ValueError(
                f"radius {self.radius} leaves pixels without a centre; it must be >= sparsity - 1 = {self.sparsity - 1}"
            )
        if not (self.ridge_relative >= 0 and self.ridge_absolute > 0):
            raise ValueError("ridge_relative must be >= 0 and ridge_absolute > 0")
        if self.sigma_position is not None and not self.sigma_position > 0:
            raise ValueError(f"sigma_position must be > 0 or None, got {self.sigma_position}")


@dataclass(frozen=True)
class PairTerms:
    """Per-pixel inputs of a block regression, all channel-first float32 planes of one H x W frame.

    Pair features of centre c and pixel i, per group g: [1, shared_i - shared_c, grouped_i - grouped_c],
    where grouped feature k is divided by (sigma_i + sigma_c + EPS_SIGMA) when scaled[k] (Choi eq. 6).
    Pair weight: exp(-|h_i - h_c|^2 / (v_i + v_c + EPS_VARIANCE)) (Choi eq. 7), times the spatial falloff
    of `BlockParams.sigma_position`, plus WEIGHT_FLOOR.
    """

    shared: np.ndarray  # (Ks, H, W): features common to all groups (normals, depth, ...)
    grouped: np.ndarray  # (G, Kg, H, W): features of one group of target channels (Kg may be 0)
    scaled: np.ndarray  # (Kg,) bool: which grouped features are divided by sigma_i + sigma_c + eps
    sigma: np.ndarray  # (H, W): standard deviation used by `scaled`, units of the scaled features
    weight_guide: np.ndarray  # (D, H, W): h of the weight (D may be 0: flat weights)
    weight_variance: np.ndarray  # (H, W): v of the weight, units of h^2

    @property
    def groups(self) -> int:
        return self.grouped.shape[0]

    @property
    def features(self) -> int:
        """K1: coefficients per group, constant included."""
        return 1 + self.shared.shape[0] + self.grouped.shape[1]


def plain_terms(shared: np.ndarray, groups: int = 1) -> PairTerms:
    """PairTerms with only shared features, flat weights and no scaling (BMFR-style regression).

    shared: (Ks, H, W) float32 planes. Returns PairTerms with `groups` groups and no grouped features.
    """
    _, height, width = shared.shape
    zeros = np.zeros((height, width), np.float32)
    return PairTerms(
        np.ascontiguousarray(shared, dtype=np.float32),
        np.zeros((groups, 0, height, width), np.float32),
        np.zeros(0, bool),
        zeros,
        np.zeros((0, height, width), np.float32),
        zeros,
    )


# --------------------------------------------------------------------------------------------- solver


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


# ------------------------------------------------------------------------------------ shared helpers


def centre_count(size: int, sparsity: int) -> int:
    """Number of centres along an axis of `size` pixels: positions 0, s, 2s, ... < size."""
    return (size + sparsity - 1) // sparsity


def spatial_weights(params: BlockParams) -> np.ndarray:
    """(2r+1, 2r+1) float32 spatial factor of the pair weight: ones, or a Gaussian of the offset in pixels."""
    r = params.radius
    if params.sigma_position is None:
        return np.ones((2 * r + 1, 2 * r + 1), np.float32)
    d = np.arange(-r, r + 1, dtype=np.float32)
    g = np.exp(-0.5 * (d / np.float32(params.sigma_position)) ** 2)
    return np.ascontiguousarray(np.outer(g, g), dtype=np.float32)


def neighbour_mean(planes: np.ndarray) -> np.ndarray:
    """Mean of the up-to-8 neighbours of each pixel in its 3x3 window, the pixel itself excluded.

    planes: (K, H, W) float32. Neighbours outside the frame are left out of the mean; a 1x1 frame has no
    neighbour and gets its own value. Returns (K, H, W) float32.
    """
    k, height, width = planes.shape
    total = np.zeros_like(planes)
    count = np.zeros((height, width), np.float32)
    for dy, dx in window_offsets(1):
        if dy == 0 and dx == 0:
            continue
        pair = overlap(height, width, dy, dx)
        if pair is None:
            continue
        (cy, cx), (ny, nx) = pair
        total[:, cy, cx] += planes[:, ny, nx]
        count[cy, cx] += 1.0
    lonely = count == 0
    total[:, lonely] = planes[:, lonely]
    return total / np.maximum(count, 1.0)


def check_firefly_k(k: float | None) -> None:
    """The one check of a stage option `firefly_k`: > 0, or None (clamp off)."""
    if k is not None and not k > 0:
        raise ValueError(f"firefly_k must be > 0 or None, got {k}")


def clamp_fireflies(planes: np.ndarray, k: float = FIREFLY_K) -> np.ndarray:
    """Clip every value to [lo - k (hi - lo), hi + k (hi - lo)], lo and hi the smallest and largest of its
    up-to-8 neighbours in the 3x3 window (the pixel itself excluded; frame border: those that exist).

    planes: (C, H, W) float32 radiance (any sign), per channel. An isolated outlier (a firefly of 1e6, or
    -1e6) is brought back to its neighbourhood; a constant image, a 1x1 frame and any value within the
    spread of its neighbours are unchanged. numba kernel; `clamp_fireflies_reference` is its numpy twin.
    Returns (C, H, W) float32.
    """
    out = np.empty_like(planes, dtype=np.float32)
    _clamp_kernel(np.ascontiguousarray(planes, dtype=np.float32), np.float32(k), out)
    return out


def clamp_fireflies_reference(planes: np.ndarray, k: float = FIREFLY_K) -> np.ndarray:
    """Plain-numpy twin of `clamp_fireflies`."""
    _, height, width = planes.shape
    lo, hi = np.full_like(planes, np.inf), np.full_like(planes, -np.inf)
    for dy, dx in window_offsets(1):
        pair = None if dy == dx == 0 else overlap(height, width, dy, dx)
        if pair is None:
            continue
        (cy, cx), (ny, nx) = pair
        lo[:, cy, cx] = np.minimum(lo[:, cy, cx], planes[:, ny, nx])
        hi[:, cy, cx] = np.maximum(hi[:, cy, cx], planes[:, ny, nx])
    spread = np.float32(k) * (hi - lo)
    out = np.clip(planes, lo - spread, hi + spread)
    return np.where(np.isfinite(lo), out, planes).astype(np.float32)


@numba.njit(parallel=True, cache=True, fastmath=False, error_model="numpy")
def _clamp_kernel(planes, k, out):
    channels, height, width = planes.shape
    for row in numba.prange(channels * height):  # a task per row of a channel
        c, y = row // height, row % height
        lo = filled(width, np.inf, np.float32)
        hi = filled(width, -np.inf, np.float32)
        for yy in range(max(0, y - 1), min(height, y + 2)):
            src = planes[c, yy]
            for dx in range(-1, 2):
                if yy == y and dx == 0:
                    continue
                for x in range(max(0, -dx), min(width, width - dx)):  # contiguous, vectorises
                    v = src[x + dx]
                    lo[x] = min(lo[x], v)
                    hi[x] = max(hi[x], v)
        src, dst = planes[c, y], out[c, y]
        for x in range(width):
            v = src[x]
            if lo[x] <= hi[x]:  # has a neighbour (not a 1x1 frame)
                spread = k * (hi[x] - lo[x])
                v = min(max(v, lo[x] - spread), hi[x] + spread)
            dst[x] = v


# -------------------------------------------------------------------------------- fast exp for numba


@numba.njit(inline="always", fastmath=True)
def _exp_neg(x):
    """exp(-x) for float32 x >= 0, vectorisable: 2^-m e^g (`simd.EXP_POLY`), relative error < 5e-7; x beyond
    `simd.EXP_NEG_LIMIT` gives exp(-EXP_NEG_LIMIT) (`simd.exp_neg` is the vector twin, bit for bit)."""
    xc = min(x, np.float32(EXP_NEG_LIMIT))
    m = np.floor(xc * np.float32(LOG2E) + np.float32(0.5))
    g = m * np.float32(LN2) - xc  # exp(-x) = 2^-m e^g, |g| <= ln2 / 2
    return bits_to_float32(float32_to_bits(exp_poly(g)) - (np.int32(m) << np.int32(23)))


# ------------------------------------------------------------------------------------ block moments


def block_solve(
    terms: PairTerms, target: np.ndarray, params: BlockParams, *, packed: np.ndarray | None = None
) -> np.ndarray:
    """Every centre's regression coefficients (Choi eqs. 3-4): the moments X^T W X, X^T W Y of its window
    (numba kernel) solved with `solve_ridge`'s Tikhonov term, in one pass over the centres' moments.

    terms: PairTerms of the frame. target: (C, H, W) float32 planes of y, C = G * M (group g owns
    channels g*M ... g*M+M-1). Returns beta (Hc, Wc, G, K1, M) float32, Hc, Wc = `centre_count` of H, W;
    feature order [1, shared..., grouped...]. packed: `pack_planes(terms, target, params)`, if at hand.
    """
    hc, wc, g, k1, m = _moment_shape(terms, target, params)
    layout = MomentLayout.of(terms, target.shape[0])
    fa, fb, dest = layout.moment_entries()
    acc = np.zeros((hc, len(fa), wc), np.float32)
    _block_moments_kernel(
        pack_planes(terms, target, params) if packed is None else packed, layout.counts(),
        np.asarray(terms.scaled, np.bool_),
        spatial_weights(params), params.radius, params.sparsity, kernel_constants(), fa, fb, acc,
    )  # fmt: skip
    gram_entry = np.zeros((g, k1, k1), np.int64)  # which accumulator holds each gram / rhs element
    rhs_entry = np.zeros((g, k1, m), np.int64)
    for e, (kind, gi, p, q) in enumerate(dest):
        if kind == 2:
            rhs_entry[gi, p, q] = e
        else:
            for gg in range(g) if kind == 0 else (gi,):  # kind 0: the shared block, in every group
                gram_entry[gg, p, q] = gram_entry[gg, q, p] = e
    beta = np.empty((hc, wc, g, k1, m), np.float32)
    _moments_solve_kernel(acc, gram_entry, rhs_entry, float(params.ridge_relative), float(params.ridge_absolute), beta)
    return beta


@numba.njit(parallel=True, cache=True, error_model="numpy")
def _moments_solve_kernel(acc, gram_entry, rhs_entry, ridge_relative, ridge_absolute, beta):
    """acc (Hc, entries, Wc) float32 moments -> beta (Hc, Wc, G, K1, M): per centre row and group, its
    centres solved together as the lanes of `cholesky_ridge_solve`."""
    hc, _, wc = acc.shape
    g, k1, m = rhs_entry.shape
    unused = np.empty(0)  # weight sums: the constant column holds them
    for a in numba.prange(hc):
        x = np.empty((k1, k1, wc))
        y = np.empty((k1, m, wc))
        for gi in range(g):
            for i in range(k1):
                for j in range(k1):
                    src = acc[a, gram_entry[gi, i, j]]
                    for b in range(wc):
                        x[i, j, b] = src[b]
                for c in range(m):
                    src = acc[a, rhs_entry[gi, i, c]]
                    for b in range(wc):
                        y[i, c, b] = src[b]
            cholesky_ridge_solve(x, y, k1, m, ridge_relative, ridge_absolute, True, unused, wc)
            for b in range(wc):
                for i in range(k1):
                    for c in range(m):
                        beta[a, b, gi, i, c] = y[i, c, b]


def block_moments_reference(terms: PairTerms, target: np.ndarray, params: BlockParams) -> tuple[np.ndarray, np.ndarray]:
    """Plain-numpy moments of every centre's window (Choi eq. 4), vectorised over centres: gram X^T W X
    (Hc, Wc, G, K1, K1) and rhs X^T W Y (Hc, Wc, G, K1, M), float32 (arguments as `block_solve`).
    `solve_ridge_reference` of them is the twin of `block_solve`."""
    hc, wc, g, k1, m = _moment_shape(terms, target, params)
    _, height, width = target.shape
    s, r = params.sparsity, params.radius
    spatial = spatial_weights(params)
    gram = np.zeros((hc, wc, g, k1, k1), np.float32)
    rhs = np.zeros((hc, wc, g, k1, m), np.float32)
    for dy, dx in window_offsets(r):
        rows, cols = _valid_centres(hc, height, s, dy), _valid_centres(wc, width, s, dx)
        if rows is None or cols is None:
            continue
        centre, pixel = _offset_slices(rows, cols, s, dy, dx)
        weight = _pair_weight(terms, centre, pixel) * spatial[dy + r, dx + r] + np.float32(WEIGHT_FLOOR)
        feats = _pair_features(terms, centre, pixel)  # (G, K1, h, w)
        y = target[(slice(None), *pixel)].reshape(g, m, *weight.shape)
        wf = feats * weight
        gram[rows, cols] += np.einsum("gkhw,glhw->hwgkl", wf, feats)
        rhs[rows, cols] += np.einsum("gkhw,gmhw->hwgkm", wf, y)
    return gram, rhs


def _moment_shape(terms: PairTerms, target: np.ndarray, params: BlockParams) -> tuple[int, int, int, int, int]:
    channels, height, width = target.shape
    g = terms.groups
    if channels % g:
        raise ValueError(f"{channels} target channels do not split into {g} groups")
    return (centre_count(height, params.sparsity), centre_count(width, params.sparsity), g, terms.features,
            channels // g)  # fmt: skip


def _valid_centres(count: int, size: int, sparsity: int, offset: int) -> slice | None:
    """Range of centre indices a whose pixel a*sparsity + offset lies inside [0, size)."""
    start = max(0, -(offset // sparsity))
    stop = min(count, (size - 1 - offset) // sparsity + 1)
    return slice(start, stop) if stop > start else None


def _offset_slices(rows: slice, cols: slice, s: int, dy: int, dx: int) -> tuple[tuple[slice, slice], ...]:
    """Pixel slices of the centres rows x cols (centre indices) and of their neighbours at (dy, dx)."""
    centre = (slice(rows.start * s, (rows.stop - 1) * s + 1, s), slice(cols.start * s, (cols.stop - 1) * s + 1, s))
    pixel = (slice(centre[0].start + dy, centre[0].stop + dy, s), slice(centre[1].start + dx, centre[1].stop + dx, s))
    return centre, pixel


def _pair_weight(terms: PairTerms, centre: tuple[slice, slice], pixel: tuple[slice, slice]) -> np.ndarray:
    """Choi eq. 7 weight (without spatial factor and floor) for centre/pixel slices: (h, w) float32."""
    h = terms.weight_guide
    d2 = np.sum((h[(slice(None), *pixel)] - h[(slice(None), *centre)]) ** 2, axis=0)
    v = terms.weight_variance
    return np.exp(-d2 / (v[pixel] + v[centre] + np.float32(EPS_VARIANCE))).astype(np.float32)


def _pair_features(terms: PairTerms, centre: tuple[slice, slice], pixel: tuple[slice, slice]) -> np.ndarray:
    """Pair features x_i - x_c with the constant first: (G, K1, h, w) float32."""
    shared = terms.shared[(slice(None), *pixel)] - terms.shared[(slice(None), *centre)]
    grouped = terms.grouped[(slice(None), slice(None), *pixel)] - terms.grouped[(slice(None), slice(None), *centre)]
    if terms.scaled.any():
        inv = np.float32(1.0) / (terms.sigma[pixel] + terms.sigma[centre] + np.float32(EPS_SIGMA))
        grouped = np.where(terms.scaled[None, :, None, None], grouped * inv, grouped)
    g = terms.groups
    ones = np.ones((g, 1, *shared.shape[1:]), np.float32)
    return np.concatenate([ones, np.broadcast_to(shared, (g, *shared.shape)), grouped], axis=1).astype(np.float32)


# ---------------------------------------------------------------------------- numba kernels' layout

LANE_CHUNK = 512  # centres processed together: a whole centre row up to 2048 px wide (fewer, longer loops)
#
# The kernels vectorise over the centres of one centre row ("lanes"). For a window offset (dy, dx) the
# pixels of consecutive centres are `sparsity` apart, so every input plane is split into `sparsity` phase
# planes (x = sparsity * q + phase), where they are consecutive. Packed planes, in this order:
# [inside-frame mask, v, sigma, h (D), shared (Ks), grouped (G * Kg), target (C)].
# Per pair the kernels build feature rows F = [1, shared (Ks), grouped (G * Kg), target (C)]; a moment is
# sum over pairs of w * F[fa] * F[fb], a prediction sum over k of beta_k * F[k].


class MomentLayout:
    """Plane and feature-row indices of a block regression: d weight guides, ks shared features, g groups
    of kg grouped features, c target channels (`of` reads them from a PairTerms)."""

    def __init__(self, d: int, ks: int, g: int, kg: int, c: int):
        self.d, self.ks, self.g, self.kg, self.c = d, ks, g, kg, c
        self.m = c // g

    @classmethod
    def of(cls, terms: PairTerms, channels: int) -> MomentLayout:
        return cls(terms.weight_guide.shape[0], terms.shared.shape[0], *terms.grouped.shape[:2], channels)

    def counts(self) -> np.ndarray:
        return np.array([self.d, self.ks, self.g, self.kg, self.c], np.int64)

    def parts(self, terms: PairTerms, target: np.ndarray | None) -> list[np.ndarray]:
        """The packed planes in order, as (k, H, W) float32 blocks (see the layout comment above)."""
        height, width = terms.sigma.shape
        parts = [np.ones((1, height, width), np.float32), terms.weight_variance[None], terms.sigma[None],
                 terms.weight_guide, terms.shared, terms.grouped.reshape(-1, height, width)]  # fmt: skip
        if target is not None:
            parts.append(target)
        return [np.ascontiguousarray(part, dtype=np.float32) for part in parts if part.shape[0]]

    def pack(self, terms: PairTerms, target: np.ndarray | None) -> np.ndarray:
        return np.concatenate(self.parts(terms, target), axis=0)

    def row(self, g: int, f: int) -> int:
        """Feature row of group g's feature f (0: constant, 1..Ks: shared, then grouped)."""
        return f if f <= self.ks else 1 + self.ks + g * self.kg + (f - 1 - self.ks)

    def moment_entries(self) -> tuple[np.ndarray, np.ndarray, list[tuple[int, int, int, int]]]:
        """(fa, fb, dest): dest[e] = (0, -, p, q) gram of all groups, (1, g, p, q) gram of group g,
        (2, g, f, m) rhs of group g."""
        fa, fb, dest = [], [], []
        for p in range(1 + self.ks):
            for q in range(p, 1 + self.ks):
                fa.append(p), fb.append(q), dest.append((0, 0, p, q))
        for g in range(self.g):
            for k in range(self.kg):
                col = 1 + self.ks + k
                for p in range(col + 1):
                    fa.append(self.row(g, p)), fb.append(self.row(g, col)), dest.append((1, g, p, col))
            for mm in range(self.m):
                trow = 1 + self.ks + self.g * self.kg + g * self.m + mm
                for f in range(1 + self.ks + self.kg):
                    fa.append(self.row(g, f)), fb.append(trow), dest.append((2, g, f, mm))
        return np.array(fa, np.int64), np.array(fb, np.int64), dest

    def prediction_entries(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(channel, feature row, beta column) of every term of every channel's prediction."""
        ch, rows, cols = [], [], []
        k1 = 1 + self.ks + self.kg
        for g in range(self.g):
            for mm in range(self.m):
                for f in range(k1):
                    ch.append(g * self.m + mm), rows.append(self.row(g, f)), cols.append((g * k1 + f) * self.m + mm)
        return np.array(ch, np.int64), np.array(rows, np.int64), np.array(cols, np.int64)


def kernel_constants() -> np.ndarray:
    """[EPS_SIGMA, EPS_VARIANCE, WEIGHT_FLOOR] float32, the constants the regression kernels take."""
    return np.array([EPS_SIGMA, EPS_VARIANCE, WEIGHT_FLOOR], np.float32)


def pad_lanes(params: BlockParams) -> int:
    return -(-params.radius // params.sparsity)


def pack_planes(terms: PairTerms, target: np.ndarray | None, params: BlockParams) -> np.ndarray:
    """The kernels' input: every plane of `terms` (and `target`) packed and split into phase planes."""
    parts = MomentLayout.of(terms, 0 if target is None else target.shape[0]).parts(terms, target)
    s, pad = params.sparsity, pad_lanes(params)
    height, width = terms.sigma.shape
    out = np.empty((s, sum(part.shape[0] for part in parts), height, centre_count(width, s) + 2 * pad + 1), np.float32)
    first = 0
    for part in parts:  # straight into the phase planes: no concatenated copy of the frame
        _phase_copy_kernel(part, first, pad, out)
        first += part.shape[0]
    return out


@numba.njit(parallel=True, cache=True, error_model="numpy")
def _phase_copy_kernel(src, first, pad, out):
    """Planes src (k, H, W) into out[:, first : first + k] of `phase_planes`' layout, zeros around."""
    count, height, width = src.shape
    s, lanes = out.shape[0], out.shape[3]
    for y in numba.prange(height):
        for p in range(s):
            n = (width - p + s - 1) // s if p < width else 0
            for k in range(count):
                dst, row = out[p, first + k, y], src[k, y]
                for j in range(pad):
                    dst[j] = 0.0
                for j in range(n):
                    dst[pad + j] = row[p + s * j]
                for j in range(pad + n, lanes):
                    dst[j] = 0.0


def phase_planes(planes: np.ndarray, params: BlockParams) -> np.ndarray:
    """Plain-numpy twin of `pack_planes`' phase split: (P, H, W) -> (S, P, H, Wc + 2 pad + 1) float32,
    S = sparsity: pixel x = S q + phase lands at [phase, :, :, q + pad], pad = ceil(radius / S); zeros
    outside the frame (the mask plane is 0 there)."""
    s, pad = params.sparsity, pad_lanes(params)
    count, height, width = planes.shape
    wc = centre_count(width, s)
    out = np.zeros((s, count, height, wc + 2 * pad + 1), np.float32)
    for phase in range(s):
        cols = planes[:, :, phase::s]
        out[phase, :, :, pad : pad + cols.shape[2]] = cols
    return out


@numba.njit(inline="always", fastmath=True)
def _pair_rows(planes, counts, scaled, consts, sw, phase, y, cy, lo, pad, rows, w, s, lanes):
    """Fill w (pair weights) and F rows 1.. (pair features, targets) for the lanes of one offset.

    Inner loops index 1-D views with the loop counter only, so LLVM sees contiguous, non-negative
    indices and vectorises them."""
    d, ks, g, kg, c = counts[0], counts[1], counts[2], counts[3], counts[4]
    eps_sigma, eps_var, floor = consts[0], consts[1], consts[2]
    for j in range(lanes):
        s[j] = 0.0
    for k in range(d):
        pix, cen = planes[phase, 3 + k, y, lo : lo + lanes], planes[0, 3 + k, cy, pad : pad + lanes]
        for j in range(lanes):
            t = pix[j] - cen[j]
            s[j] += t * t
    mask = planes[phase, 0, y, lo : lo + lanes]
    var_i, var_c = planes[phase, 1, y, lo : lo + lanes], planes[0, 1, cy, pad : pad + lanes]
    sig_i, sig_c = planes[phase, 2, y, lo : lo + lanes], planes[0, 2, cy, pad : pad + lanes]
    for j in range(lanes):
        w[j] = (_exp_neg(s[j] / (var_i[j] + var_c[j] + eps_var)) * sw + floor) * mask[j]
        s[j] = 1.0 / (sig_i[j] + sig_c[j] + eps_sigma)
    base = 3 + d
    for k in range(ks):
        pix, cen = planes[phase, base + k, y, lo : lo + lanes], planes[0, base + k, cy, pad : pad + lanes]
        out = rows[1 + k]
        for j in range(lanes):
            out[j] = pix[j] - cen[j]
    base += ks
    for gi in range(g):
        for k in range(kg):
            plane = base + gi * kg + k
            pix, cen = planes[phase, plane, y, lo : lo + lanes], planes[0, plane, cy, pad : pad + lanes]
            out = rows[1 + ks + gi * kg + k]
            if scaled[k]:
                for j in range(lanes):
                    out[j] = (pix[j] - cen[j]) * s[j]
            else:
                for j in range(lanes):
                    out[j] = pix[j] - cen[j]
    base += g * kg
    for k in range(c):
        pix, out = planes[phase, base + k, y, lo : lo + lanes], rows[1 + ks + g * kg + k]
        for j in range(lanes):
            out[j] = pix[j]


@numba.njit(parallel=True, cache=True, fastmath=True, error_model="numpy")
def _block_moments_kernel(planes, counts, scaled, spatial, radius, sparsity, consts, fa, fb, acc):
    """Moments of every centre row's lanes into acc (Hc, entries, Wc): entry e is sum w * F[fa[e]] * F[fb[e]],
    one pass per entry (the cross-regression has its own fused kernel, `cross_block`)."""
    height = planes.shape[2]
    hc, entries, lanes = acc.shape
    nrows = 1 + counts[1] + counts[2] * counts[3] + counts[4]
    pad = -(-radius // sparsity)
    for a in numba.prange(hc):
        rows = np.empty((nrows, LANE_CHUNK), np.float32)
        w = np.empty(LANE_CHUNK, np.float32)
        s = np.empty(LANE_CHUNK, np.float32)
        wf = np.empty(LANE_CHUNK, np.float32)
        part = np.empty((entries, LANE_CHUNK), np.float32)
        rows[0, :] = 1.0
        cy = a * sparsity
        for j0 in range(0, lanes, LANE_CHUNK):
            n = min(LANE_CHUNK, lanes - j0)
            part[:, :] = 0.0
            for dy in range(-radius, radius + 1):
                y = cy + dy
                if y < 0 or y >= height:
                    continue
                for dx in range(-radius, radius + 1):
                    phase = dx % sparsity
                    lo = pad + dx // sparsity + j0
                    _pair_rows(planes, counts, scaled, consts, spatial[dy + radius, dx + radius], phase, y, cy, lo,
                               pad + j0, rows, w, s, n)  # fmt: skip
                    last = -1
                    for e in range(entries):
                        if fa[e] != last:
                            last = fa[e]
                            for j in range(n):
                                wf[j] = w[j] * rows[last, j]
                        b = fb[e]
                        for j in range(n):
                            part[e, j] += wf[j] * rows[b, j]
            acc[a, :, j0 : j0 + n] = part[:, :n]


# ------------------------------------------------------------------------------ block reconstruction


def block_reconstruct(
    terms: PairTerms, beta: np.ndarray, params: BlockParams, *, packed: np.ndarray | None = None
) -> np.ndarray:
    """Choi eq. 5: each pixel's weighted mean of the predictions alpha_c + beta_c^T (x_i - x_c) of the
    centres c whose window holds it, numba kernel.

    terms: PairTerms of the frame (the same as for the moments). beta: (Hc, Wc, G, K1, M) float32 from
    `solve_ridge`. Returns (C, H, W) float32 planes, C = G * M.
    packed: `pack_planes(terms, target, params)` of the moments (target planes are ignored), if at hand.
    """
    hc, wc, g, _, m = beta.shape
    height, width = terms.sigma.shape
    s = params.sparsity
    layout = MomentLayout.of(terms, g * m)
    layout.c = 0  # the kernel reads no target planes
    ch, rows, cols = layout.prediction_entries()
    planes = pack_planes(terms, None, params) if packed is None else packed
    num = np.zeros((s, g * m, height, planes.shape[3]), np.float32)
    den = np.zeros((s, height, planes.shape[3]), np.float32)
    coefs = np.ascontiguousarray(beta.reshape(hc, wc, -1).transpose(0, 2, 1))  # (Hc, G*K1*M, Wc)
    _block_reconstruct_kernel(planes, layout.counts(), np.asarray(terms.scaled, np.bool_), spatial_weights(params),
                              params.radius, s, kernel_constants(), coefs, ch, rows, cols, num, den)  # fmt: skip
    out = np.empty((g * m, height, width), np.float32)
    normalise_phases(num, den, pad_lanes(params), out)
    return out


@numba.njit(parallel=True, cache=True, error_model="numpy")
def normalise_phases(num, den, pad, out):
    """Back from the phase planes, eq. 5's division: out[c, y, x] = num[p, c, y, q] / den[p, y, q] with
    p = x % S, q = pad + x // S (0 where no weight arrived). num (S, C, H, L), den (S, H, L), out (C, H, W);
    a task per row (`normalise_row`)."""
    for y in numba.prange(out.shape[1]):
        normalise_row(num, den, pad, y, np.empty((num.shape[0], num.shape[3]), np.float32), out, y)


@numba.njit(inline="always")
def normalise_row(num, den, pad, y, inv, out, row):
    """Row y of `normalise_phases` into row `row` of out (C, R, W) float32; inv: (S, L) float32 scratch. At
    sparsity 4 (the paper's) whole blocks of 4 LANES pixels are written as vectors (`simd.store_phases`),
    the other pixels one value at a time."""
    s = num.shape[0]
    channels, width = out.shape[0], out.shape[2]
    done = phase_blocks(width, s)
    for p in range(min(s, width)):  # phase by phase: no division per pixel
        for j in range((width - p + s - 1) // s):
            d = den[p, y, pad + j]
            inv[p, j] = np.float32(1.0) / d if d > 0 else np.float32(1.0)
    for c in range(channels):
        for x in range(0, done, 4 * LANES):
            q = x // 4
            store_phases(out, (c, row, x), load(num, (0, c, y, pad + q)) * load(inv, (0, q)),
                         load(num, (1, c, y, pad + q)) * load(inv, (1, q)),
                         load(num, (2, c, y, pad + q)) * load(inv, (2, q)),
                         load(num, (3, c, y, pad + q)) * load(inv, (3, q)))  # fmt: skip
        for p in range(min(s, width)):
            src, dst = num[p, c, y], out[c, row]
            for j in range(done // s, (width - p + s - 1) // s):
                dst[p + s * j] = src[pad + j] * inv[p, j]


def block_reconstruct_reference(terms: PairTerms, beta: np.ndarray, params: BlockParams) -> np.ndarray:
    """Plain-numpy twin of `block_reconstruct` (same arguments and result), vectorised over centres."""
    height, width = terms.sigma.shape
    hc, wc, g, _, m = beta.shape
    num = np.zeros((g * m, height, width), np.float32)
    den = np.zeros((height, width), np.float32)
    s, r = params.sparsity, params.radius
    spatial = spatial_weights(params)
    for dy, dx in window_offsets(r):
        rows, cols = _valid_centres(hc, height, s, dy), _valid_centres(wc, width, s, dx)
        if rows is None or cols is None:
            continue
        centre, pixel = _offset_slices(rows, cols, s, dy, dx)
        weight = _pair_weight(terms, centre, pixel) * spatial[dy + r, dx + r] + np.float32(WEIGHT_FLOOR)
        feats = _pair_features(terms, centre, pixel)  # (G, K1, h, w)
        pred = np.einsum("gkhw,hwgkm->gmhw", feats, beta[rows, cols]).reshape(g * m, *weight.shape)
        num[(slice(None), *pixel)] += weight * pred
        den[pixel] += weight
    return num / den


@numba.njit(parallel=True, cache=True, fastmath=True, error_model="numpy")
def _block_reconstruct_kernel(planes, counts, scaled, spatial, radius, sparsity, consts, coefs, ch, frow, col, num,
                              den):  # fmt: skip
    """Weighted predictions of every centre into num (S, C, H, lanes) and weights into den (S, H, lanes)."""
    height = planes.shape[2]
    hc, _, lanes = coefs.shape
    channels = num.shape[1]
    nrows = 1 + counts[1] + counts[2] * counts[3]
    pad = -(-radius // sparsity)
    # Centre rows `stride` apart never share a pixel, so the rows of one pass may run in parallel.
    stride = (2 * radius) // sparsity + 1
    for first in range(stride):
        for i in numba.prange((hc - first + stride - 1) // stride):
            a = first + i * stride
            rows = np.empty((nrows, LANE_CHUNK), np.float32)
            w = np.empty(LANE_CHUNK, np.float32)
            s = np.empty(LANE_CHUNK, np.float32)
            pred = np.empty((channels, LANE_CHUNK), np.float32)
            rows[0, :] = 1.0
            cy = a * sparsity
            for j0 in range(0, lanes, LANE_CHUNK):
                n = min(LANE_CHUNK, lanes - j0)
                for dy in range(-radius, radius + 1):
                    y = cy + dy
                    if y < 0 or y >= height:
                        continue
                    for dx in range(-radius, radius + 1):
                        phase = dx % sparsity
                        lo = pad + dx // sparsity + j0
                        _pair_rows(planes, counts, scaled, consts, spatial[dy + radius, dx + radius], phase, y, cy,
                                   lo, pad + j0, rows, w, s, n)  # fmt: skip
                        out = den[phase, y, lo : lo + n]
                        for j in range(n):
                            out[j] += w[j]
                        pred[:, :n] = 0.0
                        for e in range(ch.shape[0]):
                            c, r, coef = ch[e], frow[e], coefs[a, col[e], j0 : j0 + n]
                            for j in range(n):
                                pred[c, j] += coef[j] * rows[r, j]
                        for c in range(channels):
                            out = num[phase, c, y, lo : lo + n]
                            for j in range(n):
                                out[j] += w[j] * pred[c, j]


# ---------------------------------------------------------------------------------------- the whole


def block_regression(
    terms: PairTerms, target: np.ndarray, params: BlockParams, *, reference: bool = False
) -> np.ndarray:
    """Block-wise weighted regression of `target` on the pair features of `terms` (Choi eqs. 3-5).

    target: (C, H, W) float32 planes of y (any sign, any scale). Returns (C, H, W) float32: the
    reconstruction of eq. 5. reference: use the plain-numpy kernels (slow; for tests).
    """
    if reference:
        gram, rhs = block_moments_reference(terms, target, params)
        beta = solve_ridge_reference(gram, rhs, params.ridge_relative, params.ridge_absolute)
        return block_reconstruct_reference(terms, beta, params)
    packed = pack_planes(terms, target, params)
    return block_reconstruct(terms, block_solve(terms, target, params, packed=packed), params, packed=packed)


def to_planes(image: np.ndarray) -> np.ndarray:
    """(H, W, C) -> contiguous (C, H, W) float32."""
    return np.ascontiguousarray(np.moveaxis(np.asarray(image, np.float32), -1, 0))


def from_planes(planes: np.ndarray) -> np.ndarray:
    """(C, H, W) -> contiguous (H, W, C) float32."""
    return np.ascontiguousarray(np.moveaxis(planes, 0, -1), dtype=np.float32)


def standardise(planes: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """Each plane minus its mean, over its standard deviation (planes that do not vary become 0).

    planes: (K, H, W) float32. A regression with a constant term is unchanged by this affine change of
    features; it puts every feature on unit scale, which the absolute ridge floor and float32 moments need.
    out: (K, H, W) float32 to write into (`planes` itself: in place), or None for a new array. Returns it.
    numba kernel (float64 sums, parallel over blocks of every plane); `standardise_reference` is the
    plain-numpy twin.
    """
    planes = np.ascontiguousarray(planes, dtype=np.float32)
    out = np.empty_like(planes) if out is None else out
    if planes.size:
        _standardise_kernel(planes.reshape(planes.shape[0], -1), out.reshape(planes.shape[0], -1))
    return out


def standardise_reference(planes: np.ndarray) -> np.ndarray:
    """Plain-numpy twin of `standardise`."""
    if planes.shape[0] == 0:
        return np.ascontiguousarray(planes, dtype=np.float32)
    mean = planes.reshape(planes.shape[0], -1).mean(axis=1, dtype=np.float64)
    centred = planes - mean[:, None, None].astype(np.float32)
    flat = centred.reshape(planes.shape[0], -1)
    std = np.sqrt(np.einsum("kn,kn->k", flat, flat, dtype=np.float64) / max(flat.shape[1], 1))
    std = np.where(std > 1e-12 * (np.abs(mean) + 1.0), std, np.inf)
    centred /= std[:, None, None].astype(np.float32)
    return np.ascontiguousarray(centred, dtype=np.float32)


STANDARDISE_BLOCK = 1 << 16  # values per task of `_standardise_kernel`


@numba.njit(parallel=True, cache=True, fastmath=True, error_model="numpy")
def _standardise_kernel(flat, out):
    """flat, out: (K, N) float32, N >= 1. Per row, float64 sums of d = x - x0 and d^2 over blocks (x0: the
    row's first value, so the variance loses nothing to cancellation), then (x - mean) / std."""
    count, n = flat.shape
    blocks = -(-n // STANDARDISE_BLOCK)
    partial = np.empty((count, blocks, 2))  # no array expressions outside the prange loops: each would be
    for task in numba.prange(count * blocks):  # a parallel region of its own (~30 us apiece)
        k, lo = task // blocks, (task % blocks) * STANDARDISE_BLOCK
        src, first = flat[k, lo : min(n, lo + STANDARDISE_BLOCK)], np.float64(flat[k, 0])
        linear, square = 0.0, 0.0
        for j in range(src.shape[0]):
            d = np.float64(src[j]) - first
            linear += d
            square += d * d
        partial[task // blocks, task % blocks, 0] = linear
        partial[task // blocks, task % blocks, 1] = square
    mean32 = np.empty(count, np.float32)
    inv = np.empty(count, np.float32)
    for k in range(count):
        linear, square = 0.0, 0.0
        for b in range(blocks):
            linear += partial[k, b, 0]
            square += partial[k, b, 1]
        shift = linear / n
        mean = np.float64(flat[k, 0]) + shift
        std = np.sqrt(max(square / n - shift * shift, 0.0))
        mean32[k] = np.float32(mean)
        inv[k] = np.float32(1.0 / std) if std > 1e-12 * (abs(mean) + 1.0) else np.float32(0.0)
    for task in numba.prange(count * blocks):
        k, lo = task // blocks, (task % blocks) * STANDARDISE_BLOCK
        hi = min(n, lo + STANDARDISE_BLOCK)
        src, dst, m, s = flat[k, lo:hi], out[k, lo:hi], mean32[k], inv[k]
        for j in range(hi - lo):
            dst[j] = (src[j] - m) * s


def channel_planes(image: np.ndarray, albedo: np.ndarray | None = None, out: np.ndarray | None = None) -> np.ndarray:
    """`to_planes(image)`, or `to_planes(demodulate(image, albedo))` when `albedo` is given, in one pass.

    image: (H, W, C) float32 (linear radiance when demodulated); albedo: (H, W, C) float32 in [0, 1], or
    None; out: (C, H, W) float32 to write into (e.g. a slice of a larger stack of planes), or None.
    Returns the (C, H, W) float32 planes. numba kernel (parallel over rows, the same float32 division as
    `albedo.demodulate`); `channel_planes_reference` is the plain-numpy twin.
    """
    image = np.ascontiguousarray(image, dtype=np.float32)
    if out is None:
        out = np.empty((image.shape[2], *image.shape[:2]), np.float32)
    divisor = image if albedo is None else np.ascontiguousarray(albedo, dtype=np.float32)
    _channel_planes_kernel(image, divisor, albedo is not None, out)
    return out


def channel_planes_reference(
    image: np.ndarray, albedo: np.ndarray | None = None, out: np.ndarray | None = None
) -> np.ndarray:
    """Plain-numpy twin of `channel_planes`."""
    planes = to_planes(image if albedo is None else demodulate(image, albedo))
    if out is None:
        return planes
    out[...] = planes
    return out


@numba.njit(parallel=True, cache=True, error_model="numpy")
def _channel_planes_kernel(image, albedo, divide, out):
    """out[m, y, x] = image[y, x, m], divided by `albedo_factor(albedo[y, x, m])` when `divide`."""
    height, width, channels = image.shape
    for y in numba.prange(height):
        src, factor = image[y].reshape(width * channels), albedo[y].reshape(width * channels)
        if channels == 3 and divide:  # a constant stride: LLVM vectorises the strided loads together
            d0, d1, d2 = out[0, y], out[1, y], out[2, y]
            for x in range(width):
                d0[x] = src[3 * x] / albedo_factor(factor[3 * x])
                d1[x] = src[3 * x + 1] / albedo_factor(factor[3 * x + 1])
                d2[x] = src[3 * x + 2] / albedo_factor(factor[3 * x + 2])
        elif channels == 3:
            d0, d1, d2 = out[0, y], out[1, y], out[2, y]
            for x in range(width):
                d0[x] = src[3 * x]
                d1[x] = src[3 * x + 1]
                d2[x] = src[3 * x + 2]
        else:
            for m in range(channels):
                dst = out[m, y]
                for x in range(width):
                    i = x * channels + m
                    dst[x] = src[i] / albedo_factor(factor[i]) if divide else src[i]


@numba.njit(inline="always")
def interleave_row(line, albedo, modulate, out):
    """out[x, m] = line[m, x]: a row of planes (C, W) float32 into a row of pixels (W, C), times
    `albedo_factor(albedo[x, m])` when `modulate` (`albedo.remodulate`, fused into the store).
    For 3 channels the flag is tested outside the loops: tested inside, it kept them from vectorising."""
    channels, width = line.shape
    dst, factor = out.reshape(width * channels), albedo.reshape(width * channels)
    if channels == 3:  # a constant stride: the strided stores vectorise together
        s0, s1, s2 = line[0], line[1], line[2]
        if modulate:
            for x in range(width):
                dst[3 * x] = s0[x] * albedo_factor(factor[3 * x])
                dst[3 * x + 1] = s1[x] * albedo_factor(factor[3 * x + 1])
                dst[3 * x + 2] = s2[x] * albedo_factor(factor[3 * x + 2])
        else:
            for x in range(width):
                dst[3 * x] = s0[x]
                dst[3 * x + 1] = s1[x]
                dst[3 * x + 2] = s2[x]
    else:
        for m in range(channels):
            src = line[m]
            for x in range(width):
                i = x * channels + m
                dst[i] = src[x] * albedo_factor(factor[i]) if modulate else src[x]


# ------------------------------------------------------------------- flat weights: exact box sums


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


# ------------------------------------------------------------------ clusters of outliers: sigma clipping

ROBUST_RADIUS = 3  # clamp_outlier_clusters: window half-size, pixels (7x7: a 3x3 cluster is 9/49 of it)
ROBUST_CLIP = 1.5  # first pass keeps |t - mean| <= 1.5 std: a cluster under ~30% of the window is left out
ROBUST_K = 3.0  # second pass: a value may lie k clipped stds beyond the clipped mean (compressed units) ...
ROBUST_MARGIN = 1.0  # ... plus this margin, in compressed units (a factor e = 2.7 above the local level)


def radiance_scale(planes: np.ndarray) -> float:
    """Typical magnitude of a frame: the median of |value| over a 4x4-strided subsample (cheap at 720p),
    floored at 1e-6. planes: (C, H, W) float32 radiance. Below this scale the log transform of
    `clamp_outlier_clusters` is about linear."""
    sample = np.abs(planes[:, ::4, ::4]).ravel()
    if not sample.size:
        return 1e-6
    half = sample.size // 2  # the median by one partition (np.median partitions at two indices)
    part = np.partition(sample, half)
    median = float(part[half]) if sample.size % 2 else 0.5 * (float(part[:half].max()) + float(part[half]))
    return max(median, 1e-6)


def clamp_outlier_clusters(
    planes: np.ndarray,
    radius: int = ROBUST_RADIUS,
    k: float = ROBUST_K,
    clip: float = ROBUST_CLIP,
    margin: float = ROBUST_MARGIN,
) -> np.ndarray:
    """Clip values that stand out from a robust local statistic of the range-compressed signal.

    `clamp_fireflies` compares a value with its 8 neighbours, so a cluster of outliers (several bright
    samples side by side, or the emitter-edge residual left by subtracting a differently sampled emission
    buffer) shields itself. Here, per channel, on t = sign(x) log(1 + |x| / s) (s = `radiance_scale`, so
    log-like above the frame's typical level and linear near 0; signed, so negative outliers too), over
    the (2r+1)^2 window clipped to the frame:
      1. mean m and std d of t;
      2. one sigma-clipping step: the clipped mean m' and std d' of the t with |t - m| <= clip * d only.
         A group of outliers covering less than ~1 / (1 + clip^2) of the window (31% for clip 1.5) lies
         outside m +- clip * d and drops out, so it cannot raise the statistic it is judged by;
      3. t is clipped to m' +- (k d' + margin) and mapped back to radiance.
    Values inside that band, a constant image and smooth gradients are unchanged; structures that fill
    more than ~1/3 of the window count as signal. Limitation: thin bright detail (a 1-2 pixel line more
    than e^(k d' + margin) above its surround) is clipped too: the regressions fed by this blur such detail
    anyway unless a G-buffer explains it.

    planes: (C, H, W) float32 radiance (any sign). Returns (C, H, W) float32. numba kernel: t in float32
    by a vectorised log (`_log_fast`, relative error ~1e-7), box sums and statistics in float64, fused per
    band of rows; matches `clamp_outlier_clusters_reference`, the plain-numpy twin, to ~1e-6 relative.
    """
    if radius < 0:
        raise ValueError(f"radius must be >= 0, got {radius}")
    planes = np.ascontiguousarray(planes, dtype=np.float32)
    out = np.empty_like(planes)
    if planes.size:
        _cluster_kernel(planes, radiance_scale(planes), int(radius), float(k), float(clip), float(margin), out)
    return out


def _box_mean_reference(planes: np.ndarray, radius: int) -> np.ndarray:
    """Mean over the (2r+1)^2 window clipped to the frame, of (C, H, W) float64 planes (cumulative sums)."""
    _, height, width = planes.shape
    total = planes
    for axis, n in ((1, height), (2, width)):
        c = np.cumsum(total, axis=axis)
        c = np.concatenate([np.zeros_like(np.take(c, [0], axis=axis)), c], axis=axis)
        hi = np.minimum(np.arange(n) + radius + 1, n)
        lo = np.maximum(np.arange(n) - radius, 0)
        total = np.take(c, hi, axis=axis) - np.take(c, lo, axis=axis)
    ys, xs = np.arange(height), np.arange(width)
    count = np.outer(np.minimum(ys + radius, height - 1) - np.maximum(ys - radius, 0) + 1,
                     np.minimum(xs + radius, width - 1) - np.maximum(xs - radius, 0) + 1)  # fmt: skip
    return total / count


def clamp_outlier_clusters_reference(
    planes: np.ndarray,
    radius: int = ROBUST_RADIUS,
    k: float = ROBUST_K,
    clip: float = ROBUST_CLIP,
    margin: float = ROBUST_MARGIN,
) -> np.ndarray:
    """Plain-numpy twin of `clamp_outlier_clusters`."""
    if radius < 0:
        raise ValueError(f"radius must be >= 0, got {radius}")
    planes = np.asarray(planes, np.float32)
    if not planes.size:
        return planes.copy()
    s = radiance_scale(planes)
    t = np.sign(planes) * np.log1p(np.abs(planes.astype(np.float64)) / s)
    mean = _box_mean_reference(t, radius)
    std = np.sqrt(np.maximum(_box_mean_reference(t * t, radius) - mean * mean, 0.0))
    keep = (np.abs(t - mean) <= clip * std).astype(np.float64)
    n = np.maximum(_box_mean_reference(keep, radius), 1e-12)  # the centre of a window is never all out
    mean = np.where(n > 1e-9, _box_mean_reference(t * keep, radius) / n, mean)
    std = np.sqrt(np.maximum(_box_mean_reference(t * t * keep, radius) / n - mean * mean, 0.0))
    bound = k * std + margin
    clipped = np.clip(t, mean - bound, mean + bound)
    back = np.sign(clipped) * s * np.expm1(np.abs(clipped))
    return np.where(clipped == t, planes, back).astype(np.float32)


@numba.njit(inline="always", fastmath=True)
def _log_fast(v):
    """log(v) for finite float32 v >= 1, relative error ~1e-7 (Cephes logf polynomial). Vectorisable,
    unlike a call to logf: v = 2^e m with m in [sqrt(1/2), sqrt(2)), log v = e ln 2 + log m."""
    bits = float32_to_bits(v)
    e = np.float32((bits >> np.int32(23)) - np.int32(127))
    m = bits_to_float32((bits & np.int32(0x7FFFFF)) | np.int32(0x3F800000))  # [1, 2)
    big = m > np.float32(1.4142135623730951)
    m = m * np.float32(0.5) if big else m
    e = e + np.float32(1.0) if big else e
    f = m - np.float32(1.0)
    z = f * f
    p = np.float32(7.0376836292e-2)
    p = p * f - np.float32(1.1514610310e-1)
    p = p * f + np.float32(1.1676998740e-1)
    p = p * f - np.float32(1.2420140846e-1)
    p = p * f + np.float32(1.4249322787e-1)
    p = p * f - np.float32(1.6668057665e-1)
    p = p * f + np.float32(2.0000714765e-1)
    p = p * f - np.float32(2.4999993993e-1)
    p = p * f + np.float32(3.3333331174e-1)
    y = p * f * z - np.float32(2.12194440e-4) * e - np.float32(0.5) * z
    return f + y + np.float32(0.693359375) * e


ROBUST_BAND = 16  # rows per task of `_cluster_kernel`: running column sums over the band, 2r rows of halo


@numba.njit(inline="always")
def _box_rows(padded, radius, width, out):
    """out[x] = sum of padded[x .. x + 2r]: a row of width + 2r with r zeros each side, so the window
    is clipped to the frame. Shifted adds, two per pass over `out`, on views indexed from 0 (no
    negative-index fix-up): contiguous along x, vectorises."""
    first = padded[0:]
    for x in range(width):
        out[x] = first[x]
    for d in range(1, 2 * radius + 1, 2):
        a, b = padded[d:], padded[d + 1 :]
        for x in range(width):
            out[x] += a[x] + b[x]


@numba.njit(inline="always")
def _add_row(cols, t, keep, second, sign, width, pad):
    """cols[:, pad + x] += sign * [t, t^2] (first sweep) or sign * [keep, t keep, t^2 keep] (second)."""
    if second:
        c0, c1, c2 = cols[0, pad:], cols[1, pad:], cols[2, pad:]  # views: the loop vectorises
        for x in range(width):
            a, w = np.float64(t[x]), sign * np.float64(keep[x])
            c0[x] += w
            c1[x] += w * a
            c2[x] += w * a * a
    else:
        c0, c1 = cols[0, pad:], cols[1, pad:]
        for x in range(width):
            a = np.float64(t[x])
            c0[x] += sign * a
            c1[x] += sign * a * a


@numba.njit(parallel=True, cache=True, fastmath=True, error_model="numpy")
def _cluster_kernel(planes, s, radius, k, clip, margin, out):
    """Three sweeps over all channels: t (float32, fast log); box sums of [t, t^2] -> mean, std -> keep
    mask; box sums of [keep, t keep, t^2 keep] -> clipped mean, std -> clip. Box sums: float64 running
    column sums over bands of ROBUST_BAND rows, then 2r+1 shifted adds along x."""
    channels, height, width = planes.shape
    inv_s = np.float32(1.0 / s)
    t = np.empty((channels, height, width), np.float32)
    keep = np.empty((channels, height, width), np.uint8)
    inv_nx = np.empty(width)
    for x in range(width):
        inv_nx[x] = 1.0 / (min(x + radius, width - 1) - max(x - radius, 0) + 1)
    for row in numba.prange(channels * height):
        src, dst = planes[row // height, row % height], t[row // height, row % height]
        for x in range(width):
            v = src[x]
            a = _log_fast(np.float32(1.0) + abs(v) * inv_s)
            dst[x] = a if v >= 0 else -a
    bands = (height + ROBUST_BAND - 1) // ROBUST_BAND
    for second in range(2):
        for task in numba.prange(channels * bands):
            c, y0 = task // bands, (task % bands) * ROBUST_BAND
            cols = np.zeros((3, width + 2 * radius))  # running sums over the window's rows, r zeros each side
            box = np.empty((3, width))
            for y in range(max(0, y0 - radius), min(height, y0 + radius)):
                _add_row(cols, t[c, y], keep[c, y], second, 1.0, width, radius)
            for y in range(y0, min(height, y0 + ROBUST_BAND)):
                if y + radius < height:
                    _add_row(cols, t[c, y + radius], keep[c, y + radius], second, 1.0, width, radius)
                inv_ny = 1.0 / (min(y + radius, height - 1) - max(y - radius, 0) + 1)
                for q in range(3 if second else 2):
                    _box_rows(cols[q], radius, width, box[q])
                tr = t[c, y]
                if second == 0:
                    kr = keep[c, y]
                    for x in range(width):
                        ic = inv_nx[x] * inv_ny
                        m = box[0, x] * ic
                        d = np.sqrt(max(box[1, x] * ic - m * m, 0.0))
                        kr[x] = 1 if abs(tr[x] - m) <= clip * d else 0
                else:
                    clipped = box[0]  # reused: box[0] is read before it is overwritten
                    src, dst = planes[c, y], out[c, y]
                    changed = 0
                    for x in range(width):  # branch-free: vectorises
                        ic = inv_nx[x] * inv_ny
                        n = max(box[0, x] * ic, 1e-12)
                        w = ic / n  # one division: means of t keep and t^2 keep over the kept fraction
                        # No value kept: only when the window's std rounds to 0, all its t equal the first
                        # mean to rounding, and t itself (unchanged) is what the reference's fallback gives.
                        m = box[1, x] * w if n > 1e-9 else np.float64(tr[x])
                        d = np.sqrt(max(box[2, x] * w - m * m, 0.0))
                        bound = k * d + margin
                        a = np.float64(tr[x])
                        b = min(max(a, m - bound), m + bound)
                        clipped[x] = b
                        changed += b != a
                        dst[x] = src[x]
                    if changed:  # rarely clipped: expm1 only there
                        for x in range(width):
                            b = clipped[x]
                            if b != tr[x]:
                                e = s * np.expm1(abs(b))
                                dst[x] = e if b >= 0 else -e
                if y - radius >= 0:
                    _add_row(cols, t[c, y - radius], keep[c, y - radius], second, -1.0, width, radius)
