"""The cross-regression's block regression (Choi 2024 eqs. 3-7) as one fused SIMD kernel per buffer.

`regress_packed` gives the same two pilots as `local_regression.block_regression` on
`cross_regression.buffer_terms` (whose plain-numpy twin, `block_regression(..., reference=True)`, is the
reference of the parity tests), with the same constants (EPS_SIGMA, EPS_VARIANCE, WEIGHT_FLOOR, the
ridge of `solve_ridge`). It is that computation reorganised for the CPU:

- Both buffers' inputs are packed once, in one pass, into phase planes (`local_regression`'s layout:
  pixel x = S q + phase at lane q + pad of plane `phase`), so the pixels that one window offset pairs
  with LANES consecutive centres of a centre row are LANES consecutive floats: one `simd.Vec`. The
  service packs straight from the radiance (`cross_regression.pack_buffers`, which takes the logs and
  variances on the way and writes each row with `pack_row`); `pack_cross_reference` is the numpy
  packing from given logs and variances.
- Per group of LANES centres, one pass reads the window from the planes once and writes each pair's
  terms (weight, eq. 7; normal, scaled colour (eq. 6) and albedo differences; target colour) to a
  scratch in pair order, summing the 10 moments of the shared normal features on the way; three more
  passes (one per colour channel) stream that scratch and sum the channel's 17 moments. Every
  accumulator is a Vec held in a register: no per-moment store, which is what bounds a
  loop-vectorised kernel. (Gathering from the 4 phase planes x 17 rows in every pass instead cost
  ~15% more.)
- The 61 moments are solved right there, in float64 on `simd.VecD` vectors (`_cholesky_solve`, the
  operations of `local_regression.cholesky_ridge_solve`), and a last pass adds each centre's weighted
  predictions (eq. 5), from the same scratch, into a one-row tile that stays in L1 and then into the
  numerator and denominator planes. Centre rows whose windows overlap are never run at the same time.
"""

from __future__ import annotations

import numba
import numpy as np

from service.stages.local_regression import (
    BlockParams,
    MomentLayout,
    centre_count,
    kernel_constants,
    normalise_phases,
    pad_lanes,
    phase_planes,
    spatial_weights,
    to_planes,
)
from service.stages.simd import (
    HALF,
    LANES,
    exp_neg,
    load,
    load_phase,
    narrow,
    splat,
    splat_d,
    sqrt,
    store,
    vmax,
    widen,
)

# Packed planes of both buffers (`cross_regression.pack_buffers`, `pack_cross_reference`): each buffer's
# log colour (3), its variance and sigma follow each other, so a buffer is named by its first log plane.
MASK, NORMAL, ALBEDO, BUFFER_A, BUFFER_B = 0, 1, 4, 7, 12
PLANES = 17
MOMENTS = 61  # 10 of the shared features (constant, normal) + 17 per colour channel
FEATURES = 6  # per colour channel: constant, 3 normal differences, scaled colour difference, albedo difference
# Rows of the per-pair scratch (`_pairs_pass`): weight, normal difference (3), then per colour channel
# the scaled colour difference u, the albedo difference a and the target colour t.
WEIGHT, DN, U, A, T = 0, 1, 4, 7, 10
PAIR_ROWS = 13


def regress_packed(planes: np.ndarray, width: int, params: BlockParams) -> tuple[np.ndarray, np.ndarray]:
    """The two cross-regression pilots (Choi 2024 sec. 4.1) by block regression, numba SIMD kernel.

    planes: both buffers' phase planes (S, PLANES, H, L) float32 of a frame `width` pixels wide, packed
    with the same params (`cross_regression.pack_buffers` from the radiance, or `pack_cross_reference`).
    params: window radius, sparsity and ridge (`sigma_position` as in `spatial_weights`).
    Returns (pilot_a, pilot_b), (3, H, W) float32 log colour: pilot_a regresses buffer B's log colour on
    buffer A's features and weights, pilot_b buffer A's on buffer B's."""
    return _regress(planes, width, BUFFER_A, BUFFER_B, params), _regress(planes, width, BUFFER_B, BUFFER_A, params)


def empty_planes(height: int, width: int, params: BlockParams) -> np.ndarray:
    """Uninitialised phase planes (S, PLANES, H, L) float32 of an H x W frame (`plane_lanes`)."""
    return np.empty((params.sparsity, PLANES, height, plane_lanes(width, params)), np.float32)


def plane_lanes(width: int, params: BlockParams) -> int:
    """L, the lanes of a phase plane row: the centre count rounded up to LANES, plus `pad_lanes` each side."""
    return -(-centre_count(width, params.sparsity) // LANES) * LANES + 2 * pad_lanes(params)


def pack_cross_reference(
    log_a: np.ndarray,
    variance_a: np.ndarray,
    log_b: np.ndarray,
    variance_b: np.ndarray,
    albedo: np.ndarray,
    normal: np.ndarray,
    params: BlockParams,
) -> np.ndarray:
    """Plain-numpy packing of both buffers into phase planes (S, PLANES, H, L) float32, the layout of
    `cross_regression.pack_buffers`: [inside-frame mask, normal (3), albedo (3), log_a (3), variance_a,
    sigma_a, log_b (3), variance_b, sigma_b], zeros outside the frame.

    log_a, log_b: (3, H, W) float32 log colour; variance_a, variance_b: (H, W) float32 >= 0; albedo,
    normal: (H, W, 3) float32 frame layers."""
    height, width = variance_a.shape
    parts = [np.ones((1, height, width), np.float32), to_planes(normal), to_planes(albedo)]
    for log, variance in ((log_a, variance_a), (log_b, variance_b)):
        parts += [log, variance[None], np.sqrt(variance)[None]]
    split = phase_planes(np.concatenate(parts).astype(np.float32), params)  # lanes: centres + 1
    lanes = plane_lanes(width, params)
    out = np.zeros((*split.shape[:3], lanes), np.float32)
    out[..., : min(lanes, split.shape[3])] = split[..., :lanes]
    return out


@numba.njit(inline="always")
def pack_row(log_a, log_b, r, var_a, var_b, albedo, normal, pad, out, y):  # pragma: no cover
    """Frame row y into the phase planes out (S, PLANES, H, L) float32 (layout of `pack_cross_reference`),
    zeros in the pad lanes. log_a, log_b: (3, R, W) float32 log colour rows, row y at [:, r];
    var_a, var_b: (W,) float32 the row's variance; albedo, normal: (3 W,) float32 the row of the layers,
    interleaved. At sparsity 4 (the paper's) whole blocks of 4 LANES pixels go as vectors (`_split_block`),
    the other pixels one value at a time."""
    s = out.shape[0]
    width = var_a.shape[0]
    for p in range(s):
        count = (width - p + s - 1) // s if p < width else 0
        for k in range(PLANES):
            row = out[p, k, y]
            row[:pad] = 0.0
            row[pad + count :] = 0.0
    done = width // (4 * LANES) * 4 * LANES if s == 4 else 0  # pixels in whole blocks
    for x in range(0, done, 4 * LANES):
        _split_block(log_a, log_b, r, var_a, var_b, albedo, normal, x, out, y, pad + x // 4)
    for p in range(s):
        count = (width - p + s - 1) // s if p < width else 0
        for j in range(done // s, count):
            x, q = p + s * j, pad + j
            out[p, MASK, y, q] = 1.0
            for c in range(3):
                out[p, NORMAL + c, y, q] = normal[3 * x + c]
                out[p, ALBEDO + c, y, q] = albedo[3 * x + c]
                out[p, BUFFER_A + c, y, q] = log_a[c, r, x]
                out[p, BUFFER_B + c, y, q] = log_b[c, r, x]
            out[p, BUFFER_A + 3, y, q] = var_a[x]
            out[p, BUFFER_A + 4, y, q] = np.sqrt(var_a[x])
            out[p, BUFFER_B + 3, y, q] = var_b[x]
            out[p, BUFFER_B + 4, y, q] = np.sqrt(var_b[x])


@numba.njit(inline="always")
def _split_block(log_a, log_b, r, var_a, var_b, albedo, normal, x, out, y, q):  # pragma: no cover
    """Pixels x ... x + 4 LANES - 1 of `pack_row` (its arguments) at sparsity 4: phase p's LANES of each plane
    into lanes q ... of out[p, plane, y], every input read in whole vectors (`load_phase`)."""
    one = splat(np.float32(1.0))
    for p in range(4):
        store(out, (p, MASK, y, q), one)
    for c in range(3):
        _split4(log_a[c, r], x, False, out, BUFFER_A + c, y, q)
        _split4(log_b[c, r], x, False, out, BUFFER_B + c, y, q)
    _split4(var_a, x, False, out, BUFFER_A + 3, y, q)
    _split4(var_a, x, True, out, BUFFER_A + 4, y, q)  # sigma
    _split4(var_b, x, False, out, BUFFER_B + 3, y, q)
    _split4(var_b, x, True, out, BUFFER_B + 4, y, q)
    _split4x3(normal, 3 * x, out, NORMAL, y, q)
    _split4x3(albedo, 3 * x, out, ALBEDO, y, q)


@numba.njit(inline="always")
def _split4(row, x, root, out, plane, y, q):  # pragma: no cover
    """Values x ... x + 4 LANES - 1 of row (N,) float32 into out[p, plane, y, q ...] by phase p = x mod 4;
    their square roots if root. (Each vector is written out by hand: a loop over a tuple of vectors indexes
    it at run time, which compiled to code as slow as the scalar loop.)"""
    v0, v1, v2, v3 = (load_phase(row, (x,), 4, 0), load_phase(row, (x,), 4, 1), load_phase(row, (x,), 4, 2),
                      load_phase(row, (x,), 4, 3))  # fmt: skip
    store(out, (0, plane, y, q), sqrt(v0) if root else v0)
    store(out, (1, plane, y, q), sqrt(v1) if root else v1)
    store(out, (2, plane, y, q), sqrt(v2) if root else v2)
    store(out, (3, plane, y, q), sqrt(v3) if root else v3)


@numba.njit(inline="always")
def _split4x3(row, i, out, plane, y, q):  # pragma: no cover
    """The 4 LANES pixels of 3 interleaved channels from row[i] on (row (3 N,) float32) into
    out[p, plane + c, y, q ...] by channel c and phase p (written out by hand, as in `_split4`)."""
    store(out, (0, plane, y, q), load_phase(row, (i,), 12, 0))
    store(out, (0, plane + 1, y, q), load_phase(row, (i,), 12, 1))
    store(out, (0, plane + 2, y, q), load_phase(row, (i,), 12, 2))
    store(out, (1, plane, y, q), load_phase(row, (i,), 12, 3))
    store(out, (1, plane + 1, y, q), load_phase(row, (i,), 12, 4))
    store(out, (1, plane + 2, y, q), load_phase(row, (i,), 12, 5))
    store(out, (2, plane, y, q), load_phase(row, (i,), 12, 6))
    store(out, (2, plane + 1, y, q), load_phase(row, (i,), 12, 7))
    store(out, (2, plane + 2, y, q), load_phase(row, (i,), 12, 8))
    store(out, (3, plane, y, q), load_phase(row, (i,), 12, 9))
    store(out, (3, plane + 1, y, q), load_phase(row, (i,), 12, 10))
    store(out, (3, plane + 2, y, q), load_phase(row, (i,), 12, 11))


def _regress(planes: np.ndarray, width: int, guide: int, target: int, params: BlockParams) -> np.ndarray:
    """One pilot from the packed planes of a frame `width` pixels wide: the buffer at plane `guide` gives
    features and weights, the one at `target` the colours. Returns (3, H, W) float32."""
    s, _, height, lanes = planes.shape
    # A window's predictions span lanes c - pad ... c + pad + LANES - 1 of a plane; `_predict_pass` adds
    # them in whole vectors from there, so the sums carry that many lanes (rounded to vectors) more.
    extra = -(-(2 * pad_lanes(params) + LANES) // LANES) * LANES
    num = np.zeros((s, 3, height, lanes + extra), np.float32)
    den = np.zeros((s, height, lanes + extra), np.float32)
    ridge = np.array([params.ridge_relative, params.ridge_absolute])
    counts = np.array([centre_count(height, s), centre_count(width, s)], np.int64)
    _cross_block_kernel(planes, guide, target, spatial_weights(params), params.radius, counts, kernel_constants(),
                        ridge, num, den)  # fmt: skip
    out = np.empty((3, height, width), np.float32)
    normalise_phases(num, den, pad_lanes(params), out)
    return out


@numba.njit(parallel=True, cache=True, fastmath=True, error_model="numpy")
def _cross_block_kernel(planes, guide, target, spatial, radius, counts, consts, ridge, num, den):  # pragma: no cover
    """Every centre row's regression and its weighted predictions into num (S, 3, H, L'), den (S, H, L'),
    which have more lanes than the planes (L' > L, see `_regress`).

    Centre rows go in chunks of `rows` consecutive ones, which span more than a window: chunks two apart
    never add into the same pixel, so the even chunks run in parallel, then the odd ones. Within a chunk
    each group of LANES centre columns goes down the rows, so that a window shares all but s pixel rows
    with the last one, still in L2 (at 720p ~25% faster than running rows a window apart over the whole
    width, which reread every window from memory)."""
    s, height = planes.shape[0], planes.shape[2]
    hc, wc = counts[0], counts[1]
    pad = -(-radius // s)
    rows = (2 * radius) // s + 1
    chunks = -(-hc // rows)
    side = 2 * radius + 1
    for parity in range(2):
        for i in numba.prange((chunks - parity + 1) // 2):
            first = (parity + 2 * i) * rows
            pairs = np.empty((side * side, PAIR_ROWS, LANES), np.float32)  # ~220 KB: L2
            moments = np.empty((MOMENTS, LANES), np.float32)
            gram = np.empty((3, FEATURES, FEATURES, LANES))
            rhs = np.empty((3, FEATURES, LANES))
            coefs = np.empty((3 * FEATURES, LANES), np.float32)
            tile = np.empty((s, 4, num.shape[3] - planes.shape[3]), np.float32)  # see _regress
            for q in range(0, wc, LANES):
                c = pad + q
                for r in range(first, min(first + rows, hc)):
                    cy = r * s
                    y0, y1 = max(cy - radius, 0), min(cy + radius + 1, height)
                    _pairs_pass(planes, guide, target, spatial, radius, consts, cy, y0, y1, c, pairs, moments)
                    for ch in range(3):
                        _channel_pass(ch, pairs[: (y1 - y0) * side], moments)
                    _solve(moments, ridge, gram, rhs, coefs)
                    _predict_pass(s, radius, y0, y1, c, pairs, coefs, tile, num, den)


@numba.njit(inline="always", fastmath=True)
def _pairs_pass(planes, guide, target, spatial, radius, consts, cy, y0, y1, c, pairs, moments):  # pragma: no cover
    """The window (rows y0 ... y1 - 1) of LANES centres, read from the planes once: every pair's terms into
    pairs (offsets, PAIR_ROWS, LANES): the weight (eq. 7, times the spatial factor, plus WEIGHT_FLOOR, 0
    outside the frame), the normal difference dn and per colour channel u = (y_i - y_c) / (sigma_i +
    sigma_c + eps) (eq. 6), the albedo difference and the target colour; and the shared moments
    sum w [1, dn] [1, dn]^T (upper triangle row by row) into moments[0:10]. The later passes stream the
    scratch in order instead of gathering from 4 phase planes x 17 rows again."""
    s = planes.shape[0]
    eps_sigma, eps_variance, floor = consts[0], consts[1], consts[2]  # `local_regression.kernel_constants`
    mask_c = load(planes, (0, MASK, cy, c))
    g0, g1, g2 = _centres3(planes, guide, cy, c)
    var_c, sig_c = load(planes, (0, guide + 3, cy, c)) + eps_variance, load(planes, (0, guide + 4, cy, c)) + eps_sigma
    n0, n1, n2 = _centres3(planes, NORMAL, cy, c)
    a0, a1, a2 = _centres3(planes, ALBEDO, cy, c)
    zero = splat(np.float32(0.0))
    m = (zero, zero, zero, zero, zero, zero, zero, zero, zero, zero)
    for y in range(y0, y1):
        o = (y - y0) * (2 * radius + 1)
        p, x = (-radius) % s, c + (-radius) // s
        for dx in range(-radius, radius + 1):
            d0 = load(planes, (p, guide, y, x)) - g0
            d1 = load(planes, (p, guide + 1, y, x)) - g1
            d2 = load(planes, (p, guide + 2, y, x)) - g2
            ratio = (d0 * d0 + d1 * d1 + d2 * d2) / (load(planes, (p, guide + 3, y, x)) + var_c)
            sw = spatial[y - cy + radius, dx + radius]
            w = (exp_neg(ratio) * sw + floor) * (load(planes, (p, MASK, y, x)) * mask_c)
            scale = np.float32(1.0) / (load(planes, (p, guide + 4, y, x)) + sig_c)
            e0 = load(planes, (p, NORMAL, y, x)) - n0
            e1 = load(planes, (p, NORMAL + 1, y, x)) - n1
            e2 = load(planes, (p, NORMAL + 2, y, x)) - n2
            for row, value in ((WEIGHT, w), (DN, e0), (DN + 1, e1), (DN + 2, e2), (U, d0 * scale),
                               (U + 1, d1 * scale), (U + 2, d2 * scale), (A, load(planes, (p, ALBEDO, y, x)) - a0),
                               (A + 1, load(planes, (p, ALBEDO + 1, y, x)) - a1),
                               (A + 2, load(planes, (p, ALBEDO + 2, y, x)) - a2), (T, load(planes, (p, target, y, x))),
                               (T + 1, load(planes, (p, target + 1, y, x))),
                               (T + 2, load(planes, (p, target + 2, y, x)))):  # fmt: skip
                store(pairs, (o, row, 0), value)
            w0, w1, w2 = w * e0, w * e1, w * e2
            m = (m[0] + w, m[1] + w0, m[2] + w1, m[3] + w2, m[4] + w0 * e0, m[5] + w0 * e1, m[6] + w0 * e2,
                 m[7] + w1 * e1, m[8] + w1 * e2, m[9] + w2 * e2)  # fmt: skip
            o, p = o + 1, p + 1
            if p == s:
                p, x = 0, x + 1
    for e in range(10):
        store(moments, (e, 0), m[e])


@numba.njit(inline="always", fastmath=True)
def _channel_pass(ch, pairs, moments):  # pragma: no cover
    """Colour channel ch's 17 moments from the pair terms into moments[10 + 17 ch ...]: sum w u [1, dn, u],
    w a [1, dn, u, a] and the right-hand side sum w t [1, dn, u, a]."""
    zero = splat(np.float32(0.0))
    m = (zero, zero, zero, zero, zero, zero, zero, zero, zero, zero, zero, zero, zero, zero, zero, zero, zero)
    for o in range(pairs.shape[0]):
        w, u, a = load(pairs, (o, WEIGHT, 0)), load(pairs, (o, U + ch, 0)), load(pairs, (o, A + ch, 0))
        e0, e1, e2 = load(pairs, (o, DN, 0)), load(pairs, (o, DN + 1, 0)), load(pairs, (o, DN + 2, 0))
        wu, wa, wt = w * u, w * a, w * load(pairs, (o, T + ch, 0))
        m = (m[0] + wu, m[1] + wu * e0, m[2] + wu * e1, m[3] + wu * e2, m[4] + wu * u,
             m[5] + wa, m[6] + wa * e0, m[7] + wa * e1, m[8] + wa * e2, m[9] + wa * u, m[10] + wa * a,
             m[11] + wt, m[12] + wt * e0, m[13] + wt * e1, m[14] + wt * e2, m[15] + wt * u,
             m[16] + wt * a)  # fmt: skip
    k = 10 + 17 * ch
    for e in range(17):
        store(moments, (k + e, 0), m[e])


@numba.njit(inline="always")
def _centres3(planes, first, cy, c):  # pragma: no cover
    """The LANES centres' values (centre row cy, lanes c ...) of planes first, first + 1 and first + 2."""
    return load(planes, (0, first, cy, c)), load(planes, (0, first + 1, cy, c)), load(planes, (0, first + 2, cy, c))


def _moment_entries() -> np.ndarray:
    """(kind, row, column) of each moment in the order the passes store them, which is
    `local_regression.MomentLayout.moment_entries` of the cross layout (3 guides, 3 shared features, 3 groups
    of 2, 3 targets): kind 0 for the shared ones (in every channel's system), ch + 1 for channel ch's;
    column FEATURES for the right-hand side."""
    _, _, dest = MomentLayout(3, 3, 3, 2, 3).moment_entries()
    entries = [(0 if kind == 0 else g + 1, p, q if kind < 2 else FEATURES) for kind, g, p, q in dest]
    assert len(entries) == MOMENTS
    return np.array(entries, np.int64)


MOMENT_ENTRIES = _moment_entries()


@numba.njit(inline="always", fastmath=True)
def _solve(moments, ridge, gram, rhs, coefs):  # pragma: no cover
    """moments (MOMENTS, LANES) float32 -> coefs (3 * FEATURES, LANES) float32: per colour channel the
    ridge solve of `solve_ridge` in float64, on the LANES centres as vectors (`_cholesky_solve`).
    gram (3, FEATURES, FEATURES, LANES), rhs (3, FEATURES, LANES): float64 scratch."""
    for e in range(MOMENTS):
        kind, row, col = MOMENT_ENTRIES[e, 0], MOMENT_ENTRIES[e, 1], MOMENT_ENTRIES[e, 2]
        value = load(moments, (e, 0))
        lo, hi = widen(value, 0), widen(value, 1)
        for ch in range(3):
            if kind != 0 and ch != kind - 1:
                continue
            if col == FEATURES:
                store(rhs, (ch, row, 0), lo)
                store(rhs, (ch, row, HALF), hi)
            else:
                store(gram, (ch, col, row, 0), lo)  # the lower triangle, which the Cholesky reads
                store(gram, (ch, col, row, HALF), hi)
    for ch in range(3):
        for h in (0, HALF):
            _cholesky_solve(gram[ch], rhs[ch], ridge[0], ridge[1], h)
        for k in range(FEATURES):
            store(coefs, (ch * FEATURES + k, 0), narrow(load(rhs, (ch, k, 0)), load(rhs, (ch, k, HALF))))


@numba.njit(inline="always", fastmath=True)
def _cholesky_solve(a, b, ridge_relative, ridge_absolute, h):  # pragma: no cover
    """`local_regression.cholesky_ridge_solve` (constant feature 0, one right-hand side) on VecD lanes
    h ... h + HALF - 1: a (FEATURES, FEATURES, LANES) float64 lower triangle of X^T W X, b (FEATURES, LANES)
    X^T W Y -> beta, in place; the same operations in the same order."""
    scale = vmax(load(a, (0, 0, h)), splat_d(1e-30))
    store(a, (0, 0, h), scale)
    least = scale * ridge_absolute  # pivot floor
    for j in range(1, FEATURES):
        d = load(a, (j, j, h))
        store(a, (j, j, h), d + (vmax(d, splat_d(0.0)) * ridge_relative + least))
    for j in range(FEATURES):
        d = load(a, (j, j, h))
        for p in range(j):
            d -= load(a, (j, p, h)) * load(a, (j, p, h))
        inv = 1.0 / sqrt(vmax(d, least))
        store(a, (j, j, h), inv)  # the diagonal holds 1 / L_jj
        for i in range(j + 1, FEATURES):
            v = load(a, (i, j, h))
            for p in range(j):
                v -= load(a, (i, p, h)) * load(a, (j, p, h))
            store(a, (i, j, h), v * inv)
    for i in range(FEATURES):
        v = load(b, (i, h))
        for p in range(i):
            v -= load(a, (i, p, h)) * load(b, (p, h))
        store(b, (i, h), v * load(a, (i, i, h)))
    for i in range(FEATURES - 1, -1, -1):
        v = load(b, (i, h))
        for p in range(i + 1, FEATURES):
            v -= load(a, (p, i, h)) * load(b, (p, h))
        store(b, (i, h), v * load(a, (i, i, h)))


@numba.njit(inline="always", fastmath=True)
def _predict_pass(s, radius, y0, y1, c, pairs, coefs, tile, num, den):  # pragma: no cover
    """Eq. 5's sums: num[channel] += w (alpha + beta . x) and den += w at every pixel of the window, the
    pair terms x from the scratch of `_pairs_pass`; s the sparsity (phase planes). Each window row is
    summed in tile (S, 4, TW) float32 (channels, then the weight; lane j is plane lane c - pad + j),
    which stays in L1, and then added to num and den in TW / LANES vectors per plane: adding every pair
    straight into the planes missed L1 on most of them (~25% of the kernel's time at 720p)."""
    first = c - (-(-radius // s))  # plane lane of the window's leftmost pixels (tile lane 0)
    zero = splat(np.float32(0.0))
    o = 0
    for y in range(y0, y1):
        for p in range(s):
            for k in range(4):
                for v in range(0, tile.shape[2], LANES):
                    store(tile, (p, k, v), zero)
        p, j = (-radius) % s, 0
        for _ in range(2 * radius + 1):  # phases interleaved: a vector is re-read s offsets after its store
            w = load(pairs, (o, WEIGHT, 0))
            e0, e1, e2 = load(pairs, (o, DN, 0)), load(pairs, (o, DN + 1, 0)), load(pairs, (o, DN + 2, 0))
            for ch in range(3):
                k = ch * FEATURES
                pred = load(coefs, (k, 0)) + load(coefs, (k + 1, 0)) * e0 + load(coefs, (k + 2, 0)) * e1
                pred += load(coefs, (k + 3, 0)) * e2
                pred += load(coefs, (k + 4, 0)) * load(pairs, (o, U + ch, 0))
                pred += load(coefs, (k + 5, 0)) * load(pairs, (o, A + ch, 0))
                store(tile, (p, ch, j), load(tile, (p, ch, j)) + w * pred)
            store(tile, (p, 3, j), load(tile, (p, 3, j)) + w)
            o, p = o + 1, p + 1
            if p == s:
                p, j = 0, j + 1
        for p in range(s):
            for v in range(0, tile.shape[2], LANES):
                x = first + v
                for ch in range(3):
                    store(num, (p, ch, y, x), load(num, (p, ch, y, x)) + load(tile, (p, ch, v)))
                store(den, (p, y, x), load(den, (p, y, x)) + load(tile, (p, 3, v)))
