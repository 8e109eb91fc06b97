"""A denoiser's error estimated without a reference, per tile, from the two half buffers.

A denoiser f run on half A alone is independent of half B, and both halves are unbiased estimates of the
pixel mean mu with the same variance (equal sample counts). So, per pixel and channel,

    E[(f(A) - B)^2] = E[(f(A) - mu)^2] + Var(B)       (the cross term vanishes: f(A) and B are independent)
    E[(A - B)^2] / 2 = Var(B)

and  d = (f(A) - B)^2 - (A - B)^2 / 2  is an unbiased estimate of f(A)'s squared error. Scaled like relL2
(service.metrics.rel_l2_map: divided by the squared channel mean plus REL_L2_EPS, here of a `scale` image
the caller gives: smooth, so that it does not correlate with the noise, and the same for every candidate
compared, so that it weighs their errors alike) and averaged over the channels and a tile's pixels, it
estimates the tile's relL2. Single pixels are very noisy (d can be negative); a tile of 32x32 averages 1024 of them. The
variance of a tile's estimate is the sample variance of its pixels' d over their count (pixels taken as
independent, which a denoiser's output is not quite: a lower bound).

Fireflies make d useless where they are: a sample of 1e3 in B where f(A) says 0.1 adds 1e8 (relative) to
one pixel, and it ranks the candidates by which is brighter there. With `cap`, both halves are first
clipped at cap times the scale's level (plus cap x sqrt(REL_L2_EPS), so that dark pixels are left alone):
the same clipped target for every candidate, so the ranking stays fair, at the price of an estimate biased
low in tiles with fireflies.

Both ways (`cross_tile_error`): with f also run on half B alone, the mean of d for f(A) against B and of
d for f(B) against A. Writing n_A, n_B for the halves' noise and e_A, e_B for f(A)'s and f(B)'s errors,

    d(f(A), B) = e_A^2 - 2 e_A n_B + (n_B^2 - n_A^2) / 2 + n_A n_B

and the halves' own term (n_B^2 - n_A^2) / 2, the largest where f is good, changes sign between the two
ways and cancels in the mean. For Gaussian noise that halves the variance where the error is small
(2 sigma^4 -> sigma^4 per pixel and channel), at the price of running f twice.

It estimates the error of f on half the samples, not on the full frame: the ranking of candidates is what
it is for (bench/error_estimate.py measures how well it ranks them against the true error of f on the
full frame).

**Control variate** (`control`). Where f is good, most of what is left of d both ways is the product
n_A n_B, zero in expectation but as large as the noise squared. With m an estimate of mu made from both
halves (auto: the median of its candidates on the whole frame), (A - m)(B - m) = n_A n_B - delta (n_A + n_B) +
delta^2, delta = m - mu, carries the same product, and d - (A - m)(B - m) keeps little of it (delta is small
where m is good). It is not unbiased: E[(A - m)(B - m)] = E[delta^2] - (m's weight on its own pixel's samples)
x Var, the same for every denoiser compared at a pixel, so it changes no choice between them (w^T C w for
weights summing to 1 moves by that one term), and it varies from tile to tile slowly: what it buys is a
ranking of tiles closer to the true one. On the four benchmark sequences, per candidate over (frame, tile),
Spearman's correlation with the true error of f on the whole frame went from 0.69, 0.59, 0.73 and 0.87 to
0.79, 0.80, 0.90 and 0.96 (`python -m bench.error_estimate`, docs/benchmarks.md). m made from the candidates
on one half each ((f(A) + f(B)) / 2) was worse than none on `shadows` (0.44): without the halves, the
candidates skip the step's guards and blur its shadows, and m must be good for the term to cancel.

Between two denoisers f and g the same argument gives their errors' covariance: f(A) and g(A) are both
independent of B, so E[(f(A) - B)(g(A) - B)] = E[(f(A) - mu)(g(A) - mu)] + Var(B), and

    d_fg = (f(A) - B)(g(A) - B) - (A - B)^2 / 2       (both ways: the mean of that and of the same with A, B swapped)

estimates it (`tile_covariance`; d_ff is d). A blend sum_k w_k f_k (weights summing to 1) has the squared
error w^T C w, C the matrix of these per tile: what `auto` minimises when it blends candidates.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from service.metrics import REL_L2_EPS

TILE = 32  # tile side, pixels (issue 28's example)


@dataclass(frozen=True)
class TileError:
    """Per-tile estimates, (ceil(H / tile), ceil(W / tile)) float64 arrays; the last row and column of tiles
    take what is left of the frame."""

    mean: np.ndarray  # estimated relL2 of the tile (may be slightly negative where the error is ~0)
    variance: np.ndarray  # variance of that estimate (pixels taken as independent)
    tile: int


def tile_sums(values: np.ndarray, tile: int) -> tuple[np.ndarray, np.ndarray]:
    """(sums, counts) of (H, W) float64 `values` over tile x tile tiles: ((th, tw) float64, (th, tw) int64)."""
    height, width = values.shape
    sums = np.add.reduceat(np.add.reduceat(values, np.arange(0, height, tile), axis=0), np.arange(0, width, tile),
                           axis=1)
    return sums, tile_counts(height, width, tile)


def tile_counts(height: int, width: int, tile: int) -> np.ndarray:
    """(ceil(H / tile), ceil(W / tile)) int64: the pixels of each tile x tile tile of an H x W frame."""
    rows, cols = np.arange(0, height, tile), np.arange(0, width, tile)
    return np.outer(np.diff(np.append(rows, height)), np.diff(np.append(cols, width)))


def tile_means(values: np.ndarray, tile: int) -> np.ndarray:
    """Mean of (H, W) float64 `values` over each tile x tile tile: (ceil(H / tile), ceil(W / tile)) float64."""
    sums, counts = tile_sums(values, tile)
    return sums / counts


def interpolation_matrix(size: int, tile: int) -> np.ndarray:
    """(size, ceil(size / tile)) float64 linear interpolation from the tiles' centres to every pixel (clamped
    beyond the first and last centre; rows sum to 1)."""
    starts = np.arange(0, size, tile)
    centres = (starts + np.minimum(starts + tile, size) - 1) / 2.0
    pixels = np.arange(size, dtype=np.float64)
    return np.stack([np.interp(pixels, centres, np.eye(len(starts))[i]) for i in range(len(starts))], axis=1)


def interpolate_tiles(values: np.ndarray, tile: int, height: int, width: int) -> np.ndarray:
    """(..., th, tw) per-tile values -> (..., H, W) float64 interpolated between tile centres (weights summing to
    1 per pixel: where the tiles' values along a leading axis sum to 1, so do the pixels')."""
    return interpolation_matrix(height, tile) @ values @ interpolation_matrix(width, tile).T


def pixel_error(out_a: np.ndarray, color_a: np.ndarray, color_b: np.ndarray, scale: np.ndarray,
                eps: float = REL_L2_EPS, cap: float | None = None) -> np.ndarray:
    """(H, W) float64 per-pixel estimate d of out_a's relative squared error (module docstring), the mean over
    channels. out_a: (H, W, 3) a denoiser's output from half A alone; color_a, color_b: (H, W, 3) the halves;
    scale: (H, W, 3) the image whose channel mean normalises (module docstring); all linear radiance. cap:
    clip the halves at cap x (that mean + sqrt(eps)) first (fireflies, module docstring); None: unbiased."""
    return _pixel_d(out_a, *_normalised(color_a, color_b, scale, eps, cap))


def _pixel_d(out_a: np.ndarray, a: np.ndarray, b: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """`pixel_error` of out_a on the halves as `_normalised` gives them (a, b float64 (H, W, 3), weight (H, W, 1))."""
    return (((out_a.astype(np.float64) - b) ** 2 - 0.5 * (a - b) ** 2) * weight).mean(axis=-1)


def _normalised(color_a: np.ndarray, color_b: np.ndarray, scale: np.ndarray, eps: float,
                cap: float | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The halves as float64 (H, W, 3), clipped with `cap` (`pixel_error`), and the relL2 weight 1 / (m^2 + eps)
    of the scale's channel mean m, (H, W, 1) float64."""
    a, b = color_a.astype(np.float64), color_b.astype(np.float64)
    m = scale.astype(np.float64).mean(axis=-1, keepdims=True)
    if cap is not None:
        limit = cap * (np.abs(m) + np.sqrt(eps))
        a, b = np.minimum(a, limit), np.minimum(b, limit)
    return a, b, 1.0 / (m * m + eps)


def control_term(color_a: np.ndarray, color_b: np.ndarray, control: np.ndarray, scale: np.ndarray,
                 eps: float = REL_L2_EPS, cap: float | None = None) -> np.ndarray:
    """(H, W) float64 per-pixel (A - m)(B - m), scaled and clipped as `pixel_error`, m = `control` ((H, W, 3)
    linear radiance, an estimate of the pixel mean made from both halves): the control variate of the module
    docstring, subtracted from d where the estimate ranks tiles."""
    return _control(control, *_normalised(color_a, color_b, scale, eps, cap))


def _control(control: np.ndarray, a: np.ndarray, b: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """`control_term` on the halves as `_normalised` gives them."""
    m = control.astype(np.float64)
    return ((a - m) * (b - m) * weight).mean(axis=-1)


def tile_error(out_a: np.ndarray, color_a: np.ndarray, color_b: np.ndarray, scale: np.ndarray, tile: int = TILE,
               eps: float = REL_L2_EPS, cap: float | None = None, control: np.ndarray | None = None) -> TileError:
    """Per-tile estimated relL2 of `out_a` and the variance of each estimate (arguments as `pixel_error`;
    `control`: `control_term`'s m, or None for none)."""
    a, b, weight = _normalised(color_a, color_b, scale, eps, cap)
    d = _pixel_d(out_a, a, b, weight)
    if control is not None:
        d -= _control(control, a, b, weight)
    return _tiled(d, tile)


def cross_tile_error(out_a: np.ndarray, out_b: np.ndarray, color_a: np.ndarray, color_b: np.ndarray,
                     scale: np.ndarray, tile: int = TILE, eps: float = REL_L2_EPS,
                     cap: float | None = None, control: np.ndarray | None = None) -> TileError:
    """Per-tile estimated relL2 of a denoiser on half the samples, both ways (module docstring): out_a and
    out_b (H, W, 3) are its outputs from half A alone and from half B alone; the other arguments as
    `tile_error`. The variance takes the pixels' mean of the two ways as independent, as `tile_error` does."""
    a, b, weight = _normalised(color_a, color_b, scale, eps, cap)
    d = 0.5 * (_pixel_d(out_a, a, b, weight) + _pixel_d(out_b, b, a, weight))
    if control is not None:
        d -= _control(control, a, b, weight)
    return _tiled(d, tile)


def tile_covariance(outs_a: list[np.ndarray], color_a: np.ndarray, color_b: np.ndarray, scale: np.ndarray,
                    tile: int = TILE, eps: float = REL_L2_EPS, cap: float | None = None,
                    outs_b: list[np.ndarray] | None = None) -> np.ndarray:
    """Per tile, the estimated covariance of K denoisers' relative errors on half the samples (module docstring):
    (K, K, ceil(H / tile), ceil(W / tile)) float64, symmetric, its diagonal `tile_error`'s means (with `outs_b`,
    `cross_tile_error`'s). outs_a: K (H, W, 3) outputs from half A alone; outs_b: the same from half B alone,
    for the estimate both ways, or None for one way; the other arguments as `pixel_error`. Not positive
    semi-definite in general (noise): a caller that needs it so projects it."""
    if tile < 1:
        raise ValueError(f"tile must be >= 1, got {tile}")
    a, b, weight = _normalised(color_a, color_b, scale, eps, cap)
    root = np.sqrt(weight)  # folded into each difference: one product per pair and way
    halves = 0.5 * ((a - b) ** 2 * weight).mean(axis=-1)
    ways = [[(x.astype(np.float64) - b) * root for x in outs_a]]
    if outs_b is not None:
        ways.append([(x.astype(np.float64) - a) * root for x in outs_b])
    count = len(outs_a)
    height, width = a.shape[:2]
    result = np.empty((count, count, -(-height // tile), -(-width // tile)))
    for j in range(count):
        for k in range(j, count):
            d = sum((way[j] * way[k]).mean(axis=-1) for way in ways) / len(ways) - halves
            result[j, k] = result[k, j] = tile_means(d, tile)
    return result


def _tiled(d: np.ndarray, tile: int) -> TileError:
    """Per-tile mean of the (H, W) float64 per-pixel estimates `d`, and its variance."""
    if tile < 1:
        raise ValueError(f"tile must be >= 1, got {tile}")
    sums, counts = tile_sums(d, tile)
    squares, _ = tile_sums(d * d, tile)
    mean = sums / counts
    spread = np.maximum(squares / counts - mean * mean, 0.0) * counts / np.maximum(counts - 1, 1)
    return TileError(mean, spread / counts, tile)
