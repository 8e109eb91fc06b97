"""Edge-aware a-trous wavelet filter of SVGF (Schied et al. 2017, sec. 4.3; Dammertz et al. 2010).

One pass filters per-pixel values with the weights

    w(p, q) = h(q - p) * w_z * w_n * w_l                                    (Schied eq. 1)
    w_z = exp(-|z_p - z_q| / (sigma_z |grad z_p| |p - q| + eps))            (eq. 3)
    w_n = max(0, n_p . n_q) ^ sigma_n                                        (eq. 4)
    w_l = exp(-|l_p - l_q| / phi_l(p)),  phi_l = sigma_l sqrt(g3x3(Var(l))_p + eps)   (eq. 5)

over taps q = p + step * (i, j), |i|, |j| <= 2, with h the 5x5 B3-spline kernel and step = 2^k in
iteration k. The variance channel is filtered with the squared weights, Var_out = sum w^2 Var /
(sum w)^2 (eq. 2). The same pass, with a flat 7x7 kernel, step 1 and a constant phi_l, is SVGF's
spatial moment estimate for pixels with short history (`service.stages.svgf`).

Pixels where nothing was hit (zero normal) only mix with each other. Taps outside the frame are
skipped (no padding). `edge_aware_filter` is compiled; `edge_aware_filter_numpy` is its reference.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit, prange

from service.stages.window import overlap

B3_SPLINE = (1 / 16, 1 / 4, 3 / 8, 1 / 4, 1 / 16)  # Dammertz 2010 / Schied 2017 sec. 4.3: 1D B3-spline taps
GAUSS_3X3 = (1 / 4, 1 / 2, 1 / 4)  # Schied 2017 sec. 4.3: 1D taps of the 3x3 variance prefilter
DEPTH_GRADIENT_FLOOR = 1e-8  # scene units per pixel; Falcor SVGF's floor of fwidth(z)
VARIANCE_EPS = 1e-10  # luminance^2; Falcor SVGF's epsilon under the square root of phi_l
NORMAL_HIT = 0.25  # squared normal length above which a pixel is a surface hit
LUMINANCE_WEIGHTS = (0.2126, 0.7152, 0.0722)  # Rec. 709 / sRGB luminance of linear RGB
MAX_EXPONENT = 40.0  # taps with w_z * w_l < e^-40 (~4e-18) are skipped by the compiled pass


@dataclass(frozen=True)
class AtrousParams:
    iterations: int = 5  # Schied 2017 sec. 4.3: 5 a-trous levels (steps 1, 2, 4, 8, 16)
    sigma_depth: float = 1.0  # sigma_z, Schied 2017 eq. 3
    sigma_normal: float = 128.0  # sigma_n, exponent of Schied 2017 eq. 4
    sigma_luminance: float = 4.0  # sigma_l, Schied 2017 eq. 5

    def __post_init__(self) -> None:
        if self.iterations < 0:
            raise ValueError(f"iterations must be >= 0, got {self.iterations}")
        for name in ("sigma_depth", "sigma_normal", "sigma_luminance"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")


@dataclass(frozen=True)
class EdgeGuides:
    """Edge-stopping inputs of one frame: depth (H, W) float32 scene units, depth_gradient (H, W) float32
    |grad z| in scene units per pixel (>= DEPTH_GRADIENT_FLOOR), normal (H, W, 3) float32 unit or zero."""

    depth: np.ndarray
    depth_gradient: np.ndarray
    normal: np.ndarray


def luminance(rgb: np.ndarray) -> np.ndarray:
    """(H, W, 3) float32 linear RGB -> (H, W) float32 luminance (Rec. 709 weights)."""
    return np.ascontiguousarray(rgb @ np.asarray(LUMINANCE_WEIGHTS, np.float32), np.float32)


def depth_gradient(depth: np.ndarray) -> np.ndarray:
    """|dz/dx| + |dz/dy| per pixel (the GPU's fwidth), each the smaller one-sided difference so that a
    silhouette does not inflate the gradient of the surfaces on either side of it.

    depth: (H, W) float32 scene units. Returns (H, W) float32 >= DEPTH_GRADIENT_FLOOR.
    """
    total = np.zeros(depth.shape, np.float32)
    for axis in (0, 1):
        diff = np.abs(np.diff(depth, axis=axis))
        pad = [(0, 0), (0, 0)]
        pad[axis] = (1, 0)
        backward = np.pad(diff, pad, constant_values=np.inf)
        pad[axis] = (0, 1)
        forward = np.pad(diff, pad, constant_values=np.inf)
        one_sided = np.minimum(backward, forward)
        total += np.where(np.isfinite(one_sided), one_sided, np.float32(0.0))
    return np.maximum(total, np.float32(DEPTH_GRADIENT_FLOOR))


def edge_guides(depth: np.ndarray, normal: np.ndarray) -> EdgeGuides:
    """EdgeGuides from frame layers: depth (H, W, 1) float32, normal (H, W, 3) float32."""
    z = np.ascontiguousarray(depth[..., 0], np.float32)
    return EdgeGuides(z, depth_gradient(z), np.ascontiguousarray(normal, np.float32))


def prefilter_variance(variance: np.ndarray) -> np.ndarray:
    """3x3 Gaussian blur of (H, W) float32 variance, renormalised over in-frame taps (Schied sec. 4.3)."""
    height, width = variance.shape
    num = np.zeros((height, width), np.float32)
    den = np.zeros((height, width), np.float32)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            pair = overlap(height, width, dy, dx)
            if pair is None:
                continue
            centre, neighbour = pair
            weight = np.float32(GAUSS_3X3[dy + 1] * GAUSS_3X3[dx + 1])
            num[centre] += weight * variance[neighbour]
            den[centre] += weight
    return num / den


def _normal_power(cos: np.ndarray | float, sigma_normal: float):
    """max(0, cos)^sigma_n; by repeated squaring when sigma_n is a power of two (the default 128)."""
    cos = np.maximum(cos, np.float32(0.0))
    exponent = int(sigma_normal)
    if exponent == sigma_normal and exponent > 0 and exponent & (exponent - 1) == 0:
        while exponent > 1:
            cos = cos * cos
            exponent //= 2
        return cos
    return cos ** np.float32(sigma_normal)


def edge_aware_filter_numpy(
    values: np.ndarray,
    lum: np.ndarray,
    phi_luminance: np.ndarray,
    guides: EdgeGuides,
    kernel: np.ndarray,
    step: int,
    sigma_depth: float,
    sigma_normal: float,
    squared_channel: int = -1,
) -> np.ndarray:
    """Reference of `edge_aware_filter` in numpy, tap by tap (same arguments)."""
    height, width, channels = values.shape
    radius = kernel.size // 2
    one = np.float32(1.0)
    hit = np.einsum("hwc,hwc->hw", guides.normal, guides.normal) > NORMAL_HIT
    phi_z = np.float32(sigma_depth) * guides.depth_gradient * np.float32(step)
    num = np.zeros((height, width, channels), np.float32)
    den = np.zeros((height, width), np.float32)
    for i in range(-radius, radius + 1):
        for j in range(-radius, radius + 1):
            pair = overlap(height, width, i * step, j * step)
            if pair is None:
                continue
            c, n = pair
            h = np.float32(kernel[i + radius] * kernel[j + radius])
            if i == 0 and j == 0:
                weight = np.full(lum[c].shape, h, np.float32)
            else:
                distance = np.float32(np.sqrt(i * i + j * j))
                exponent = np.abs(guides.depth[c] - guides.depth[n]) / (phi_z[c] * distance)
                exponent += np.abs(lum[c] - lum[n]) / phi_luminance[c]
                cos = np.einsum("hwc,hwc->hw", guides.normal[c], guides.normal[n])
                w_n = np.where(hit[c] & hit[n], _normal_power(cos, sigma_normal), np.float32(0.0))
                w_n = np.where(~hit[c] & ~hit[n], one, w_n)
                weight = h * np.exp(-exponent) * w_n
            tap = weight[..., None] * values[n]
            if squared_channel >= 0:
                tap[..., squared_channel] *= weight
            num[c] += tap
            den[c] += weight
    out = num / den[..., None]
    if squared_channel >= 0:
        out[..., squared_channel] = num[..., squared_channel] / (den * den)
    return out


@njit(cache=True, inline="always")
def _pow_normal(cos, sigma_normal, squarings):
    if cos <= 0.0:
        return np.float32(0.0)
    if squarings >= 0:
        for _ in range(squarings):
            cos = cos * cos
        return cos
    return cos ** sigma_normal


@njit(parallel=True, cache=True)
def _edge_aware_kernel(values, lum, phi_luminance, depth, grad, normal, hit, kernel, step, sigma_depth, sigma_normal,
                       squarings, squared):
    height, width, channels = values.shape
    radius = kernel.size // 2
    out = np.empty_like(values)
    inv_distance = np.zeros((2 * radius + 1, 2 * radius + 1), np.float32)
    for i in range(-radius, radius + 1):
        for j in range(-radius, radius + 1):
            if i or j:
                inv_distance[i + radius, j + radius] = np.float32(1.0) / np.float32(np.sqrt(np.float32(i * i + j * j)))
    for yy in prange(height):
        y = np.int64(yy)
        acc = np.zeros(channels, np.float32)
        for x in range(width):
            acc[:] = 0.0
            den = np.float32(0.0)
            hit_p = hit[y, x]
            inv_phi_z = np.float32(1.0) / (sigma_depth * grad[y, x] * np.float32(step))
            inv_phi_l = np.float32(1.0) / phi_luminance[y, x]
            z_p, l_p = depth[y, x], lum[y, x]
            n0, n1, n2 = normal[y, x, 0], normal[y, x, 1], normal[y, x, 2]
            for i in range(-radius, radius + 1):
                yn = y + i * step
                if yn < 0 or yn >= height:
                    continue
                for j in range(-radius, radius + 1):
                    xn = x + j * step
                    if xn < 0 or xn >= width:
                        continue
                    h = kernel[i + radius] * kernel[j + radius]
                    if i == 0 and j == 0:
                        weight = h
                    else:
                        hit_q = hit[yn, xn]
                        if hit_p and hit_q:
                            cos = n0 * normal[yn, xn, 0] + n1 * normal[yn, xn, 1] + n2 * normal[yn, xn, 2]
                            w_n = _pow_normal(cos, sigma_normal, squarings)
                        elif hit_p or hit_q:
                            continue  # weight 0: a surface never mixes with the background
                        else:
                            w_n = np.float32(1.0)
                        exponent = abs(z_p - depth[yn, xn]) * inv_phi_z * inv_distance[i + radius, j + radius]
                        exponent += abs(l_p - lum[yn, xn]) * inv_phi_l
                        if exponent > MAX_EXPONENT or w_n == 0.0:
                            continue  # weight below e^-MAX_EXPONENT: as good as zero
                        weight = h * np.exp(-exponent) * w_n
                    for c in range(channels):
                        tap = weight * values[yn, xn, c]
                        acc[c] += tap * weight if c == squared else tap
                    den += weight
            for c in range(channels):
                out[y, x, c] = acc[c] / (den * den) if c == squared else acc[c] / den
    return out


def edge_aware_filter(
    values: np.ndarray,
    lum: np.ndarray,
    phi_luminance: np.ndarray,
    guides: EdgeGuides,
    kernel: np.ndarray,
    step: int,
    sigma_depth: float,
    sigma_normal: float,
    squared_channel: int = -1,
) -> np.ndarray:
    """One edge-aware pass (Schied 2017 eqs. 1-5) over taps p + step * (i, j), |i|, |j| <= len(kernel) // 2.

    values: (H, W, K) float32 to filter (colour, moments, variance, ...); channel `squared_channel`
        (if >= 0) is a variance and is filtered with squared weights, Var = sum w^2 Var / (sum w)^2.
    lum: (H, W) float32 luminance used by w_l; phi_luminance: (H, W) float32 > 0, its scale phi_l(p).
    guides: EdgeGuides of the frame. kernel: (2R+1,) float32 1D kernel h; the 2D one is its outer product.
    step: tap spacing in pixels. sigma_depth, sigma_normal: sigma_z and sigma_n.
    Returns (H, W, K) float32. The centre tap has weight h(0, 0) > 0, so the sums never vanish; a
    constant input is returned unchanged. Compiled; parity with `edge_aware_filter_numpy` is tested.
    """
    exponent = int(sigma_normal)
    power_of_two = exponent == sigma_normal and exponent > 0 and exponent & (exponent - 1) == 0
    return _edge_aware_kernel(
        np.ascontiguousarray(values, np.float32),
        np.ascontiguousarray(lum, np.float32),
        np.ascontiguousarray(phi_luminance, np.float32),
        guides.depth,
        guides.depth_gradient,
        guides.normal,
        np.einsum("hwc,hwc->hw", guides.normal, guides.normal) > NORMAL_HIT,
        np.asarray(kernel, np.float32),
        int(step),
        np.float32(sigma_depth),
        np.float32(sigma_normal),
        exponent.bit_length() - 1 if power_of_two else -1,
        int(squared_channel),
    )


def atrous(
    color: np.ndarray, variance: np.ndarray, guides: EdgeGuides, params: AtrousParams
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """SVGF's wavelet filter: `params.iterations` edge-aware passes with steps 1, 2, 4, ...

    color: (H, W, 3) float32 (demodulated) linear radiance; variance: (H, W) float32 >= 0 variance of
    its luminance. Each pass prefilters the variance by a 3x3 Gaussian for phi_l, then filters colour and
    variance together. Returns (color, variance, color after the first pass); SVGF keeps the latter as
    its temporal colour history. With 0 iterations all three are the input.
    """
    kernel = np.asarray(B3_SPLINE, np.float32)
    values = np.concatenate([color, variance[..., None]], axis=-1).astype(np.float32)
    first = color
    for k in range(params.iterations):
        phi = np.float32(params.sigma_luminance) * np.sqrt(
            np.maximum(prefilter_variance(values[..., 3]), 0) + np.float32(VARIANCE_EPS)
        )
        values = edge_aware_filter(
            values, luminance(values[..., :3]), phi, guides, kernel, 1 << k, params.sigma_depth,
            params.sigma_normal, squared_channel=3,
        )
        if k == 0:
            first = values[..., :3].copy()
    return np.ascontiguousarray(values[..., :3]), np.ascontiguousarray(values[..., 3]), first
