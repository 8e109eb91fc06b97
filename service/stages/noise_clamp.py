"""Keep a denoiser's output within the noise the two half buffers show at each pixel.

A pixel estimate `color` = (colorA + colorB) / 2 has variance Var(color) = E[(colorA - colorB)^2] / 4
(the halves are independent estimates of the same mean). Where that variance is small the renderer has
already resolved the pixel, and a filter that moves it far (a sky blurred with the horizon, a black
reflection of the void lifted by its bright surround) makes it worse than it came in. So every output
value is clipped to (the band reaching the input's firefly clip where given, below)

    color +- k sd,   sd^2 = mean over the 3x3 window (clipped at the border) of (colorA - colorB)^2 / 4,

per channel (a band beyond float32, from half differences above ~1e19, does not clip). The 3x3 mean
gives each sd about nine degrees of freedom, so an sd far below the true one (which would freeze noise in
place) is rare (less so on a surface of few pixels, below); where the halves disagree strongly (fireflies,
heavy-tailed paths) sd is large and the denoiser is free. A region where every sample of both halves was
black keeps black: that is what the samples say. Exact pixels (`service.stages.exact`) come out exactly as `color`;
other pixels with emission in the renderer's `emission` layer are not clipped.

With the G-buffer (`normal`, and `depth` where the frame has it) the mean is over the window's pixels on the
pixel's own surface: both background, or both surface hits whose normals' directions are within SURFACE_COS
(whatever their lengths: a normal averaged over a pixel's samples is short) and depths within SURFACE_DEPTH of
the nearer one's (the reprojection's thresholds; one relation both ways). The other surface's noise says
nothing about this pixel's:
- on `make bench`'s `fireflies`, frame 7, a column one pixel wide of a box's side that no light reaches (every
  sample black) stands beside the lit floor, whose noise widened the 3x3 band enough to let svgf's bleed
  through (0.1 where the input and the reference are 0: 51x the input's error over the 16x16 tile, kpn 16x,
  flr 6x). Its own pixels' halves all agree: band 0, the output is the input, as in a black region;
- on the held-out `data/val/veiled_light_s6`, dark bars one pixel wide (0.07) stand in front of a wall of ~9
  whose noise let every filter's bleed of ~1 through: 100 times the input's error at those pixels.

Measured against the 3x3 band with the all-agreeing surfaces only (the rule before, 2026-11-29; `python -m
bench run`, relL2 0.1% trimmed, out/bench/val-s54b -> val-s54d and report-s54b -> report-s54d): on veiled_light
svgf 0.490 -> 0.204, rae 0.326 -> 0.164, bmfr 0.0885 -> 0.0632, flr 0.0975 -> 0.0790, flnr 0.0831 -> 0.0696,
statistical 0.0770 -> 0.0635, bilateral 0.0588 -> 0.0503, auto 0.0407 -> 0.0365, kpn 0.0373 -> 0.0352
(OIDN-high 0.147); the 11 data/val sequences' mean relL2 lower or within 0.1% for every pipeline, at most +1.8%
on one sequence (auto on shadows). On `make bench`'s four sequences relL2 moves by -1.7% to +1.0%, but the
relL2 over disoccluded pixels rises 1-7% (auto 0.0308 -> 0.0328): a pixel at an object's edge takes its band
from fewer pixels, a noisier estimate. On the hard cases (`python -m bench.hard_cases table`, 64x64, against
the table before this and the step's radiance floor) relL2 on `veiled` (bars that are lit, not dark) rises
1-12% (rae 0.0386 -> 0.0432) and on `window` up to 7%; all still pass. Time at 1280x720: about 20 ms a
frame where the window band took 10 (`out/exp/s54/nc_time.py`, 2 cores).

The band also reaches, in any case, the input's firefly clip where the pixel's own halves allow it
(`noise_blend.firefly_clip`: the colour clipped where its halves differ to its 3x3 neighbours' range widened by
FIREFLY_K times its width, admitted
where within ADMIT_K = 10 times the pixel's own |A - B| / 2 of the colour). A firefly in both halves (at one
sample per half, both samples found a rare bright path while the neighbours' found none) has halves that differ
too little to widen a band diluted by its neighbours' zeros, and the band held every denoiser that removed it:
on the hard case `window_1spp` (a room lit through a window by a sky of 1e3) a pixel of reference 7 and input
353 (halves 419 and 287) came out 242 for every pipeline, and every pipeline's relL2 was 1.31. With the clip
admitted 1.00-1.01 (worst tile 0.244x -> 0.144x the noisy input's; OIDN-high 0.126: the rest is the rare hits'
light, which the denoisers' own firefly clamps take away). Without the spread test, a glint both halves saw
(1015 and 1050, reference 792, on the held-out `glossy_env_s6`) was darkened to 496 in one frame and the
sequence's temporal error rose 14-35%. Measured (`make bench`, `python -m bench.hard_cases table`, the 11
`data/val` sequences, against the clamp without it): `make bench` relL2 0.1-0.6% lower for every pipeline on
`shadows` and `fireflies`, the rest unchanged; `data/val` mean relL2 2.1-2.4% lower for every pipeline (`window`
2.6% and its temporal error 20-26%, `indirect` 3%), no sequence higher by more than 0.6% (flr on `dark`); hard
case `window` (4 samples per half) up to 5% higher (flr 0.540 -> 0.567), lower for crossreg, crossregression
and rae; all pass.

What it costs on ordinary frames, together with the other guards of `Pipeline.step` (the benchmark's
trimmed relL2, mean over frames, `make bench`, against the commit before the guards): NOISE_K = 5 is the
tightest of 3, 4 and 5 that kept every pipeline within 3% of its relL2 before. On the shadows sample flr
0.0382 -> 0.0388, bmfr 0.0494 -> 0.0494, crossregression 0.0601 -> 0.0598; on the `fireflies` sequence
crossregression 0.0324 -> 0.0330, while bmfr improves there, 0.150 -> 0.071. An earlier
version with K = 3 cost flr 8.6% on the shadows sample.
"""

from __future__ import annotations

import numba
import numpy as np

from service.kernels.row_ranges import BAND_ROWS
from service.kernels.window import overlap, window_offsets
from service.stages.exact import EXACT_MIN, EXACT_RTOL, agree, any_agree, exact_mask, pixel_exact
from service.stages.reprojection import DEPTH_FLOOR, NORMAL_HIT, ReprojectionParams
from service.stages.svgf import box_mean

NOISE_K = 5.0  # half-width of the allowed band, in standard deviations of the pixel estimate
NOISE_RADIUS = 1  # window half-size of the variance estimate, pixels (3x3)
# Two pixels are on one surface (module docstring) at the reprojection's thresholds for a consistent tap: the
# cosine between their normals' directions at least SURFACE_COS, depths within SURFACE_DEPTH of the nearer one's
SURFACE_COS = ReprojectionParams.normal_cos_min
SURFACE_DEPTH = ReprojectionParams.depth_tolerance
_COS2 = np.float32(SURFACE_COS**2)  # the kernel compares dot^2 with cos^2 |n|^2 |m|^2 (dot > 0): no square root
LINKS = ((0, 1), (1, -1), (1, 0), (1, 1))  # (dy, dx): the neighbours whose surface links a pixel stores


def noise_clamp(
    out: np.ndarray,
    color: np.ndarray,
    color_a: np.ndarray,
    color_b: np.ndarray,
    emission: np.ndarray | None = None,
    k: float = NOISE_K,
    exact: bool = True,
    *,
    normal: np.ndarray | None = None,
    depth: np.ndarray | None = None,
    admitted: np.ndarray | None = None,
) -> np.ndarray:
    """`out` clipped to `color` +- k sd per pixel and channel, the band reaching `admitted` (module docstring).

    out: (H, W, 3) float32 denoised radiance; color, color_a, color_b: (H, W, 3) float32 noisy radiance and
    its two halves; emission: the renderer's (H, W, 3) float32 emission layer or None; all linear. Exact
    pixels (`service.stages.exact.exact_mask(color_a, color_b, color, emission)`) take `color`; pixels
    with emission keep `out` unclipped (there the samples' binary coverage of an emitter's edge can make
    the halves agree by chance, and the emission split already tells the denoiser what is exact). Returns
    a new (H, W, 3) float32 array. One parallel numba pass; `noise_clamp_reference` is the numpy twin.
    exact=False: the caller knows that no pixel is exact (`exact.exact_emission` found none in a frame
    without an emission layer), and the per-pixel test is skipped. normal: (H, W, 3) float32 (zero where
    nothing was hit) and depth: (H, W, 1) float32 or None: the band comes from the 3x3 pixels on the pixel's
    own surface (module docstring); depth is used only with normal (its shape is checked either way).
    admitted: (H, W, 3) float32 or None: a value per pixel and channel that the band reaches in any case, linear
    radiance with the emission like `color` (the input with its fireflies clipped, `noise_blend.firefly_clip`'s
    second array; module docstring).
    """
    if not 0 <= k < np.inf:
        raise ValueError(f"noise clamp k must be finite and >= 0, got {k}")
    arrays = [np.ascontiguousarray(x, dtype=np.float32) for x in (out, color, color_a, color_b)]
    e = arrays[1] if emission is None else np.ascontiguousarray(emission, dtype=np.float32)  # unread without it
    reach = arrays[1] if admitted is None else np.ascontiguousarray(admitted, dtype=np.float32)  # unread without it
    shapes = {x.shape for x in arrays + [e, reach]}
    if len(shapes) != 1 or arrays[0].ndim != 3:
        raise ValueError(f"noise clamp: out, color, the halves, emission and admitted must share one (H, W, C) shape: "
                         f"{shapes}")
    result = np.empty_like(arrays[0])
    use_normal, use_depth = normal is not None, normal is not None and depth is not None
    normal, depth = _gbuffer(normal, depth, arrays[0].shape)
    links = np.zeros((len(LINKS), *arrays[0].shape[:2]) if use_normal else (len(LINKS), 1, 1), np.uint8)
    if use_normal:
        _links_kernel(normal, depth, use_depth, links)
    _clamp_kernel(*arrays[:4], e, emission is not None, exact or emission is not None, np.float32(k),
                  np.float32(EXACT_RTOL), np.float32(EXACT_MIN), links, use_normal, reach, admitted is not None, result)
    return result


def _gbuffer(normal: np.ndarray | None, depth: np.ndarray | None,
             shape: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray]:
    """normal (H, W, 3) and depth (H, W, 1) as contiguous float32 for the kernel (placeholders of one pixel
    where not given); ValueError where their shape does not match the frame's (H, W)."""
    pair = []
    for name, layer, channels in (("normal", normal, 3), ("depth", depth, 1)):
        if layer is None:
            pair.append(np.zeros((1, 1, channels), np.float32))
            continue
        if layer.shape != (*shape[:2], channels):
            raise ValueError(f"noise clamp: {name} {layer.shape} does not match the frame {shape[:2]}")
        pair.append(np.ascontiguousarray(layer, np.float32))
    return pair[0], pair[1]


def same_surface_reference(normal: np.ndarray, depth: np.ndarray | None, dy: int, dx: int) -> np.ndarray:
    """(H, W) bool: pixel (y, x) and (y + dy, x + dx) are on one surface (module docstring; False where the
    second is outside the frame); numpy twin of `_links_kernel`. normal (H, W, 3), depth (H, W, 1) or None."""
    normal = normal.astype(np.float32)
    depth = None if depth is None else depth.astype(np.float32)
    height, width = normal.shape[:2]
    same = np.zeros((height, width), bool)
    pair = overlap(height, width, dy, dx)
    if pair is None:
        return same
    centre, neighbour = pair
    n, m = normal[centre], normal[neighbour]
    own, other = (n * n).sum(axis=-1), (m * m).sum(axis=-1)
    hit, other_hit = own > np.float32(NORMAL_HIT), other > np.float32(NORMAL_HIT)
    dot = (n * m).sum(axis=-1)
    aligned = (dot > 0) & (dot * dot >= _COS2 * (own * other))
    if depth is not None:
        z, w = depth[centre][..., 0], depth[neighbour][..., 0]
        aligned &= np.abs(w - z) <= np.float32(SURFACE_DEPTH) * np.maximum(np.minimum(np.abs(z), np.abs(w)),
                                                                           np.float32(DEPTH_FLOOR))
    same[centre] = (hit == other_hit) & (~hit | aligned)
    return same


def noise_sd_reference(color_a: np.ndarray, color_b: np.ndarray, normal: np.ndarray | None = None,
                       depth: np.ndarray | None = None) -> np.ndarray:
    """(H, W, C) float32 sd of the pixel estimate (module docstring): over the 3x3 window, or with `normal`
    over the window's pixels on the pixel's own surface; numpy."""
    d = color_a.astype(np.float32) - color_b.astype(np.float32)
    if normal is None:
        return np.sqrt(box_mean(d * d, NOISE_RADIUS) / np.float32(4.0))
    height, width = d.shape[:2]
    total, count = d * d, np.ones((height, width, 1), np.float32)
    for dy, dx in window_offsets(NOISE_RADIUS):
        pair = overlap(height, width, dy, dx)
        if pair is None or (dy, dx) == (0, 0):
            continue
        centre, neighbour = pair
        same = same_surface_reference(normal, depth, dy, dx)[centre][..., None]
        total[centre] += np.where(same, d[neighbour] * d[neighbour], np.float32(0.0))
        count[centre] += same
    return np.sqrt(total / count / np.float32(4.0))


def noise_clamp_reference(
    out: np.ndarray,
    color: np.ndarray,
    color_a: np.ndarray,
    color_b: np.ndarray,
    emission: np.ndarray | None = None,
    k: float = NOISE_K,
    *,
    normal: np.ndarray | None = None,
    depth: np.ndarray | None = None,
    admitted: np.ndarray | None = None,
) -> np.ndarray:
    """Plain-numpy twin of `noise_clamp`."""
    band = k * noise_sd_reference(color_a, color_b, normal, depth)
    low, high = color - band, color + band
    if admitted is not None:
        low, high = np.minimum(low, admitted), np.maximum(high, admitted)
    clipped = np.clip(out, low, high)
    if emission is not None:
        clipped = np.where((emission != 0).any(axis=-1, keepdims=True), out, clipped)
    exact = exact_mask(color_a, color_b, color, emission)
    return np.where(exact[..., None], color, clipped).astype(np.float32)


@numba.njit(parallel=True, cache=True, error_model="numpy")
def _links_kernel(normal, depth, use_depth, links):  # pragma: no cover - jitted
    """links (len(LINKS), H, W) uint8: 1 where pixel (y, x) and (y + dy, x + dx) of LINKS[d] are on one surface
    (module docstring; 0 beyond the frame). normal (H, W, 3), depth (H, W, 1) float32. A task per row, on
    planar copies of its row and the next (`_surface_row`), branch-free loops along the row (`_link_row`)."""
    height, width = normal.shape[:2]
    for y in numba.prange(height):
        here = _surface_row(normal, depth, use_depth, y)
        _link_row(here, here, 1, links[0, y])
        if y + 1 < height:
            below = _surface_row(normal, depth, use_depth, y + 1)
            _link_row(here, below, -1, links[1, y])
            _link_row(here, below, 0, links[2, y])
            _link_row(here, below, 1, links[3, y])


@numba.njit(inline="always", cache=True)
def _surface_row(normal, depth, use_depth, y):  # pragma: no cover - jitted
    """(5, W) float32 of row y: the normal's three components, its squared length, and depth (0 without
    `use_depth`)."""
    width = normal.shape[1]
    row = np.empty((5, width), np.float32)
    for x in range(width):
        n0, n1, n2 = normal[y, x, 0], normal[y, x, 1], normal[y, x, 2]
        row[0, x], row[1, x], row[2, x] = n0, n1, n2
        row[3, x] = n0 * n0 + n1 * n1 + n2 * n2
        row[4, x] = depth[y, x, 0] if use_depth else np.float32(0.0)
    return row


@numba.njit(inline="always", cache=True)
def _link_row(here, there, dx, out):  # pragma: no cover - jitted
    """out[x] = whether pixel x of row `here` and pixel x + dx of row `there` ((5, W) float32, `_surface_row`)
    are on one surface: both background, or both hits whose normals' directions are within SURFACE_COS and
    depths within SURFACE_DEPTH of the nearer one's (depth 0 when not used passes). Branch-free: vectorises."""
    width = here.shape[1]
    for x in range(max(0, -dx), min(width, width - dx)):
        xx = x + dx
        own, other = here[3, x], there[3, xx]
        hit, other_hit = own > np.float32(NORMAL_HIT), other > np.float32(NORMAL_HIT)
        dot = here[0, x] * there[0, xx] + here[1, x] * there[1, xx] + here[2, x] * there[2, xx]
        z, w = abs(here[4, x]), abs(there[4, xx])
        near = abs(there[4, xx] - here[4, x]) <= np.float32(SURFACE_DEPTH) * max(min(z, w), np.float32(DEPTH_FLOOR))
        aligned = (dot > 0) & (dot * dot >= _COS2 * (own * other)) & near
        out[x] = (hit == other_hit) & ((not hit) | aligned)


@numba.njit(inline="always", cache=True)
def _window_band(a, b, y, k, band):  # pragma: no cover - jitted
    """band ((W * C,) float32) = k sd of row y's pixels over their 3x3 windows (clipped at the border): the
    3-row column sums of (a - b)^2 along the interleaved row, then the 3-column sums as shifts by C."""
    height, width, channels = a.shape
    n = width * channels
    y0, y1 = max(y - 1, 0), min(y + 2, height)
    column = np.zeros(n, np.float32)
    for yy in range(y0, y1):
        ra, rb = a[yy].reshape(n), b[yy].reshape(n)
        for i in range(n):
            d = ra[i] - rb[i]
            column[i] += d * d
    scale = np.float32(0.25) / np.float32(y1 - y0)
    inner = scale / np.float32(min(width, 3))  # interior pixels sum three columns
    edge = scale / np.float32(min(width, 2))  # the first and last pixel two (one in a 1-pixel row)
    for i in range(channels, n - channels):  # interior: contiguous, vectorises
        band[i] = k * np.sqrt((column[i - channels] + column[i] + column[i + channels]) * inner)
    for c in range(channels):  # the first and last pixel of the row
        for i in (c, n - channels + c):
            total = column[i]
            if i >= channels:
                total += column[i - channels]
            if i + channels < n:
                total += column[i + channels]
            band[i] = k * np.sqrt(total * edge)


@numba.njit(inline="always", cache=True)
def _surface_band(above, here, below, links, y, k, band):  # pragma: no cover - jitted
    """band ((W * C,) float32) = k sd of row y's pixels over the pixels of their 3x3 windows on their own
    surface (`links`, (len(LINKS), H, W) uint8: the pixel and its neighbour at LINKS[d] are on one surface;
    the neighbour in the opposite direction reads the link stored at that neighbour). above, here, below:
    (C, W) float32 planar (a - b)^2 of rows y - 1, y and y + 1 (`_squares_row`; read only within the
    frame). Branch-free loops along the row."""
    height, width = links.shape[1], links.shape[2]
    channels = here.shape[0]
    total = here.copy()
    count = np.ones(width, np.float32)
    if y > 0:  # the row above: its links to this row (SW, S, SE of that row) read from there
        _add_linked(above, links[1, y - 1], 1, 1, total, count)  # above's (x + 1) links to x here: NE
        _add_linked(above, links[2, y - 1], 0, 0, total, count)
        _add_linked(above, links[3, y - 1], -1, -1, total, count)  # above's (x - 1) links to x here: NW
    if y + 1 < height:
        _add_linked(below, links[1, y], 0, -1, total, count)
        _add_linked(below, links[2, y], 0, 0, total, count)
        _add_linked(below, links[3, y], 0, 1, total, count)
    _add_linked(here, links[0, y], 0, 1, total, count)  # the pixel's own link to its right neighbour
    _add_linked(here, links[0, y], -1, -1, total, count)  # the left neighbour's link to the pixel
    for x in range(width):
        scale = np.float32(0.25) / count[x]
        for c in range(channels):
            band[x * channels + c] = k * np.sqrt(total[c, x] * scale)


@numba.njit(inline="always", cache=True)
def _squares_row(a, b, y, row):  # pragma: no cover - jitted
    """row ((C, W) float32) = (a - b)^2 of row y of the halves ((H, W, C) float32), planar."""
    width, channels = a.shape[1], a.shape[2]
    for x in range(width):
        for c in range(channels):
            d = a[y, x, c] - b[y, x, c]
            row[c, x] = d * d


@numba.njit(inline="always", cache=True)
def _add_linked(squares, link, shift, dx, total, count):  # pragma: no cover - jitted
    """For pixels x of the row: with l = link[x + shift] (uint8, (W,)), count[x] += l and total[:, x] += l *
    squares[:, x + dx] ((C, W) float32), where x + shift and x + dx are in the row."""
    width = count.shape[0]
    x0, x1 = max(0, -dx, -shift), min(width, width - dx, width - shift)
    for x in range(x0, x1):  # one contiguous loop per plane: vectorises
        count[x] += np.float32(link[x + shift])
    for c in range(squares.shape[0]):
        for x in range(x0, x1):
            total[c, x] += np.float32(link[x + shift]) * squares[c, x + dx]


@numba.njit(inline="always", cache=True)
def _may_be_exact(ra, rb, rc, re, has_emission, rtol):  # pragma: no cover - jitted
    """Whether a pixel of a row ((W * C,) float32 halves ra, rb, colour rc, emission re) may take the exact
    pass of `_clamp_kernel`: with `has_emission`, some value has emission or a colour of 0; without, some
    value's halves agree (`agree`, rtol). Counted branch-free: a row with none costs one vectorised pass."""
    count = 0
    if has_emission:
        for i in range(rc.shape[0]):
            count += 1 if re[i] != 0 or rc[i] == 0 else 0
        return count > 0
    return any_agree(ra, rb, rtol)


@numba.njit(parallel=True, cache=True, error_model="numpy")
def _clamp_kernel(out, color, a, b, e, has_emission, exact, k, rtol, floor, links, use_normal, admitted,
                  has_admitted, result):  # pragma: no cover - jitted
    """A task per band of BAND_ROWS rows, each row in turn: the band from the 3x3 window (`_window_band`), or with
    `use_normal` from the window's pixels on the pixel's own surface (`_surface_band`, on `links` of
    `_links_kernel`, each row's squares made once and kept for the rows around), then the clip; unless
    `exact` is False (and so `has_emission`), exact pixels take `color`, other pixels with emission take `out`
    unclipped. With `has_admitted` the band reaches each value of `admitted` ((H, W, C) float32)."""
    height, width, channels = out.shape
    n = width * channels
    for task in numba.prange(-(-height // BAND_ROWS)):
        y0, y1 = task * BAND_ROWS, min((task + 1) * BAND_ROWS, height)
        band = np.empty(n, np.float32)
        squares = np.zeros((3, channels, width), np.float32)  # rows y - 1, y, y + 1 in slots y % 3
        if use_normal:
            if y0 > 0:
                _squares_row(a, b, y0 - 1, squares[(y0 - 1) % 3])
            _squares_row(a, b, y0, squares[y0 % 3])
        for y in range(y0, y1):
            if use_normal:
                if y + 1 < height:
                    _squares_row(a, b, y + 1, squares[(y + 1) % 3])
                _surface_band(squares[(y + 2) % 3], squares[y % 3], squares[(y + 1) % 3], links, y, k, band)
            else:
                _window_band(a, b, y, k, band)
            ra, rb = a[y].reshape(n), b[y].reshape(n)
            rc, ro, rr = color[y].reshape(n), out[y].reshape(n), result[y].reshape(n)
            if has_admitted:
                rm = admitted[y].reshape(n)
                for i in range(n):
                    rr[i] = min(max(ro[i], min(rc[i] - band[i], rm[i])), max(rc[i] + band[i], rm[i]))
            else:
                for i in range(n):
                    rr[i] = min(max(ro[i], rc[i] - band[i]), rc[i] + band[i])
            re = e[y].reshape(n)
            if not exact or not _may_be_exact(ra, rb, rc, re, has_emission, rtol):
                continue
            for x in range(width):
                i = x * channels
                if has_emission:  # an exact pixel is all emission: without any, only a black colour can be
                    emitted, black = False, True
                    for c in range(channels):
                        emitted = emitted or re[i + c] != 0
                        black = black and rc[i + c] == 0
                    if not emitted:
                        if black and pixel_exact(ra, rb, i, channels, rtol, floor):  # (a repaired NaN colour)
                            for c in range(channels):
                                rr[i + c] = rc[i + c]
                        continue
                    keep = pixel_exact(ra, rb, i, channels, rtol, floor)
                    for c in range(channels):
                        keep = keep and agree(rc[i + c], re[i + c], rtol)
                    src = rc if keep else ro  # exact: the input; other emission: unclipped
                    for c in range(channels):
                        rr[i + c] = src[i + c]
                elif pixel_exact(ra, rb, i, channels, rtol, floor):
                    for c in range(channels):
                        rr[i + c] = rc[i + c]
