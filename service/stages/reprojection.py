"""Reprojection: warp a buffer of the previous frame onto the current frame by backward motion.

Motion follows the frame format (shared FRAME_FORMAT.md): the surface seen at the centre of pixel
(x, y) now was seen at (x + X, y + Y) in the previous frame, x to the right and y downwards, in
pixels. In array indices, pixel (row y, column x) samples the previous frame at the continuous index
position (y + Y, x + X), where integer positions are pixel centres. The sample is bilinear over the
four surrounding pixels, and a tap counts only when it is consistent (inside the frame and, when the
depth/normal pairs are given, with matching depth and normal); the taps' weights are renormalised
over the consistent ones, as the SVGF reference implementation does (Schied et al. 2017, Falcor
`SVGFReproject`). A pixel is valid when its sample point is on screen and the consistent taps carry
at least `min_weight` of the bilinear weight. An integer motion therefore reproduces the previous
pixel exactly.

With `catmull_rom`, a valid pixel whose 4x4 taps around the sample point are all inside the frame and
consistent takes the Catmull-Rom spline through them instead (separable, weights in float64), clamped per
channel to the range of its 2x2 bilinear taps, as temporal anti-aliasing samples its history: a history
warped frame after frame by sub-pixel motion is blurred by every bilinear sample (half a pixel there and
back is a [1/4, 1/2, 1/4] kernel) and much less by the spline, which reproduces quadratics; the clamp keeps
its overshoot at an edge out. Other pixels keep the bilinear sample.

The same function serves every temporal pipeline. `reproject` is compiled (numba, rows in parallel);
`reproject_numpy` is its reference, and a parity test holds the two together.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit, prange

from service.kernels.window import overlap

DEPTH_FLOOR = 1e-6  # scene units; denominators of relative depth differences are at least this
NORMAL_HIT = 0.25  # squared length above which a normal is a surface hit (zero normal: nothing hit)


def surface_hit(normal: np.ndarray) -> np.ndarray:
    """normal: (..., 3) float32 normals, zero where nothing was hit. Returns (...) bool: |n|^2 > NORMAL_HIT.
    Summed per channel: an einsum over the last axis of 3 took three times as long (5.2 against 1.7 ms at
    1280x720)."""
    x, y, z = normal[..., 0], normal[..., 1], normal[..., 2]
    square = x * x
    square += y * y
    square += z * z
    return square > NORMAL_HIT


DUAL_OCCLUSION_PX = 0.5  # |motionDual - motion| above which a pixel was occluded in the previous frame, pixels
# (Zeng 2023 sec. 4.4 takes the two vectors' difference as its occlusion mask; the threshold is ours)


def dual_occluded(motion: np.ndarray, motion_dual: np.ndarray) -> np.ndarray:
    """motion, motion_dual: (H, W, 2) float32 backward motion and dual motion vectors, pixels. Returns (H, W)
    bool: the Euclidean length of their difference exceeds DUAL_OCCLUSION_PX (the surface was hidden in the
    previous frame; FRAME_FORMAT.md)."""
    diff = motion_dual - motion
    return np.einsum("hwc,hwc->hw", diff, diff) > np.float32(DUAL_OCCLUSION_PX**2)


@dataclass(frozen=True)
class ReprojectionParams:
    depth_tolerance: float = 0.1  # max relative depth change |z - z_prev| / z of a consistent tap
    normal_cos_min: float = 0.9  # min dot(n, n_prev) of a consistent tap (about 25 degrees)
    min_weight: float = 0.01  # min summed bilinear weight of consistent taps (Falcor SVGF uses 0.01)
    erode: bool = False  # also invalidate pixels with an invalid 3x3 neighbour (as the Choi et al. 2024 code)
    catmull_rom: bool = False  # the clamped Catmull-Rom sample where its 4x4 taps are consistent (module docstring)

    def __post_init__(self) -> None:
        if not self.depth_tolerance > 0:
            raise ValueError(f"depth_tolerance must be > 0, got {self.depth_tolerance}")
        if not -1.0 <= self.normal_cos_min <= 1.0:
            raise ValueError(f"normal_cos_min must be in [-1, 1], got {self.normal_cos_min}")
        if not 0.0 < self.min_weight <= 1.0:
            raise ValueError(f"min_weight must be in (0, 1], got {self.min_weight}")


def sample_positions(motion: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where each pixel samples the previous frame, and whether that point is on screen.

    motion: (H, W, 2) float32 backward motion (X, Y) in pixels. Returns (ys, xs, on_screen): (H, W)
    float64 continuous row and column index positions (pixel centres at integers) and (H, W) bool,
    True where the point lies inside the previous frame's pixel area [-1/2, H - 1/2) x [-1/2, W - 1/2).
    """
    height, width = motion.shape[:2]
    rows, cols = np.indices((height, width), dtype=np.float64)
    ys = rows + motion[..., 1]
    xs = cols + motion[..., 0]
    on_screen = (ys >= -0.5) & (ys < height - 0.5) & (xs >= -0.5) & (xs < width - 0.5)
    # Keep far-off positions small enough to convert to integers; they are invalid anyway.
    return np.clip(ys, -2.0, height + 1.0), np.clip(xs, -2.0, width + 1.0), on_screen


def _consistent(
    index: np.ndarray,
    depth: np.ndarray | None,
    prev_depth: np.ndarray | None,
    normal: np.ndarray | None,
    prev_normal: np.ndarray | None,
    params: ReprojectionParams,
) -> np.ndarray:
    """(H, W) bool: the previous-frame pixel at flat `index` matches the current pixel's surface."""
    ok = np.ones(index.shape, bool)
    if depth is not None and prev_depth is not None:
        z = depth[..., 0]
        z_prev = prev_depth.reshape(-1)[index]
        ok &= np.abs(z - z_prev) <= params.depth_tolerance * np.maximum(np.abs(z), DEPTH_FLOOR)
    if normal is not None and prev_normal is not None:
        n_prev = prev_normal.reshape(-1, 3)[index]
        hit, hit_prev = surface_hit(normal), surface_hit(n_prev)
        cos = np.einsum("hwc,hwc->hw", normal, n_prev)
        ok &= (hit == hit_prev) & (~hit | (cos >= params.normal_cos_min))
    return ok


def erode(valid: np.ndarray) -> np.ndarray:
    """3x3 erosion of a (H, W) bool mask: a pixel stays True only if its in-frame 3x3 neighbours are True."""
    out = valid.copy()
    height, width = valid.shape
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            pair = overlap(height, width, dy, dx)
            if pair is not None and (dy or dx):
                centre, neighbour = pair
                out[centre] &= valid[neighbour]
    return out


def _checked(depth, prev_depth, normal, prev_normal, params):
    if (depth is None) != (prev_depth is None) or (normal is None) != (prev_normal is None):
        raise ValueError("reproject needs depth with prev_depth and normal with prev_normal (both or neither)")
    return params or ReprojectionParams()


@njit(cache=True, error_model="numpy", inline="always")
def _tap_consistent(ty, tx, z, n0, n1, n2, hit, prev_depth, prev_normal, use_depth, use_normal, tolerance, cos_min):
    """`_consistent` for one tap: does previous pixel (ty, tx) match the current surface (depth z, normal n, hit)?"""
    if use_depth and not abs(z - prev_depth[ty, tx]) <= tolerance * max(abs(z), np.float32(DEPTH_FLOOR)):
        return False
    if use_normal:
        p0, p1, p2 = prev_normal[ty, tx, 0], prev_normal[ty, tx, 1], prev_normal[ty, tx, 2]
        hit_prev = p0 * p0 + p1 * p1 + p2 * p2 > np.float32(NORMAL_HIT)
        if hit != hit_prev or (hit and not n0 * p0 + n1 * p1 + n2 * p2 >= cos_min):
            return False
    return True


@njit(parallel=True, cache=True, error_model="numpy")
def _reproject_kernel(
    buffer,
    motion,
    depth,
    prev_depth,
    normal,
    prev_normal,
    use_depth,
    use_normal,
    tolerance,
    cos_min,
    min_weight,
    warped,
):
    """`reproject_numpy` pixel by pixel, rows in parallel: the same float64 sample positions and float32 weights.
    Writes warped (H, W, C) float32 (any strides); returns valid (H, W) bool (before any erosion)."""
    height, width, channels = buffer.shape
    valid = np.empty((height, width), np.bool_)
    one = np.float32(1.0)
    for yy in prange(height):
        y = np.int64(yy)
        acc = np.empty(channels, np.float32)
        for x in range(width):
            for c in range(channels):
                acc[c] = 0.0
            total = np.float32(0.0)
            ys = y + np.float64(motion[y, x, 1])
            xs = x + np.float64(motion[y, x, 0])
            if ys >= -0.5 and ys < height - 0.5 and xs >= -0.5 and xs < width - 0.5:  # on screen (NaN is not)
                y0, x0 = np.floor(ys), np.floor(xs)
                fy, fx = np.float32(ys - y0), np.float32(xs - x0)
                iy, ix = np.int64(y0), np.int64(x0)
                z = depth[y, x] if use_depth else np.float32(0.0)
                n0, n1, n2 = (normal[y, x, 0], normal[y, x, 1], normal[y, x, 2]) if use_normal else (one, one, one)
                hit = n0 * n0 + n1 * n1 + n2 * n2 > np.float32(NORMAL_HIT)
                for tap in range(4):
                    ty, tx = iy + tap // 2, ix + tap % 2
                    weight = (fy if tap // 2 else one - fy) * (fx if tap % 2 else one - fx)
                    if ty < 0 or ty >= height or tx < 0 or tx >= width or not weight > 0:
                        continue
                    if not _tap_consistent(
                        ty, tx, z, n0, n1, n2, hit, prev_depth, prev_normal, use_depth, use_normal, tolerance, cos_min
                    ):
                        continue
                    for c in range(channels):
                        acc[c] += weight * buffer[ty, tx, c]
                    total += weight
            ok = total >= min_weight  # min_weight > 0: off screen is never valid
            valid[y, x] = ok
            for c in range(channels):
                warped[y, x, c] = acc[c] / total if ok else np.float32(0.0)
    return valid


@njit(cache=True, error_model="numpy")
def spline_weights(t):
    """Catmull-Rom weights of the taps at -1, 0, 1, 2 for a sample t in [0, 1) past tap 0: a tuple of four float64
    values, or of four arrays for an array t (the numpy twin's)."""
    return ((-0.5 * t + 1.0) * t * t - 0.5 * t, (1.5 * t - 2.5) * t * t + 1.0,
            (-1.5 * t + 2.0) * t * t + 0.5 * t, (0.5 * t - 0.5) * t * t)


@njit(parallel=True, cache=True, error_model="numpy")
def _spline_kernel(
    buffer, motion, depth, prev_depth, normal, prev_normal, use_depth, use_normal, tolerance, cos_min, valid, warped
):
    """Where `valid` and the 4x4 taps around the sample point are inside the frame and consistent, warped (H, W, C)
    float32 <- the Catmull-Rom sample of buffer over them (float64), clamped per channel to the 2x2 bilinear
    taps' range (module docstring); rows in parallel. A kernel of its own: inside `_reproject_kernel` (as inlined
    helpers, or written out) numba 0.68.1 miscompiled it, for planar views (tests: `..._in_a_fresh_cache`)."""
    height, width, channels = buffer.shape
    one = np.float32(1.0)
    for yy in prange(height):
        y = np.int64(yy)
        weights_y = np.empty(4, np.float64)
        for x in range(width):
            if not valid[y, x]:
                continue
            ys = y + np.float64(motion[y, x, 1])
            xs = x + np.float64(motion[y, x, 0])
            y0, x0 = np.floor(ys), np.floor(xs)
            iy, ix = np.int64(y0), np.int64(x0)
            if iy < 1 or iy + 2 >= height or ix < 1 or ix + 2 >= width:
                continue
            z = depth[y, x] if use_depth else np.float32(0.0)
            n0, n1, n2 = (normal[y, x, 0], normal[y, x, 1], normal[y, x, 2]) if use_normal else (one, one, one)
            hit = n0 * n0 + n1 * n1 + n2 * n2 > np.float32(NORMAL_HIT)
            consistent = True
            for tap in range(16):
                if not _tap_consistent(iy - 1 + tap // 4, ix - 1 + tap % 4, z, n0, n1, n2, hit, prev_depth,
                                       prev_normal, use_depth, use_normal, tolerance, cos_min):
                    consistent = False
                    break
            if not consistent:
                continue
            weights_y[0], weights_y[1], weights_y[2], weights_y[3] = spline_weights(ys - y0)  # rows iy - 1 .. iy + 2
            wx0, wx1, wx2, wx3 = spline_weights(xs - x0)  # columns ix - 1 .. ix + 2
            for c in range(channels):
                rows = np.float64(0.0)
                for r in range(4):
                    ty = iy - 1 + r
                    line = (wx0 * np.float64(buffer[ty, ix - 1, c]) + wx1 * np.float64(buffer[ty, ix, c])
                            + wx2 * np.float64(buffer[ty, ix + 1, c]) + wx3 * np.float64(buffer[ty, ix + 2, c]))
                    rows += weights_y[r] * line
                b00, b01 = buffer[iy, ix, c], buffer[iy, ix + 1, c]
                b10, b11 = buffer[iy + 1, ix, c], buffer[iy + 1, ix + 1, c]
                lo, hi = min(b00, b01, b10, b11), max(b00, b01, b10, b11)  # the bilinear taps' range
                warped[y, x, c] = np.float32(min(max(rows, np.float64(lo)), np.float64(hi)))


def reproject(
    buffer: np.ndarray,
    motion: np.ndarray,
    *,
    depth: np.ndarray | None = None,
    prev_depth: np.ndarray | None = None,
    normal: np.ndarray | None = None,
    prev_normal: np.ndarray | None = None,
    params: ReprojectionParams | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Warp `buffer` of the previous frame onto the current frame.

    buffer: (H, W, C) float32, any per-pixel quantity of the PREVIOUS frame (radiance, moments,
        history lengths, hidden features).
    motion: (H, W, 2) float32 backward motion of the CURRENT frame in pixels (frame-format convention).
    depth, prev_depth: (H, W, 1) float32 camera distance of the current and previous frame, scene
        units; both or neither. A tap is inconsistent when |z - z_prev| > depth_tolerance * z.
    normal, prev_normal: (H, W, 3) float32 unit world-space normals (zero: nothing hit) of the current
        and previous frame; both or neither. A tap is inconsistent when dot(n, n_prev) < normal_cos_min
        or exactly one of the two is a hit.
    Returns (warped, valid): warped (H, W, C) float32, the bilinear sample renormalised over consistent
    taps (or with `params.catmull_rom` the clamped spline, module docstring), zero where invalid, laid out in
    memory as `buffer` is (a channel-planar buffer, an (H, W, C) view of (C, H, W) planes, gives a
    channel-planar result); valid (H, W) bool, see the module docstring (eroded if `params.erode`).
    """
    params = _checked(depth, prev_depth, normal, prev_normal, params)
    height, width = buffer.shape[:2]
    no_depth, no_normal = np.zeros((1, 1), np.float32), np.zeros((1, 1, 3), np.float32)
    buffer = np.asarray(buffer, np.float32)
    warped = np.empty_like(buffer)  # same memory order as the buffer
    guides = (
        np.ascontiguousarray(motion, np.float32),
        no_depth if depth is None else np.ascontiguousarray(depth.reshape(height, width), np.float32),
        no_depth if prev_depth is None else np.ascontiguousarray(prev_depth.reshape(height, width), np.float32),
        no_normal if normal is None else np.ascontiguousarray(normal, np.float32),
        no_normal if prev_normal is None else np.ascontiguousarray(prev_normal, np.float32),
        depth is not None,
        normal is not None,
        np.float32(params.depth_tolerance),
        np.float32(params.normal_cos_min),
    )
    valid = _reproject_kernel(buffer, *guides, np.float32(params.min_weight), warped)
    if params.catmull_rom:
        _spline_kernel(buffer, *guides, valid, warped)
    if params.erode:
        valid = erode(valid)
        warped[~valid] = 0.0
    return warped, valid


def reproject_numpy(
    buffer: np.ndarray,
    motion: np.ndarray,
    *,
    depth: np.ndarray | None = None,
    prev_depth: np.ndarray | None = None,
    normal: np.ndarray | None = None,
    prev_normal: np.ndarray | None = None,
    params: ReprojectionParams | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Reference implementation of `reproject` in numpy (same arguments and results)."""
    params = _checked(depth, prev_depth, normal, prev_normal, params)
    height, width, channels = buffer.shape
    ys, xs, on_screen = sample_positions(motion)
    y0, x0 = np.floor(ys), np.floor(xs)
    fy, fx = (ys - y0).astype(np.float32), (xs - x0).astype(np.float32)
    y0, x0 = y0.astype(np.int64), x0.astype(np.int64)
    flat = buffer.reshape(-1, channels)
    warped = np.zeros((height, width, channels), np.float32)
    total = np.zeros((height, width), np.float32)
    one = np.float32(1.0)
    for ty, tx, weight in (
        (y0, x0, (one - fy) * (one - fx)),
        (y0, x0 + 1, (one - fy) * fx),
        (y0 + 1, x0, fy * (one - fx)),
        (y0 + 1, x0 + 1, fy * fx),
    ):
        inside = (ty >= 0) & (ty < height) & (tx >= 0) & (tx < width)
        index = np.clip(ty, 0, height - 1) * width + np.clip(tx, 0, width - 1)
        use = inside & (weight > 0) & _consistent(index, depth, prev_depth, normal, prev_normal, params)
        weight = np.where(use, weight, np.float32(0.0))
        warped += weight[..., None] * np.where(use[..., None], flat[index], np.float32(0.0))
        total += weight
    valid = on_screen & (total >= np.float32(params.min_weight))
    warped = np.where(valid[..., None], warped / np.where(valid, total, one)[..., None], np.float32(0.0))
    if params.catmull_rom:
        warped = _spline_numpy(buffer, warped, valid, ys - y0, xs - x0, y0, x0,
                               lambda index: _consistent(index, depth, prev_depth, normal, prev_normal, params))
    if params.erode:
        valid = erode(valid)
        warped[~valid] = 0.0
    return warped.astype(np.float32, copy=False), valid


def _spline_numpy(buffer: np.ndarray, warped: np.ndarray, valid: np.ndarray, fy: np.ndarray, fx: np.ndarray,
                  y0: np.ndarray, x0: np.ndarray, consistent) -> np.ndarray:
    """`reproject_numpy`'s clamped Catmull-Rom samples (module docstring) over the bilinear `warped` (H, W, C)
    float32. fy, fx: (H, W) float64 fractional sample positions past the taps (y0, x0), (H, W) int64;
    consistent(index) -> (H, W) bool for flat previous-frame indices. Returns (H, W, C) float32."""
    height, width, channels = buffer.shape
    flat = buffer.reshape(-1, channels).astype(np.float64)
    use = valid & (y0 >= 1) & (y0 + 2 < height) & (x0 >= 1) & (x0 + 2 < width)
    weights_y, weights_x = spline_weights(fy), spline_weights(fx)
    total = np.zeros((height, width, channels), np.float64)
    lo = np.full((height, width, channels), np.inf)
    hi = np.full((height, width, channels), -np.inf)
    for i in range(4):
        for j in range(4):
            index = np.clip(y0 - 1 + i, 0, height - 1) * width + np.clip(x0 - 1 + j, 0, width - 1)
            use &= consistent(index)
            tap = flat[index]
            total += (weights_y[i] * weights_x[j])[..., None] * tap
            if i in (1, 2) and j in (1, 2):
                lo, hi = np.minimum(lo, tap), np.maximum(hi, tap)
    spline = np.clip(total, lo, hi).astype(np.float32)
    return np.where(use[..., None], spline, warped)
