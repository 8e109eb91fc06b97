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

The one-hit value is estimated from variance-to-mean ratios v / c (v = ((A - B) / 2)^2, the pixel estimate's
variance): for n samples that each hit (value M) or miss, v / c = M (1 - q) / n with q the chance of a hit,
which is M / n where hits are rare and less where samples rarely miss, so that a smaller h refutes more
readily. It is the least ratio of the 3x3 half tiles around whose share of noisy pixels (halves that differ)
is at least the blend's NOISY_SHARE, or the half tile's own ratio over its noisy pixels where that is larger:
a dim room's few bright sky samples (a one-hit value of ~25 in tests/service/stages/test_noise_blend.py,
beside a lit floor of ratio 0.2) must not make its many dark pixels refute an output that is right. Where no
neighbour qualifies nothing is refuted. An all-dark half tile beside a region whose samples rarely miss is
judged by that region's ratio, the boldest case: its light must add up to 7 of those one-hit values. A pixel
is dark where both its halves, less emission, are within DARK_FRACTION of one hit of 0 (a renderer's shadow
holds values of 1e-15); pixels whose halves agree on another value (exact pixels) take no part. Tested only on
the half tiles the blend asks about (`candidates`).

numba kernel `_dark_kernel`; `refuted_reference` is the numpy twin.
"""

from __future__ import annotations

import math

import numba
import numpy as np

EVIDENCE = 7.0  # refuted where the output's light leaves the dark pixels a chance below exp(-7) ~ 1e-3
DARK_FRACTION = 1e-3  # a pixel is dark where both halves (less emission) are within this share of one hit of 0
# A neighbour whose noisy pixels average this little radiance is no measure of a hit: a renderer's shadow holds
# specks of 1e-15 whose halves differ, and their ratio (~5e-16) would make every dark pixel around refute
SPECK = 1e-9


def one_hit_values(noisy: np.ndarray, lit: np.ndarray, variance: np.ndarray, pixels: np.ndarray,
                   share: float) -> np.ndarray:
    """Per half tile the one-hit value (module docstring): the least variance-to-mean ratio of the 3x3 half
    tiles around that qualify, or the half tile's own where it has noisy pixels and that is larger; inf where
    no neighbour qualifies. noisy: count of pixels whose halves differ; lit, variance: sums over those pixels
    of the channel means of the input (at least 0) and of v; pixels: the half tiles' pixel counts; all (th',
    tw') float64 (pixels int64); share: the least share of noisy pixels a neighbour needs, whose input must
    also average more than SPECK. Returns (th', tw') float64, radiance."""
    ratio = variance / np.where(lit > 0, lit, 1.0)
    qualifies = (noisy >= share * np.maximum(pixels, 1)) & (lit > SPECK * np.maximum(noisy, 1))
    padded = np.pad(np.where(qualifies, ratio, np.inf), 1, constant_values=np.inf)
    th, tw = ratio.shape
    around = np.min([padded[dy:dy + th, dx:dx + tw] for dy in range(3) for dx in range(3)], axis=0)
    return np.maximum(around, np.where((noisy > 0) & (lit > 0), ratio, 0.0))


def refuted(out: np.ndarray, color_a: np.ndarray, color_b: np.ndarray, emission: np.ndarray | None,
            one_hit: np.ndarray, candidates: np.ndarray, half: int) -> np.ndarray:
    """Per half tile of side `half` whether its dark pixels refute `out` (module docstring). out, the input's
    halves, emission (or None): (H, W, C) float32, C-contiguous, linear radiance; one_hit, candidates:
    (th', tw') float64 and bool, the half tiles tested. Returns (th', tw') bool."""
    chance = np.ones(one_hit.shape, np.float64)
    hit = np.where(candidates & np.isfinite(one_hit), one_hit, np.inf)
    e = out if emission is None else emission  # not read without emission
    _dark_kernel(out, color_a, color_b, e, emission is not None, hit, half, chance)
    with np.errstate(divide="ignore"):  # log 0 = -inf: refuted
        return np.log(chance) < -EVIDENCE


def dark_levels(one_hit: np.ndarray, refute: np.ndarray) -> np.ndarray:
    """Per half tile the level within which a pixel is dark (`is_dark`) where `refute` ((th', tw') bool) says
    its dark pixels refute the output, -1 elsewhere: (th', tw') float64, radiance."""
    return np.where(refute, DARK_FRACTION * one_hit, -1.0)


def lower_tail(dark_chances: np.ndarray, lit: int) -> float:
    """P(K <= lit), K the count of pixels not dark, each independently with chance 1 - dark_chances[i];
    dark_chances (N,) float64 in [0, 1]. Dynamic programming over the pixels, counts above `lit` dropped."""
    tail = np.zeros(lit + 1)
    tail[0] = 1.0
    for p in dark_chances:
        tail[1:] = tail[1:] * p + tail[:-1] * (1.0 - p)
        tail[0] *= p
    return float(tail.sum())


def refuted_reference(out: np.ndarray, color_a: np.ndarray, color_b: np.ndarray, emission: np.ndarray | None,
                      one_hit: np.ndarray, candidates: np.ndarray, half: int) -> np.ndarray:
    """Plain-numpy twin of `refuted`."""
    e = np.zeros(out.shape, np.float64) if emission is None else emission.astype(np.float64)
    hit = np.where(candidates & np.isfinite(one_hit), one_hit, np.inf)
    per_pixel = np.repeat(np.repeat(hit, half, axis=0), half, axis=1)[:out.shape[0], :out.shape[1]]
    o = out.astype(np.float64) - e
    dark = dark_mask_reference(color_a, color_b, emission, DARK_FRACTION * per_pixel)
    taking = ~(color_a == color_b).all(axis=-1) | dark
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


def dark_mask_reference(color_a: np.ndarray, color_b: np.ndarray, emission: np.ndarray | None,
                        level: np.ndarray) -> np.ndarray:
    """(H, W) bool: `is_dark` per pixel, level (H, W) float64; numpy."""
    e = 0.0 if emission is None else emission.astype(np.float64)
    near = (np.abs(color_a.astype(np.float64) - e) <= level[..., None]) & (np.abs(color_b.astype(np.float64) - e)
                                                                          <= level[..., None])
    return near.all(axis=-1)


@numba.njit(inline="always", cache=True, error_model="numpy")
def is_dark(a, b, e, has_emission, y, x, level):  # pragma: no cover - jitted
    """Whether both halves a, b of pixel (y, x), less e with `has_emission`, are within `level` of 0 in every
    channel (float64 arithmetic)."""
    dark = True
    for c in range(a.shape[2]):
        ea = np.float64(e[y, x, c]) if has_emission else 0.0
        dark = dark and abs(np.float64(a[y, x, c]) - ea) <= level and abs(np.float64(b[y, x, c]) - ea) <= level
    return dark


@numba.njit(inline="always", cache=True, error_model="numpy")
def _pixel(out, a, b, e, has_emission, y, x, level):  # pragma: no cover - jitted
    """(kind, o) of pixel (y, x): kind 1 dark (`is_dark` within `level`), 0 exact (halves agree, not dark:
    takes no part), 2 noisy (halves differ); o the output's channel mean less e, at least 0 (float64)."""
    channels = out.shape[2]
    agree, mean_out = True, 0.0
    for c in range(channels):
        agree = agree and a[y, x, c] == b[y, x, c]
        mean_out += np.float64(out[y, x, c]) - e[y, x, c] if has_emission else np.float64(out[y, x, c])
    kind = 1 if is_dark(a, b, e, has_emission, y, x, level) else (0 if agree else 2)
    return kind, max(mean_out / channels, 0.0)


@numba.njit(parallel=True, cache=True, error_model="numpy")
def _dark_kernel(out, a, b, e, has_emission, hit, half, chance):  # pragma: no cover - jitted
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
                    kind = _pixel(out, a, b, e, has_emission, y, x, DARK_FRACTION * h)[0]
                    dark += kind == 1
                    lit += kind == 2
            if dark == 0:
                continue
            tail = np.zeros(lit + 1)
            tail[0] = 1.0
            for y in range(y0, y1):
                for x in range(x0, x1):
                    kind, o = _pixel(out, a, b, e, has_emission, y, x, DARK_FRACTION * h)
                    if kind == 0:
                        continue
                    p = math.exp(-o / h)
                    for j in range(lit, 0, -1):
                        tail[j] = tail[j] * p + tail[j - 1] * (1.0 - p)
                    tail[0] *= p
            chance[ty, tx] = tail.sum()
