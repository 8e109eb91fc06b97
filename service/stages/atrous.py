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
The compiled pass works on planar (K, H, W) arrays (`atrous` keeps them planar over its passes): rows
in parallel, each tap offset a branch-free SIMD loop along the row, exp by `bilateral.neg_exp`. Taps
with an exponent above MAX_EXPONENT or w_n below WEIGHT_FLOOR get weight 0 (no subnormal arithmetic).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
from numba import njit, prange

from service.kernels.window import overlap
from service.stages.bilateral import neg_exp
from service.stages.reprojection import surface_hit

B3_SPLINE = (1 / 16, 1 / 4, 3 / 8, 1 / 4, 1 / 16)  # Dammertz 2010 / Schied 2017 sec. 4.3: 1D B3-spline taps
GAUSS_3X3 = (1 / 4, 1 / 2, 1 / 4)  # Schied 2017 sec. 4.3: 1D taps of the 3x3 variance prefilter
DEPTH_GRADIENT_FLOOR = 1e-8  # scene units per pixel; Falcor SVGF's floor of fwidth(z)
VARIANCE_EPS = 1e-10  # luminance^2; Falcor SVGF's epsilon under the square root of phi_l
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

    @cached_property
    def hit(self) -> np.ndarray:
        """(H, W) float32: 1 where a surface was hit (|n|^2 > NORMAL_HIT), else 0; computed once per frame."""
        return surface_hit(self.normal).astype(np.float32)

    @cached_property
    def normal_planes(self) -> np.ndarray:
        """(3, H, W) float32: the normal as planes, the layout of the compiled passes."""
        return np.ascontiguousarray(np.moveaxis(self.normal, -1, 0), np.float32)


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
    """min(max(0, cos), 1)^sigma_n (normals longer than 1, which the frame contract lets in, would raise cos
    above 1 and the power to inf); by repeated squaring when sigma_n is a power of two (the default 128)."""
    cos = np.clip(cos, np.float32(0.0), np.float32(1.0))
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
    hit = surface_hit(guides.normal)
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


WEIGHT_FLOOR = 1e-18  # w_n below this is 0: keeps the squarings of cos out of float32 subnormals (slow)
MAX_SQUARINGS = 10  # sigma_n up to 2^10 is evaluated by repeated squaring in the compiled pass


@njit(cache=True, error_model="numpy")
def _tap_weights(row_p, row_q, h, inv_distance, sigma_normal, squarings, cos_min, weight):
    """Weights h * w_z * w_n * w_l (eqs. 1-5) of pixel pairs p, q along a row segment, into weight (n,) float32.

    row_*: (depth, lum, hit, n0, n1, n2) (n,) float32 rows of p and of q; row_p also ends with inv_phi_z and
    inv_phi_l. w_n = min(n_p . n_q, 1)^sigma_n where both are hits (0 below cos_min, where it is under
    WEIGHT_FLOOR), 1 where neither is, 0 where one is; squarings >= 0: sigma_n = 2^squarings. Branch-free (SIMD)."""
    z_p, l_p, hit_p, p0, p1, p2, iz_p, il_p = row_p
    z_q, l_q, hit_q, q0, q1, q2 = row_q
    max_exponent = np.float32(MAX_EXPONENT)
    one = np.float32(1.0)
    for t in range(weight.size):
        cos = min(p0[t] * q0[t] + p1[t] * q1[t] + p2[t] * q2[t], one)  # normals longer than 1: no inf power
        weight[t] = cos if cos >= cos_min else np.float32(0.0)
    if squarings >= 0:
        for t in range(weight.size):
            cos = weight[t]
            for k in range(MAX_SQUARINGS):
                cos = cos * cos if k < squarings else cos
            weight[t] = cos
    else:
        for t in range(weight.size):
            weight[t] = weight[t] ** sigma_normal
    for t in range(weight.size):
        w_n = hit_p[t] * hit_q[t] * weight[t] + (one - hit_p[t]) * (one - hit_q[t])
        exponent = abs(z_p[t] - z_q[t]) * iz_p[t] * inv_distance + abs(l_p[t] - l_q[t]) * il_p[t]
        w = h * neg_exp(exponent) * w_n
        weight[t] = w if exponent <= max_exponent else np.float32(0.0)


@njit(cache=True, error_model="numpy")
def _edge_aware_row(values, lum, inv_phi_l, depth, grad, normal, hit, kernel, step, sigma_depth, sigma_normal,
                    squarings, cos_min, squared, y, out):
    """One output row y of `_edge_aware_planes`. Each tap offset is a branch-free loop over a contiguous row
    segment (1D slices indexed from 0, which LLVM turns into SIMD code)."""
    channels, height, width = values.shape
    radius = kernel.size // 2
    num = np.zeros((channels, width), np.float32)
    den = np.zeros(width, np.float32)
    weight = np.empty(width, np.float32)
    inv_phi_z = np.empty(width, np.float32)
    grad_p = grad[y]
    for x in range(width):
        inv_phi_z[x] = np.float32(1.0) / (sigma_depth * grad_p[x] * np.float32(step))
    for i in range(-radius, radius + 1):
        yn = y + i * step
        if yn < 0 or yn >= height:
            continue
        for j in range(-radius, radius + 1):
            off = j * step
            x0, x1 = max(0, -off), min(width, width - off)
            if x0 >= x1:
                continue
            n = x1 - x0
            p, q = slice(x0, x1), slice(x0 + off, x1 + off)
            h = kernel[i + radius] * kernel[j + radius]
            wt = weight[:n]
            if i == 0 and j == 0:
                wt[:] = h
            else:
                row_p = (depth[y, p], lum[y, p], hit[y, p], normal[0, y, p], normal[1, y, p], normal[2, y, p],
                         inv_phi_z[p], inv_phi_l[y, p])
                row_q = (depth[yn, q], lum[yn, q], hit[yn, q], normal[0, yn, q], normal[1, yn, q], normal[2, yn, q])
                inv_distance = np.float32(1.0) / np.float32(np.sqrt(np.float32(i * i + j * j)))
                _tap_weights(row_p, row_q, h, inv_distance, sigma_normal, squarings, cos_min, wt)
            d = den[p]
            for t in range(n):
                d[t] += wt[t]
            for c in range(channels):
                acc, v_q = num[c, p], values[c, yn, q]
                if c == squared:
                    for t in range(n):
                        acc[t] += wt[t] * wt[t] * v_q[t]
                else:
                    for t in range(n):
                        acc[t] += wt[t] * v_q[t]
    for c in range(channels):
        row = out[c, y]
        acc = num[c]
        if c == squared:
            for x in range(width):
                row[x] = acc[x] / (den[x] * den[x])
        else:
            for x in range(width):
                row[x] = acc[x] / den[x]


@njit(parallel=True, cache=True, error_model="numpy")
def _edge_aware_planes(values, lum, inv_phi_l, depth, grad, normal, hit, kernel, step, sigma_depth, sigma_normal,
                       squarings, cos_min, squared):
    """`edge_aware_filter` on planar arrays: values (K, H, W), normal (3, H, W), the rest (H, W) float32; hit 1 or 0;
    inv_phi_l = 1 / phi_l. Rows in parallel."""
    out = np.empty(values.shape, np.float32)
    for y in prange(values.shape[1]):
        _edge_aware_row(values, lum, inv_phi_l, depth, grad, normal, hit, kernel, step, sigma_depth, sigma_normal,
                        squarings, cos_min, squared, np.int64(y), out)
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
    planes = np.ascontiguousarray(np.moveaxis(np.asarray(values, np.float32), -1, 0))
    out = _edge_aware_pass(planes, np.asarray(lum, np.float32), np.asarray(phi_luminance, np.float32), guides,
                           kernel, step, sigma_depth, sigma_normal, squared_channel)
    return np.ascontiguousarray(np.moveaxis(out, 0, -1))


def _edge_aware_pass(
    planes: np.ndarray,
    lum: np.ndarray,
    phi_luminance: np.ndarray,
    guides: EdgeGuides,
    kernel: np.ndarray,
    step: int,
    sigma_depth: float,
    sigma_normal: float,
    squared_channel: int,
) -> np.ndarray:
    """`edge_aware_filter` on planar values (K, H, W) float32; returns (K, H, W) float32."""
    exponent = int(sigma_normal)
    power_of_two = exponent == sigma_normal and 0 < exponent <= 1 << MAX_SQUARINGS and exponent & (exponent - 1) == 0
    cos_min = np.float32(WEIGHT_FLOOR ** (1.0 / sigma_normal))  # max(0, cos)^sigma_n < WEIGHT_FLOOR below it
    return _edge_aware_planes(
        np.ascontiguousarray(planes, np.float32),
        np.ascontiguousarray(lum, np.float32),
        np.ascontiguousarray(np.float32(1.0) / phi_luminance, np.float32),
        guides.depth,
        guides.depth_gradient,
        guides.normal_planes,
        guides.hit,
        np.asarray(kernel, np.float32),
        int(step),
        np.float32(sigma_depth),
        np.float32(sigma_normal),
        exponent.bit_length() - 1 if power_of_two else -1,
        cos_min,
        int(squared_channel),
    )


@njit(parallel=True, cache=True, error_model="numpy")
def _pass_inputs(planes, sigma_luminance):
    """Luminance of planes[0:3] and phi_l = sigma_l sqrt(g3x3(planes[3]) + eps) (Schied eq. 5), (H, W) float32 each.
    The compiled twin of `luminance` and `prefilter_variance` (taps in the same order), rows in parallel."""
    _, height, width = planes.shape
    lum = np.empty((height, width), np.float32)
    phi = np.empty((height, width), np.float32)
    wr, wg, wb = np.float32(LUMINANCE_WEIGHTS[0]), np.float32(LUMINANCE_WEIGHTS[1]), np.float32(LUMINANCE_WEIGHTS[2])
    eps = np.float32(VARIANCE_EPS)
    for yy in prange(height):
        y = np.int64(yy)
        r, g, b, out = planes[0, y], planes[1, y], planes[2, y], lum[y]
        for x in range(width):
            out[x] = wr * r[x] + wg * g[x] + wb * b[x]
        num = np.zeros(width, np.float32)
        den = np.zeros(width, np.float32)
        for dy in range(-1, 2):
            if not 0 <= y + dy < height:
                continue
            for dx in range(-1, 2):
                x0, x1 = max(0, -dx), min(width, width - dx)
                if x0 >= x1:
                    continue
                weight = np.float32(GAUSS_3X3[dy + 1] * GAUSS_3X3[dx + 1])
                acc, d, v = num[x0:x1], den[x0:x1], planes[3, y + dy, x0 + dx:x1 + dx]
                for t in range(x1 - x0):
                    acc[t] += weight * v[t]
                    d[t] += weight
        out = phi[y]
        for x in range(width):
            out[x] = sigma_luminance * np.sqrt(max(num[x] / den[x], np.float32(0.0)) + eps)
    return lum, phi


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
    planes = np.ascontiguousarray(np.concatenate([np.moveaxis(color, -1, 0), variance[None]], axis=0), np.float32)
    first = None
    for k in range(params.iterations):
        lum, phi = _pass_inputs(planes, np.float32(params.sigma_luminance))
        planes = _edge_aware_pass(
            planes, lum, phi, guides, kernel, 1 << k, params.sigma_depth, params.sigma_normal, squared_channel=3
        )
        if k == 0:
            first = np.ascontiguousarray(np.moveaxis(planes[:3], 0, -1))
    out = np.ascontiguousarray(np.moveaxis(planes[:3], 0, -1))
    return out, np.ascontiguousarray(planes[3]), out.copy() if first is None else first
