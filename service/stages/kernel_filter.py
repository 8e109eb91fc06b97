"""Multi-scale per-pixel kernel filtering with a temporal blend (Zeng et al. 2023, sec. 4.3, eq. 4, Fig. 6),
the inference side of the `kpn` pipeline; the network that predicts the kernels runs before it.

    i_s  = K_s * (D^s noisy)                          5x5 per-pixel kernel at scales 1, 1/2, 1/4
    o_4  = i_4
    o_s  = i_s + U[alpha_2s (o_2s - D i_s)]           eq. 4: i^f - U[a^c D i^f] + U[a^c i^c], s = 2, 1
    out  = alpha_t o_1 + (1 - alpha_t) K_t * previous eq. 1 with the temporal kernel of Fig. 6

The network predicts logits: each kernel is the softmax of its 25 tap logits, each weight (alpha) the
sigmoid of its logit, computed here (in ONNX Runtime a softmax over the channel axis of a full-resolution
tensor cost four times the whole network). The finest predictions come in the network's space-to-depth
layout (see `apply_kernel`), read where they lie instead of rearranged first.

D is 2x2 average pooling (the paper: max pooling; the mean keeps a constant a constant and an average of
noise unbiased), U bilinear 2x upsampling with half-pixel centres, edges replicated (torch's
`interpolate(..., mode="bilinear", align_corners=False)`). Kernel taps outside the frame read the edge
pixel (edge replication). The kernels sum to 1 per pixel and the weights lie in (0, 1), so a constant image
stays that constant. Everything here is in the network's log1p demodulated radiance.

Layout: planes (C, H, W) float32; a kernel's logits are 25 planes, tap t = (dy + 2) * 5 + (dx + 2) weighing
the pixel at row + dy, column + dx. The torch twin that training runs through is models/train/kernel_filter.py;
tests/models/train/test_kernel_filter_parity.py holds the two together.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from service.layout import KPN_COARSE_OUTPUTS, KPN_FINE_OUTPUTS, KPN_TAPS, channel_slices, total_channels

KERNEL_SIZE = 5  # Zeng 2023 sec. 4.3: 5x5 per-pixel kernels
RADIUS = KERNEL_SIZE // 2
SCALES = 3  # full, 1/2 and 1/4 of the frame (Zeng 2023 sec. 4.3)
ALIGNMENT = 2 ** (SCALES - 1)  # height and width must be multiples of this (two 2x poolings)
SIGMOID_CLIP = 80.0  # logits are clipped to +-80 before the sigmoid: exp(80) ~ 5.5e34 is finite in float32
FINE = channel_slices(KPN_FINE_OUTPUTS)  # "kernel", "temporal", "alpha" planes of the finest prediction
COARSE = channel_slices(KPN_COARSE_OUTPUTS)  # "kernel", "alpha" planes of a coarser scale's prediction
if KERNEL_SIZE * KERNEL_SIZE != KPN_TAPS:
    raise ImportError("service.layout.KPN_TAPS must be KERNEL_SIZE^2")


@njit(parallel=True, cache=True, error_model="numpy")
def _apply_kernel(image, logits, first, s, out):
    """out[c, y, x] = sum_t softmax_t(logits) image[c, clamp(y + dy), clamp(x + dx)], the logits of pixel
    (y, x) read from planes first..first+24 of a space-to-depth layout of factor s; rows in parallel."""
    channels, height, width = image.shape
    s2 = s * s
    for y in prange(height):
        weight = np.empty(KPN_TAPS, np.float32)
        row, sub_row = y // s, (y % s) * s
        for x in range(width):
            col, sub = x // s, sub_row + x % s
            top = logits[first * s2 + sub, row, col]
            for t in range(KPN_TAPS):
                weight[t] = logits[(first + t) * s2 + sub, row, col]
                top = max(top, weight[t])
            total = np.float32(0.0)
            for t in range(KPN_TAPS):
                weight[t] = np.exp(weight[t] - top)
                total += weight[t]
            inverse = np.float32(1.0) / total  # >= 1 / 25: the largest tap's weight is exp(0) = 1
            for c in range(channels):
                acc = np.float32(0.0)
                for dy in range(-RADIUS, RADIUS + 1):
                    yy = min(max(y + dy, 0), height - 1)
                    for dx in range(-RADIUS, RADIUS + 1):
                        xx = min(max(x + dx, 0), width - 1)
                        acc += weight[(dy + RADIUS) * KERNEL_SIZE + dx + RADIUS] * image[c, yy, xx]
                out[c, y, x] = acc * inverse


def apply_kernel(image: np.ndarray, logits: np.ndarray, *, first: int = 0, space_to_depth: int = 1) -> np.ndarray:
    """image: (C, H, W) float32; logits: (P * s^2, H / s, W / s) float32 predictions in a space-to-depth layout
    of factor s = `space_to_depth` (pixel (y, x) reads plane p * s^2 + (y % s) * s + x % s at (y // s, x // s),
    the order of torch's pixel_shuffle), of which planes first..first+24 are the kernel's tap logits (tap
    layout in the module docstring). Returns (C, H, W) float32: per pixel, the softmax of its 25 logits
    weighing its edge-replicated 5x5 neighbourhood."""
    out = np.empty(image.shape, np.float32)
    _apply_kernel(np.ascontiguousarray(image, np.float32), np.ascontiguousarray(logits, np.float32), first,
                  space_to_depth, out)
    return out


def weight(logits: np.ndarray, plane: int, space_to_depth: int = 1) -> np.ndarray:
    """(H, W) float32 in (0, 1): the sigmoid of plane `plane` of `logits` (a space-to-depth layout as in
    `apply_kernel`), at full resolution."""
    s = space_to_depth
    planes = logits[plane * s * s : (plane + 1) * s * s]
    h, w = planes.shape[1:]
    full = planes.reshape(s, s, h, w).transpose(2, 0, 3, 1).reshape(h * s, w * s)
    return np.float32(1.0) / (np.float32(1.0) + np.exp(-np.clip(full, -SIGMOID_CLIP, SIGMOID_CLIP)))


def downsample(image: np.ndarray) -> np.ndarray:
    """(C, H, W) float32, H and W even -> (C, H / 2, W / 2) float32 2x2 block means (D of eq. 4)."""
    total = image[:, 0::2, 0::2] + image[:, 0::2, 1::2]
    total += image[:, 1::2, 0::2]
    total += image[:, 1::2, 1::2]
    return total * np.float32(0.25)


def _upsample_axis(image: np.ndarray, axis: int) -> np.ndarray:
    """Linear 2x upsampling along `axis` with half-pixel centres, edges replicated."""
    n = image.shape[axis]
    before = np.take(image, np.maximum(np.arange(n) - 1, 0), axis=axis)
    after = np.take(image, np.minimum(np.arange(n) + 1, n - 1), axis=axis)
    shape = list(image.shape)
    shape[axis] = 2 * n
    out = np.empty(shape, np.float32)
    index = [slice(None)] * image.ndim
    index[axis] = slice(0, None, 2)
    out[tuple(index)] = np.float32(0.75) * image + np.float32(0.25) * before
    index[axis] = slice(1, None, 2)
    out[tuple(index)] = np.float32(0.75) * image + np.float32(0.25) * after
    return out


def upsample(image: np.ndarray) -> np.ndarray:
    """(C, h, w) float32 -> (C, 2h, 2w) float32 bilinear upsampling (U of eq. 4; torch's bilinear
    interpolation with align_corners=False)."""
    return _upsample_axis(_upsample_axis(image, 1), 2)


def combine_scales(fine: np.ndarray, coarse: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """Zeng 2023 eq. 4. fine: (C, H, W) float32 filtered at the finer scale; coarse: (C, H/2, W/2) float32
    filtered (and combined) at the coarser one; alpha: (H/2, W/2) float32 in (0, 1), the coarse scale's
    weight. Returns (C, H, W) float32 fine + U[alpha (coarse - D fine)]."""
    return fine + upsample(alpha[None] * (coarse - downsample(fine)))


def kernel_filter(noisy: np.ndarray, previous: np.ndarray, fine: np.ndarray, half: np.ndarray,
                  quarter: np.ndarray, space_to_depth: int = 1) -> np.ndarray:
    """The whole filter of the module docstring.

    noisy: (3, H, W) float32 log1p demodulated noisy radiance, H and W multiples of ALIGNMENT and of
    `space_to_depth`; previous: (3, H, W) float32 the previous output warped to this frame, same space;
    fine: (51 s^2, H / s, W / s) float32 raw predictions in layout.KPN_FINE_OUTPUTS order (spatial kernel
    logits, temporal kernel logits, alpha_t logit) in the space-to-depth layout of factor s = `space_to_depth`
    (see `apply_kernel`); half, quarter: (26, H/2, W/2) and (26, H/4, W/4) float32 raw predictions in
    KPN_COARSE_OUTPUTS order (kernel logits, alpha logit). Returns (3, H, W) float32 filtered log1p
    demodulated radiance.
    """
    s = space_to_depth
    height, width = noisy.shape[1:]
    step = np.lcm(ALIGNMENT, s)
    if height % step or width % step:
        raise ValueError(f"kernel filter: the frame ({width}x{height}) must be padded to a multiple of {step}")
    fine_c, coarse_c = total_channels(KPN_FINE_OUTPUTS), total_channels(KPN_COARSE_OUTPUTS)
    expected = {"previous": (previous, (3, height, width)), "fine": (fine, (fine_c * s * s, height // s, width // s)),
                "half": (half, (coarse_c, height // 2, width // 2)),
                "quarter": (quarter, (coarse_c, height // 4, width // 4))}
    for name, (array, shape) in expected.items():
        if array.shape != shape:
            raise ValueError(f"kernel filter: {name} has shape {array.shape}, expected {shape}")
    half_noisy = downsample(noisy)
    coarse = apply_kernel(downsample(half_noisy), quarter, first=COARSE["kernel"].start)
    coarse = combine_scales(apply_kernel(half_noisy, half, first=COARSE["kernel"].start), coarse,
                            weight(quarter, COARSE["alpha"].start))
    spatial = combine_scales(apply_kernel(noisy, fine, first=FINE["kernel"].start, space_to_depth=s), coarse,
                             weight(half, COARSE["alpha"].start))
    temporal = apply_kernel(previous, fine, first=FINE["temporal"].start, space_to_depth=s)
    alpha = weight(fine, FINE["alpha"].start, s)
    return alpha * spatial + (np.float32(1.0) - alpha) * temporal
