"""Block-wise weighted local linear regression of Choi et al. 2024 (sec. 3, eqs. 3-5, after Koskela et al.
2019 and Moon et al. 2015): `block_regression` = `block_solve` -> `block_reconstruct`, the numba kernels
by default and their plain-numpy twins with `reference=True`.

Normal equations are solved only at centre pixels on every `sparsity`-th row and column; each centre fits
a linear function of pair features x_i - x_c over its (2r+1)^2 window, and every pixel averages the
predictions of the centres whose window holds it (eq. 5). Pair weights have the form of Choi eq. 7.
Windows are clipped at the frame border (no padding), as in `service.kernels.window`.
"""

from __future__ import annotations

from collections.abc import Iterator

import numba
import numpy as np

from service.kernels.simd import (
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
from service.kernels.window import window_offsets
from service.regression.solve import cholesky_ridge_solve, solve_ridge_reference
from service.regression.terms import (
    EPS_SIGMA,
    EPS_VARIANCE,
    WEIGHT_FLOOR,
    BlockParams,
    PairTerms,
    centre_count,
    spatial_weights,
)


@numba.njit(inline="always", fastmath=True)
def _exp_neg(x):
    """exp(-x) for float32 x >= 0, vectorisable: 2^-m e^g (`simd.EXP_POLY`), relative error < 5e-7; x beyond
    `simd.EXP_NEG_LIMIT` gives exp(-EXP_NEG_LIMIT) (`simd.exp_neg` is the vector twin, bit for bit)."""
    xc = min(x, np.float32(EXP_NEG_LIMIT))
    m = np.floor(xc * np.float32(LOG2E) + np.float32(0.5))
    g = m * np.float32(LN2) - xc  # exp(-x) = 2^-m e^g, |g| <= ln2 / 2
    return bits_to_float32(float32_to_bits(exp_poly(g)) - (np.int32(m) << np.int32(23)))


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
    gram = np.zeros((hc, wc, g, k1, k1), np.float32)
    rhs = np.zeros((hc, wc, g, k1, m), np.float32)
    for rows, cols, pixel, weight, feats in _window_pairs(terms, params, hc, wc):
        y = target[(slice(None), *pixel)].reshape(g, m, *weight.shape)
        wf = feats * weight
        gram[rows, cols] += np.einsum("gkhw,glhw->hwgkl", wf, feats)
        rhs[rows, cols] += np.einsum("gkhw,gmhw->hwgkm", wf, y)
    return gram, rhs


def _window_pairs(terms: PairTerms, params: BlockParams, hc: int, wc: int) -> Iterator[tuple]:
    """The pairs of the numpy twins, one window offset at a time: (rows, cols) the centres (Hc x Wc grid
    slices) with an in-frame pixel at that offset, `pixel` the pixels' slices, `weight` their pair weights
    (h, w) and `feats` their pair features (G, K1, h, w), float32."""
    height, width = terms.sigma.shape
    s, r = params.sparsity, params.radius
    spatial = spatial_weights(params)
    for dy, dx in window_offsets(r):
        rows, cols = _valid_centres(hc, height, s, dy), _valid_centres(wc, width, s, dx)
        if rows is None or cols is None:
            continue
        centre, pixel = _offset_slices(rows, cols, s, dy, dx)
        weight = _pair_weight(terms, centre, pixel) * spatial[dy + r, dx + r] + np.float32(WEIGHT_FLOOR)
        yield rows, cols, pixel, weight, _pair_features(terms, centre, pixel)


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


LANE_CHUNK = 512  # centres processed together: a whole centre row up to 2048 px wide (fewer, longer loops)


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
    for rows, cols, pixel, weight, feats in _window_pairs(terms, params, hc, wc):
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
