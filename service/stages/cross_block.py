"""The cross-regression's block regression (Choi 2024 eqs. 3-7) as one fused SIMD kernel for both buffers.

`regress_packed` gives the same two pilots as `regression.block.block_regression` on
`cross_regression.buffer_terms` (whose plain-numpy twin, `block_regression(..., reference=True)`, is the
reference of the parity tests), with the same constants (EPS_SIGMA, EPS_VARIANCE, WEIGHT_FLOOR, the
ridge of `solve_ridge`). It is that computation reorganised for the CPU:

- Both buffers' inputs are packed once, in one pass, into phase planes (`service.regression`'s layout:
  pixel x = S q + phase at lane q + pad of plane `phase`), so the pixels that one window offset pairs
  with LANES consecutive centres of a centre row are LANES consecutive floats: one `simd.Vec`. The
  service packs straight from the radiance (`cross_regression.pack_buffers`, which takes the logs and
  variances on the way and writes each row with `pack_row`); `pack_cross_reference` is the numpy
  packing from given logs and variances.
- Both regressions run in one kernel (pilot_a: buffer A's features and weights fitted to buffer B's
  colours; pilot_b the reverse). Per group of LANES centres and window row, one pass reads the row from
  the planes once and writes each pair's terms for both (per buffer the weight, eq. 7, the colour scale of
  eq. 6 and the log colour differences; the normal and albedo differences, shared) to a scratch in pair
  order; passes over that row's terms (~17 KB, still in L1) add the 10 moments of the shared normal
  features and each colour channel's 17 moments of each regression. Every accumulator is a Vec held in a
  register within a pass: no per-moment store per pair, which is what bounds a loop-vectorised kernel.
  The target colour enters relative to its centre value, which is the other buffer's colour difference
  already in the scratch. The ridge leaves the constant feature alone, so this is the same fit with the
  intercept less that value, added back after the solve.
- The 61 moments of each regression are solved right there, in float64 on `simd.VecD` vectors
  (`_cholesky_solve`, the operations of `regression.solve.cholesky_ridge_solve`), and a last pass adds
  each centre's weighted predictions of both regressions (eq. 5), from the window's scratch, into a
  strip of the pixel rows that the lane group's chunk of centre rows covers (each row is in L1 while a
  window row is added), and the strip into the numerator and denominator planes once per chunk. Centre
  rows whose windows overlap are never run at the same time.

One module of more than 600 lines: the packed layout's constants (PLANES, MOMENTS, the scratch
rows) and the passes that read them change together.
"""

from __future__ import annotations

import numba
import numpy as np

from service.kernels.simd import (
    HALF,
    LANES,
    aligned_empty,
    exp_neg,
    jit_aligned_empty,
    load,
    load_phase,
    narrow,
    phase_blocks,
    prefetch,
    splat,
    splat_d,
    sqrt,
    store,
    vmax,
    widen,
)
from service.regression.block import MomentLayout, kernel_constants, normalise_phases, pad_lanes, phase_planes
from service.regression.planes import to_planes
from service.regression.terms import BlockParams, centre_count, spatial_weights

# Packed planes of both buffers (`cross_regression.pack_buffers`, `pack_cross_reference`): each buffer's
# log colour (3), its variance and sigma follow each other, so a buffer is named by its first log plane.
MASK, NORMAL, ALBEDO, BUFFER_A, BUFFER_B = 0, 1, 4, 7, 12
PLANES = 17
MOMENTS = 61  # 10 of the shared features (constant, normal) + 17 per colour channel
FEATURES = 6  # per colour channel: constant, 3 normal differences, scaled colour difference, albedo difference
# Rows of the per-pair scratch (`_pairs_pass`), shared by both regressions: per buffer the weight and the
# colour scale, then per buffer and colour channel the log colour difference, then the normal and albedo
# differences (3 each).
WEIGHT, SCALE, D, DN, DA = 0, 2, 4, 10, 13
PAIR_ROWS = 16


def regress_packed(planes: np.ndarray, width: int, params: BlockParams) -> tuple[np.ndarray, np.ndarray]:
    """The two cross-regression pilots (Choi 2024 sec. 4.1) by block regression, numba SIMD kernel.

    planes: both buffers' phase planes (S, PLANES, H, L) float32 of a frame `width` pixels wide, packed
    with the same params (`cross_regression.pack_buffers` from the radiance, or `pack_cross_reference`).
    params: window radius, sparsity and ridge (`sigma_position` as in `spatial_weights`).
    Returns (pilot_a, pilot_b), (3, H, W) float32 log colour: pilot_a regresses buffer B's log colour on
    buffer A's features and weights, pilot_b buffer A's on buffer B's."""
    num, den = regress_sums(planes, width, params)
    pilots = np.empty((2, 3, planes.shape[2], width), np.float32)
    for b in range(2):
        normalise_phases(num[b], den[b], pad_lanes(params), pilots[b])
    return pilots[0], pilots[1]


def regress_sums(
    planes: np.ndarray, width: int, params: BlockParams, tasks: int | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Eq. 5's sums of both regressions before the division (`regress_packed`'s arguments): num
    (2, S, 3, H, L') and den (2, S, H, L') float32 phase planes, first index the regression (0: pilot_a,
    1: pilot_b), pixel x of row y at [.., x % S, .., y, pad + x // S] (`normalise_phases` divides them),
    L' >= L. tasks: bands of centre rows run in parallel (`centre_bands`), default one per numba thread;
    the sums do not depend on it."""
    s, _, height, lanes = planes.shape
    # A window's predictions span lanes c - pad ... c + pad + LANES - 1 of a plane; `_group_rows` adds
    # them in whole vectors from there (lane q of group q on), so the sums carry that many lanes (rounded
    # to vectors) more. Rows of a whole number of vectors from a 64-byte boundary: each of those vectors
    # is one cache line.
    extra = -(-(2 * pad_lanes(params) + LANES) // LANES) * LANES
    total = -(-(lanes + extra) // LANES) * LANES
    num = aligned_empty((2, s, 3, height, total))  # zeroed by the kernel, just before first use
    den = aligned_empty((2, s, height, total))
    ridge = np.array([params.ridge_relative, params.ridge_absolute])
    counts = np.array([centre_count(height, s), centre_count(width, s)], np.int64)
    bands = centre_bands(int(counts[0]), params, numba.get_num_threads() if tasks is None else tasks)
    spatial = spatial_weights(params)
    _cross_block_kernel(planes, spatial, params.radius, counts, kernel_constants(), ridge, bands, extra, num, den)
    return num, den


def centre_bands(centre_rows: int, params: BlockParams, tasks: int) -> np.ndarray:
    """The centre rows 0 ... centre_rows - 1 as at most `tasks` bands (B, 2) int64 of [first, end) rows, in
    order, as even as may be, with a gap of `band_gap` rows between neighbours: bands whose windows never
    share a pixel row, however far each has got, and each at least as long as a gap (so that the gaps'
    windows never share one either). One band when the rows are too few for two."""
    gap = band_gap(params)
    count = max(1, min(tasks, (centre_rows + gap) // (2 * gap + 1)))
    sizes = np.full(count, (centre_rows - (count - 1) * gap) // count, np.int64)
    sizes[: (centre_rows - (count - 1) * gap) % count] += 1
    first = np.concatenate([[0], np.cumsum(sizes + gap)[:-1]])
    return np.stack([first, first + sizes], axis=1)


def band_gap(params: BlockParams) -> int:
    """The fewest centre rows between two bands whose windows share no pixel row: the next band's first
    window row, s (end + gap) - radius, lies past the last one of this band, s (end - 1) + radius."""
    return -(-(2 * params.radius + 1) // params.sparsity) - 1


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
    done = phase_blocks(width, s)
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


@numba.njit(parallel=True, cache=True, fastmath=True, error_model="numpy")
def _cross_block_kernel(planes, spatial, radius, counts, consts, ridge, bands, tw, num, den):  # pragma: no cover
    """Every centre row's two regressions and their weighted predictions into num (2, S, 3, H, L'), den
    (2, S, H, L'), first index the regression (0: buffer A's features and weights fitted to buffer B's
    colours, 1: the reverse); L' > L, see `regress_sums`. bands (B, 2): `centre_bands`. tw: the strip width
    TW, lanes (`regress_sums`' extra lanes).

    The bands run in parallel, each one chunk of `rows` centre rows after the other, top to bottom; within
    a chunk each group of LANES centre columns goes down the rows (`_group_rows`), so that a window shares
    all but s pixel rows with the last one, still in L2 (rows a window apart over the whole width would
    reread every window from memory), and a chunk finds the sums of the rows it shares with the one before
    still in cache. Then the gaps between the bands, which share rows with both: their lane groups in
    parallel, groups TW / LANES apart at a time (strip width TW: such groups share no lane).

    Each chunk zeroes the sums of the rows that it is the first to reach (the band's last chunk: up to the
    next band's first window row, which covers the gap's rows) just before first use, the lanes of each
    group as it starts (zeroing all the sums first would send them to memory before the first addition
    reads them back)."""
    s, height = planes.shape[0], planes.shape[2]
    wc = counts[1]
    rows = (2 * radius) // s + 1  # a window's worth (two: no clear change at 720p); > band_gap: a gap fits a strip
    for band in numba.prange(bands.shape[0]):
        start, end = bands[band, 0], bands[band, 1]
        z1 = max(start * s - radius, 0)  # pixel rows zeroed so far end here
        for first in range(start, end, rows):
            last = min(first + rows, end)
            z0, z1 = z1, min((last - 1) * s + radius + 1, height)
            if last == end:
                z1 = height if band + 1 == bands.shape[0] else bands[band + 1, 0] * s - radius
            zeroed = 0
            for q in range(0, wc, LANES):
                lanes = num.shape[4] if q + LANES >= wc else q + tw  # this group adds into lanes q ... q + TW - 1
                _zero_lanes(num, den, z0, z1, zeroed, lanes)
                zeroed = lanes
                _group_rows(planes, spatial, radius, consts, ridge, q, first, last, tw, rows, num, den)
    colours, parts = tw // LANES, bands.shape[0]
    groups = -(-wc // LANES)
    for colour in range(colours):
        for item in numba.prange((bands.shape[0] - 1) * parts):  # a gap's groups of this colour, in parts
            gap, part = item // parts, item % parts
            for g in range(colour + colours * part, groups, colours * parts):
                _group_rows(planes, spatial, radius, consts, ridge, g * LANES, bands[gap, 1], bands[gap + 1, 0],
                            tw, rows, num, den)  # fmt: skip


@numba.njit(inline="always")
def _scratch(radius, s, tw, rows):  # pragma: no cover
    """`_group_rows`' scratch (new arrays) for chunks of up to `rows` centre rows: (pairs (side^2, PAIR_ROWS,
    LANES) ~300 KB at radius 8, moments (2, MOMENTS, LANES), gram (3, FEATURES, FEATURES, LANES) float64,
    rhs (3, FEATURES, LANES) float64, coefs (2, 3 FEATURES, LANES), strip (R, 2, S, 4, tw) with R the pixel
    rows that a chunk's windows cover, ~135 KB at radius 8), float32 unless said."""
    side = 2 * radius + 1
    empty = jit_aligned_empty
    return (empty((side * side, PAIR_ROWS, LANES), np.float32), empty((2, MOMENTS, LANES), np.float32),
            empty((3, FEATURES, FEATURES, LANES), np.float64), empty((3, FEATURES, LANES), np.float64),
            empty((2, 3 * FEATURES, LANES), np.float32),
            empty(((rows - 1) * s + side, 2, s, 4, tw), np.float32))  # fmt: skip


@numba.njit(fastmath=True, error_model="numpy")
def _group_rows(planes, spatial, radius, consts, ridge, q, first, last, tw, rows, num, den):  # pragma: no cover
    """Centre columns q ... q + LANES - 1 (a lane group) of centre rows first ... last - 1, one row after the
    other: both regressions' moments (`_pairs_pass`, `_shared_pass`, `_channel_pass`), their solves and
    predictions (`_predict_row`) into the strip of the pixel rows their windows cover, which is then added
    to num and den. tw, rows: the strip width and the most centre rows of a chunk, for the scratch
    (`_scratch`), allocated here: its trailing sizes are constants in this function, so the compiler folds
    the element offsets, which it cannot for arrays passed in.

    A function of its own, called from the kernel's two parallel loops, not inlined into them: numba's
    parallel passes take time superlinear in the size of a parallel loop's body, and inlined it was
    compiled twice (a cold compile of the kernel took 3x as long).

    The strip takes each pixel row's sums over all the chunk's centre rows, so num and den are read and
    written once per chunk, not once per centre row whose window covers the row.

    The passes take whole scratch arrays and a first index (window row o0 of pairs, regression b), never a
    slice: numba counts the references of every view it makes, an atomic increment and decrement by call
    per view, which per window row would be a measurable share of the kernel.

    While a window row's moments are summed, the plane lines of the next row are prefetched: they come from
    L2 (a window shares all but s rows with the last one), and the pair pass would wait for them."""
    pairs, moments, gram, rhs, coefs, strip = _scratch(radius, planes.shape[0], tw, rows)
    s, height = planes.shape[0], planes.shape[2]
    c = -(-radius // s) + q  # plane lane of the first centre
    first_lane = q  # of the windows' leftmost pixels, c - pad (strip lane 0; a row: 20 lanes at the paper's window)
    side = 2 * radius + 1
    zero = splat(np.float32(0.0))
    top, bottom = max(first * s - radius, 0), min((last - 1) * s + radius + 1, height)  # the strip's rows
    for y in range(top, bottom):
        for b in range(2):
            for p in range(s):
                for k in range(4):
                    for v in range(0, strip.shape[4], LANES):
                        store(strip, (y - top, b, p, k, v), zero)
    for r in range(first, last):
        cy = r * s
        y0, y1 = max(cy - radius, 0), min(cy + radius + 1, height)
        for e in range(MOMENTS):
            store(moments, (0, e, 0), zero)
            store(moments, (1, e, 0), zero)
        for y in range(y0, y1):  # a window row's terms (~17 KB) are summed while still in L1
            o0 = (y - y0) * side
            _pairs_pass(planes, spatial, radius, consts, cy, y, c, pairs, o0)
            if y + 1 < y1:  # the next window row's plane lines, on their way from L2 while this row is summed
                for p in range(s):
                    for k in range(PLANES):
                        prefetch(planes, (p, k, y + 1, first_lane))
                        prefetch(planes, (p, k, y + 1, first_lane + LANES))
            for b in range(2):
                _shared_pass(b, pairs, o0, side, moments)
                for ch in range(3):
                    _channel_pass(b, ch, pairs, o0, side, moments)
        for b in range(2):
            _solve(moments, b, ridge, gram, rhs, coefs)
            target = BUFFER_B if b == 0 else BUFFER_A
            for ch in range(3):  # the target was fitted relative to its centre value: add it back
                k = ch * FEATURES
                store(coefs, (b, k, 0), load(coefs, (b, k, 0)) + load(planes, (0, target + ch, cy, c)))
        for y in range(y0, y1):
            for b in range(2):
                _predict_row(b, s, radius, pairs, (y - y0) * side, coefs, strip, y - top)
    for y in range(top, bottom):
        for b in range(2):
            for p in range(s):
                for v in range(0, strip.shape[4], LANES):
                    x = first_lane + v
                    for ch in range(3):
                        store(num, (b, p, ch, y, x), load(num, (b, p, ch, y, x)) + load(strip, (y - top, b, p, ch, v)))
                    store(den, (b, p, y, x), load(den, (b, p, y, x)) + load(strip, (y - top, b, p, 3, v)))


@numba.njit(inline="always")
def _zero_lanes(num, den, y0, y1, x0, x1):  # pragma: no cover
    """Zero lanes x0 ... x1 - 1 of rows y0 ... y1 - 1 of the sums num (2, S, 3, H, L') and den (2, S, H, L')."""
    for y in range(y0, y1):
        for b in range(num.shape[0]):
            for p in range(num.shape[1]):
                for ch in range(num.shape[2]):
                    num[b, p, ch, y, x0:x1] = 0.0
                den[b, p, y, x0:x1] = 0.0


@numba.njit(inline="always", fastmath=True)
def _pairs_pass(planes, spatial, radius, consts, cy, y, c, pairs, o0):  # pragma: no cover
    """Window row y of LANES centres (centre row cy, lanes c ...), read from the planes once for both
    regressions: every pair's terms into pairs[o0 + o] (pairs (side^2, PAIR_ROWS, LANES), o the offset in
    the row, side = 2 radius + 1): per buffer the weight (eq. 7, times the spatial factor, plus
    WEIGHT_FLOOR, 0 outside the frame), the colour scale
    1 / (sigma_i + sigma_c + eps) of eq. 6 and the log colour differences y_i - y_c; the normal and albedo
    differences. The later passes stream the scratch in order instead of gathering from 4 phase planes x
    17 rows again."""
    s = planes.shape[0]
    eps_sigma, eps_variance, floor = consts[0], consts[1], consts[2]  # `regression.block.kernel_constants`
    mask_c = load(planes, (0, MASK, cy, c))
    ga0, ga1, ga2 = _centres3(planes, BUFFER_A, cy, c)
    gb0, gb1, gb2 = _centres3(planes, BUFFER_B, cy, c)
    var_a, sig_a = load(planes, (0, BUFFER_A + 3, cy, c)), load(planes, (0, BUFFER_A + 4, cy, c))
    var_b, sig_b = load(planes, (0, BUFFER_B + 3, cy, c)), load(planes, (0, BUFFER_B + 4, cy, c))
    var_a, sig_a, var_b, sig_b = var_a + eps_variance, sig_a + eps_sigma, var_b + eps_variance, sig_b + eps_sigma
    n0, n1, n2 = _centres3(planes, NORMAL, cy, c)
    a0, a1, a2 = _centres3(planes, ALBEDO, cy, c)
    one = np.float32(1.0)
    p, x = (-radius) % s, c + (-radius) // s
    for o in range(2 * radius + 1):
        i = o0 + o  # the pair's row in the scratch
        sw = spatial[y - cy + radius, o]
        mask = load(planes, (p, MASK, y, x)) * mask_c
        da0 = load(planes, (p, BUFFER_A, y, x)) - ga0
        da1 = load(planes, (p, BUFFER_A + 1, y, x)) - ga1
        da2 = load(planes, (p, BUFFER_A + 2, y, x)) - ga2
        db0 = load(planes, (p, BUFFER_B, y, x)) - gb0
        db1 = load(planes, (p, BUFFER_B + 1, y, x)) - gb1
        db2 = load(planes, (p, BUFFER_B + 2, y, x)) - gb2
        ratio_a = (da0 * da0 + da1 * da1 + da2 * da2) / (load(planes, (p, BUFFER_A + 3, y, x)) + var_a)
        ratio_b = (db0 * db0 + db1 * db1 + db2 * db2) / (load(planes, (p, BUFFER_B + 3, y, x)) + var_b)
        store(pairs, (i, WEIGHT, 0), (exp_neg(ratio_a) * sw + floor) * mask)
        store(pairs, (i, WEIGHT + 1, 0), (exp_neg(ratio_b) * sw + floor) * mask)
        store(pairs, (i, SCALE, 0), one / (load(planes, (p, BUFFER_A + 4, y, x)) + sig_a))
        store(pairs, (i, SCALE + 1, 0), one / (load(planes, (p, BUFFER_B + 4, y, x)) + sig_b))
        store(pairs, (i, D, 0), da0)
        store(pairs, (i, D + 1, 0), da1)
        store(pairs, (i, D + 2, 0), da2)
        store(pairs, (i, D + 3, 0), db0)
        store(pairs, (i, D + 4, 0), db1)
        store(pairs, (i, D + 5, 0), db2)
        store(pairs, (i, DN, 0), load(planes, (p, NORMAL, y, x)) - n0)
        store(pairs, (i, DN + 1, 0), load(planes, (p, NORMAL + 1, y, x)) - n1)
        store(pairs, (i, DN + 2, 0), load(planes, (p, NORMAL + 2, y, x)) - n2)
        store(pairs, (i, DA, 0), load(planes, (p, ALBEDO, y, x)) - a0)
        store(pairs, (i, DA + 1, 0), load(planes, (p, ALBEDO + 1, y, x)) - a1)
        store(pairs, (i, DA + 2, 0), load(planes, (p, ALBEDO + 2, y, x)) - a2)
        p += 1
        if p == s:
            p, x = 0, x + 1


@numba.njit(inline="always", fastmath=True)
def _shared_pass(b, pairs, o0, side, moments):  # pragma: no cover
    """Regression b's moments of the shared features over pairs[o0 ... o0 + side - 1] (one window row),
    added to moments[b, 0:10] (moments (2, MOMENTS, LANES)): sum w [1, dn] [1, dn]^T, the upper triangle
    row by row."""
    m = (load(moments, (b, 0, 0)), load(moments, (b, 1, 0)), load(moments, (b, 2, 0)), load(moments, (b, 3, 0)),
         load(moments, (b, 4, 0)), load(moments, (b, 5, 0)), load(moments, (b, 6, 0)), load(moments, (b, 7, 0)),
         load(moments, (b, 8, 0)), load(moments, (b, 9, 0)))  # fmt: skip
    for o in range(o0, o0 + side):
        w = load(pairs, (o, WEIGHT + b, 0))
        e0, e1, e2 = load(pairs, (o, DN, 0)), load(pairs, (o, DN + 1, 0)), load(pairs, (o, DN + 2, 0))
        w0, w1, w2 = w * e0, w * e1, w * e2
        m = (m[0] + w, m[1] + w0, m[2] + w1, m[3] + w2, m[4] + w0 * e0, m[5] + w0 * e1, m[6] + w0 * e2,
             m[7] + w1 * e1, m[8] + w1 * e2, m[9] + w2 * e2)  # fmt: skip
    for e in range(10):
        store(moments, (b, e, 0), m[e])


@numba.njit(inline="always", fastmath=True)
def _channel_pass(b, ch, pairs, o0, side, moments):  # pragma: no cover
    """Regression b's colour channel ch: its 17 moments over pairs[o0 ... o0 + side - 1], added to
    moments[b, 10 + 17 ch ...]:
    sum w u [1, dn, u], w a [1, dn, u, a] and the right-hand side sum w t [1, dn, u, a], with u the scaled
    colour difference of buffer b (eq. 6) and t the other buffer's colour relative to its centre value (the
    same fit, the intercept less that value: `_cross_block_kernel` adds it back)."""
    k = 10 + 17 * ch
    m = (load(moments, (b, k, 0)), load(moments, (b, k + 1, 0)), load(moments, (b, k + 2, 0)),
         load(moments, (b, k + 3, 0)), load(moments, (b, k + 4, 0)), load(moments, (b, k + 5, 0)),
         load(moments, (b, k + 6, 0)), load(moments, (b, k + 7, 0)), load(moments, (b, k + 8, 0)),
         load(moments, (b, k + 9, 0)), load(moments, (b, k + 10, 0)), load(moments, (b, k + 11, 0)),
         load(moments, (b, k + 12, 0)), load(moments, (b, k + 13, 0)), load(moments, (b, k + 14, 0)),
         load(moments, (b, k + 15, 0)), load(moments, (b, k + 16, 0)))  # fmt: skip
    guide, target = D + 3 * b + ch, D + 3 * (1 - b) + ch
    for o in range(o0, o0 + side):
        w, a = load(pairs, (o, WEIGHT + b, 0)), load(pairs, (o, DA + ch, 0))
        u = load(pairs, (o, guide, 0)) * load(pairs, (o, SCALE + b, 0))
        e0, e1, e2 = load(pairs, (o, DN, 0)), load(pairs, (o, DN + 1, 0)), load(pairs, (o, DN + 2, 0))
        wu, wa, wt = w * u, w * a, w * load(pairs, (o, target, 0))
        m = (m[0] + wu, m[1] + wu * e0, m[2] + wu * e1, m[3] + wu * e2, m[4] + wu * u,
             m[5] + wa, m[6] + wa * e0, m[7] + wa * e1, m[8] + wa * e2, m[9] + wa * u, m[10] + wa * a,
             m[11] + wt, m[12] + wt * e0, m[13] + wt * e1, m[14] + wt * e2, m[15] + wt * u,
             m[16] + wt * a)  # fmt: skip
    for e in range(17):
        store(moments, (b, k + e, 0), m[e])


@numba.njit(inline="always")
def _centres3(planes, first, cy, c):  # pragma: no cover
    """The LANES centres' values (centre row cy, lanes c ...) of planes first, first + 1 and first + 2."""
    return load(planes, (0, first, cy, c)), load(planes, (0, first + 1, cy, c)), load(planes, (0, first + 2, cy, c))


def _moment_entries() -> np.ndarray:
    """(kind, row, column) of each moment in the order the passes store them, which is
    `regression.block.MomentLayout.moment_entries` of the cross layout (3 guides, 3 shared features, 3 groups
    of 2, 3 targets): kind 0 for the shared ones (in every channel's system), ch + 1 for channel ch's;
    column FEATURES for the right-hand side."""
    _, _, dest = MomentLayout(3, 3, 3, 2, 3).moment_entries()
    entries = [(0 if kind == 0 else g + 1, p, q if kind < 2 else FEATURES) for kind, g, p, q in dest]
    assert len(entries) == MOMENTS
    return np.array(entries, np.int64)


MOMENT_ENTRIES = _moment_entries()


@numba.njit(inline="always", fastmath=True)
def _solve(moments, b, ridge, gram, rhs, coefs):  # pragma: no cover
    """Regression b's moments[b] -> coefs[b], moments (2, MOMENTS, LANES), coefs (2, 3 FEATURES, LANES)
    float32: per colour channel the
    ridge solve of `solve_ridge` in float64, on the LANES centres as vectors (`_cholesky_solve`).
    gram (3, FEATURES, FEATURES, LANES), rhs (3, FEATURES, LANES): float64 scratch."""
    for e in range(MOMENTS):
        kind, row, col = MOMENT_ENTRIES[e, 0], MOMENT_ENTRIES[e, 1], MOMENT_ENTRIES[e, 2]
        value = load(moments, (b, e, 0))
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
            _cholesky_solve(gram, rhs, ch, ridge[0], ridge[1], h)
        for k in range(FEATURES):
            store(coefs, (b, ch * FEATURES + k, 0), narrow(load(rhs, (ch, k, 0)), load(rhs, (ch, k, HALF))))


@numba.njit(inline="always", fastmath=True)
def _cholesky_solve(a, b, g, ridge_relative, ridge_absolute, h):  # pragma: no cover
    """`regression.solve.cholesky_ridge_solve` (constant feature 0, one right-hand side) on VecD lanes
    h ... h + HALF - 1 of system g: a[g] (a (3, FEATURES, FEATURES, LANES) float64) the lower triangle of
    X^T W X, b[g] (b (3, FEATURES, LANES)) X^T W Y -> beta, in place; the same operations in the same order."""
    scale = vmax(load(a, (g, 0, 0, h)), splat_d(1e-30))
    store(a, (g, 0, 0, h), scale)
    least = scale * ridge_absolute  # pivot floor
    for j in range(1, FEATURES):
        d = load(a, (g, j, j, h))
        store(a, (g, j, j, h), d + (vmax(d, splat_d(0.0)) * ridge_relative + least))
    for j in range(FEATURES):
        d = load(a, (g, j, j, h))
        for p in range(j):
            d -= load(a, (g, j, p, h)) * load(a, (g, j, p, h))
        inv = 1.0 / sqrt(vmax(d, least))
        store(a, (g, j, j, h), inv)  # the diagonal holds 1 / L_jj
        for i in range(j + 1, FEATURES):
            v = load(a, (g, i, j, h))
            for p in range(j):
                v -= load(a, (g, i, p, h)) * load(a, (g, j, p, h))
            store(a, (g, i, j, h), v * inv)
    for i in range(FEATURES):
        v = load(b, (g, i, h))
        for p in range(i):
            v -= load(a, (g, i, p, h)) * load(b, (g, p, h))
        store(b, (g, i, h), v * load(a, (g, i, i, h)))
    for i in range(FEATURES - 1, -1, -1):
        v = load(b, (g, i, h))
        for p in range(i + 1, FEATURES):
            v -= load(a, (g, p, i, h)) * load(b, (g, p, h))
        store(b, (g, i, h), v * load(a, (g, i, i, h)))


@numba.njit(inline="always", fastmath=True)
def _predict_row(b, s, radius, pairs, o0, coefs, strip, row):  # pragma: no cover
    """Eq. 5's sums of regression b over one window row: num[b, channel] += w_b (alpha + beta . x_b) and
    den[b] += w_b at each of its pixels, into strip[row, b] (strip (R, 2, S, 4, TW) float32: channels, then
    the weight; lane j is plane lane c - pad + j), from its terms pairs[o0 ... o0 + 2 radius] (pairs
    (side^2, PAIR_ROWS, LANES)) and the coefficients coefs (2, 3 FEATURES, LANES); s the sparsity (phase
    planes). A strip row stays in L1 while a window row is added (adding every pair straight into the
    planes would miss L1 on most of them). One regression at a time, so that its 18 coefficients stay in
    registers across the row (both at once would reload them from L1 for every pair).
    Phases interleaved: a strip vector is re-read s offsets after its store."""
    k0 = (load(coefs, (b, 0, 0)), load(coefs, (b, 1, 0)), load(coefs, (b, 2, 0)), load(coefs, (b, 3, 0)),
          load(coefs, (b, 4, 0)), load(coefs, (b, 5, 0)))  # fmt: skip
    k1 = (load(coefs, (b, 6, 0)), load(coefs, (b, 7, 0)), load(coefs, (b, 8, 0)), load(coefs, (b, 9, 0)),
          load(coefs, (b, 10, 0)), load(coefs, (b, 11, 0)))  # fmt: skip
    k2 = (load(coefs, (b, 12, 0)), load(coefs, (b, 13, 0)), load(coefs, (b, 14, 0)), load(coefs, (b, 15, 0)),
          load(coefs, (b, 16, 0)), load(coefs, (b, 17, 0)))  # fmt: skip
    p, j = (-radius) % s, 0
    for o in range(2 * radius + 1):
        e0, e1, e2 = load(pairs, (o0 + o, DN, 0)), load(pairs, (o0 + o, DN + 1, 0)), load(pairs, (o0 + o, DN + 2, 0))
        w, scale = load(pairs, (o0 + o, WEIGHT + b, 0)), load(pairs, (o0 + o, SCALE + b, 0))
        _add_prediction(k0, pairs, o0 + o, b, 0, e0, e1, e2, scale, w, strip, row, p, j)
        _add_prediction(k1, pairs, o0 + o, b, 1, e0, e1, e2, scale, w, strip, row, p, j)
        _add_prediction(k2, pairs, o0 + o, b, 2, e0, e1, e2, scale, w, strip, row, p, j)
        store(strip, (row, b, p, 3, j), load(strip, (row, b, p, 3, j)) + w)
        p += 1
        if p == s:
            p, j = 0, j + 1


@numba.njit(inline="always", fastmath=True)
def _add_prediction(k, pairs, o, b, ch, e0, e1, e2, scale, w, strip, row, p, j):  # pragma: no cover
    """strip[row, b, p, ch, j ...] += w (k0 + k1 e0 + k2 e1 + k3 e2 + k4 u + k5 a): colour channel ch's weighted
    prediction (eq. 5) at pair o of regression b, from its coefficients k (FEATURES Vecs), the shared normal
    differences e, the scaled colour difference u and the albedo difference a."""
    u = load(pairs, (o, D + 3 * b + ch, 0)) * scale
    pred = k[0] + k[1] * e0 + k[2] * e1 + k[3] * e2 + k[4] * u + k[5] * load(pairs, (o, DA + ch, 0))
    store(strip, (row, b, p, ch, j), load(strip, (row, b, p, ch, j)) + w * pred)
