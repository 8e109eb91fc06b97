"""Which half tiles of the noise blend the input's zeros refute the output in.

A pixel whose samples in both halves are all 0 (its radiance less emission) says: no sample hit light here.
Where the output puts light o >= 0 on a pixel, and one hit would have added h to the pixel's mean (its one-hit
value: a sample's radiance over the samples per pixel), its samples all missed with a chance of about p =
exp(-o / h). Over a half tile the count K of pixels that are not dark is then a sum of independent Bernoulli
variables of chances 1 - p, and the output is refuted where P(K <= k) < exp(-EVIDENCE), k the count seen
(exactly, by dynamic programming over the pixels; with k = 0 it is exp(-sum o / h)). This is what a light that
has just left a region, or a filter that smeared light into a hard shadow, looks like: pixels whose samples
all missed, far more of them than the output's light allows. A dim region whose output is right (the 0/1 frame
of tests/service/stages/test_noise_blend.py, one sample per half hitting with a chance of 0.01) keeps about
the count of dark pixels its light predicts, and passes.

The one-hit value is estimated as the least variance-to-mean ratio v / c (v = ((A - B) / 2)^2, the pixel
estimate's variance) of the 3x3 half tiles around whose share of noisy pixels (halves that differ) is at
least the blend's NOISY_SHARE: for n samples that each hit (value M) or miss, v / c = M (1 - q) / n with q
the chance of a hit, which is M / n where hits are rare and less where samples rarely miss. A smaller h
refutes more readily; where no neighbour qualifies nothing is refuted. Pixels whose halves agree on a value
other than 0 (exact pixels) take no part. Tested only on the half tiles the blend asks about (`candidates`).

numba kernel `_dark_kernel`; `refuted_reference` is the numpy twin.
"""

from __future__ import annotations

import math

import numba
import numpy as np

EVIDENCE = 7.0  # refuted where the output's light leaves the dark pixels a chance below exp(-7) ~ 1e-3


def one_hit_values(noisy: np.ndarray, lit: np.ndarray, variance: np.ndarray, pixels: np.ndarray,
                   share: float) -> np.ndarray:
    """Per half tile the one-hit value (module docstring), inf where none of the 3x3 half tiles around
    qualifies. noisy: count of pixels whose halves differ; lit, variance: sums over those pixels of the
    channel means of the input (at least 0) and of v; pixels: the half tiles' pixel counts; all (th', tw')
    float64 (pixels int64); share: the least share of noisy pixels a neighbour needs. Returns (th', tw')
    float64, radiance."""
    qualifies = (noisy >= share * np.maximum(pixels, 1)) & (lit > 0)
    ratio = np.where(qualifies, variance / np.where(lit > 0, lit, 1.0), np.inf)
    padded = np.pad(ratio, 1, constant_values=np.inf)
    th, tw = ratio.shape
    return np.min([padded[dy:dy + th, dx:dx + tw] for dy in range(3) for dx in range(3)], axis=0)


def refuted(out: np.ndarray, color: np.ndarray, color_a: np.ndarray, color_b: np.ndarray,
            emission: np.ndarray | None, one_hit: np.ndarray, candidates: np.ndarray, half: int) -> np.ndarray:
    """Per half tile of side `half` whether its dark pixels refute `out` (module docstring). out, color and
    its halves, emission (or None): (H, W, C) float32, C-contiguous, linear radiance; one_hit, candidates:
    (th', tw') float64 and bool, the half tiles tested. Returns (th', tw') bool."""
    chance = np.ones(one_hit.shape, np.float64)
    hit = np.where(candidates & np.isfinite(one_hit), one_hit, np.inf)
    e = color if emission is None else emission  # not read without emission
    _dark_kernel(out, color, color_a, color_b, e, emission is not None, hit, half, chance)
    with np.errstate(divide="ignore"):  # log 0 = -inf: refuted
        return np.log(chance) < -EVIDENCE


def lower_tail(dark_chances: np.ndarray, lit: int) -> float:
    """P(K <= lit), K the count of pixels not dark, each independently with chance 1 - dark_chances[i];
    dark_chances (N,) float64 in [0, 1]. Dynamic programming over the pixels, counts above `lit` dropped."""
    tail = np.zeros(lit + 1)
    tail[0] = 1.0
    for p in dark_chances:
        tail[1:] = tail[1:] * p + tail[:-1] * (1.0 - p)
        tail[0] *= p
    return float(tail.sum())


def refuted_reference(out: np.ndarray, color: np.ndarray, color_a: np.ndarray, color_b: np.ndarray,
                      emission: np.ndarray | None, one_hit: np.ndarray, candidates: np.ndarray,
                      half: int) -> np.ndarray:
    """Plain-numpy twin of `refuted`."""
    e = np.zeros(out.shape, np.float64) if emission is None else emission.astype(np.float64)
    o, c, a, b = (x.astype(np.float64) - e for x in (out, color, color_a, color_b))
    agree = (color_a == color_b).all(axis=-1)
    dark = agree & (c == 0).all(axis=-1)
    taking = ~agree | dark
    hit = np.where(candidates & np.isfinite(one_hit), one_hit, np.inf)
    per_pixel = np.repeat(np.repeat(hit, half, axis=0), half, axis=1)[:o.shape[0], :o.shape[1]]
    dark_chance = np.exp(-np.maximum(o.mean(axis=-1), 0.0) / per_pixel)
    result = np.zeros(hit.shape, np.bool_)
    for ty, tx in zip(*np.nonzero(np.isfinite(hit)), strict=True):
        tile = (slice(ty * half, (ty + 1) * half), slice(tx * half, (tx + 1) * half))
        if dark[tile].any():
            chances = dark_chance[tile][taking[tile]]
            lit = int(taking[tile].sum() - dark[tile].sum())
            with np.errstate(divide="ignore"):
                result[ty, tx] = np.log(lower_tail(chances, lit)) < -EVIDENCE
    return result


@numba.njit(inline="always", cache=True, error_model="numpy")
def _pixel(out, color, a, b, e, has_emission, y, x):  # pragma: no cover - jitted
    """(kind, o) of pixel (y, x): kind 0 exact (halves agree, not 0 less e: takes no part), 1 dark (both
    halves 0 less e), 2 noisy (halves differ); o the output's channel mean less e, at least 0 (float64)."""
    channels = out.shape[2]
    agree, zero, mean_out = True, True, 0.0
    for c in range(channels):
        agree = agree and a[y, x, c] == b[y, x, c]
        level = np.float64(color[y, x, c]) - e[y, x, c] if has_emission else np.float64(color[y, x, c])
        zero = zero and level == 0
        mean_out += np.float64(out[y, x, c]) - e[y, x, c] if has_emission else np.float64(out[y, x, c])
    kind = (1 if zero else 0) if agree else 2
    return kind, max(mean_out / channels, 0.0)


@numba.njit(parallel=True, cache=True, error_model="numpy")
def _dark_kernel(out, color, a, b, e, has_emission, hit, half, chance):  # pragma: no cover - jitted
    """chance (th', tw') float64: per half tile with a finite `hit` (its one-hit value) and a dark pixel,
    P(K <= k) (module docstring, `lower_tail`), else left as it is. A task per row of half tiles: per tile one
    pass counting, one for the dynamic programme."""
    height, width = out.shape[:2]
    for ty in numba.prange(hit.shape[0]):
        for tx in range(hit.shape[1]):
            h = hit[ty, tx]
            if not math.isfinite(h):
                continue
            y0, y1, x0, x1 = ty * half, min((ty + 1) * half, height), tx * half, min((tx + 1) * half, width)
            dark, lit = 0, 0
            for y in range(y0, y1):
                for x in range(x0, x1):
                    kind = _pixel(out, color, a, b, e, has_emission, y, x)[0]
                    dark += kind == 1
                    lit += kind == 2
            if dark == 0:
                continue
            tail = np.zeros(lit + 1)
            tail[0] = 1.0
            for y in range(y0, y1):
                for x in range(x0, x1):
                    kind, o = _pixel(out, color, a, b, e, has_emission, y, x)
                    if kind == 0:
                        continue
                    p = math.exp(-o / h)
                    for j in range(lit, 0, -1):
                        tail[j] = tail[j] * p + tail[j - 1] * (1.0 - p)
                    tail[0] *= p
            chance[ty, tx] = tail.sum()
