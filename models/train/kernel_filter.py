"""The multi-scale kernel filter with temporal blend of Zeng et al. 2023 (sec. 4.3, eq. 4) in torch,
differentiable in the kernels, the weights and both images.

The same filter as service/stages/kernel_filter.py (numba, inference; the equations, the kernel layout and
the normalisation of the network's logits are in its docstring), written with whole-tensor shifts over the
5x5 window of an edge-replicated image; tests/models/train/test_kernel_filter_parity.py holds the two
together. Layout (N, C, H, W).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from service.stages.kernel_filter import COARSE, FINE, KERNEL_SIZE, RADIUS


def apply_kernel(image: torch.Tensor, logits: torch.Tensor) -> torch.Tensor:
    """image (N, C, H, W); logits (N, 25, H, W) tap logits -> (N, C, H, W): per pixel, the softmax of its logits
    weighing its edge-replicated 5x5 neighbourhood."""
    kernel = torch.softmax(logits, dim=1)
    h, w = image.shape[-2:]
    padded = F.pad(image, (RADIUS,) * 4, mode="replicate")
    out = torch.zeros_like(image)
    for tap in range(KERNEL_SIZE * KERNEL_SIZE):
        dy, dx = divmod(tap, KERNEL_SIZE)
        out = out + kernel[:, tap : tap + 1] * padded[..., dy : dy + h, dx : dx + w]
    return out


def downsample(image: torch.Tensor) -> torch.Tensor:
    """(N, C, H, W), H and W even -> (N, C, H/2, W/2) 2x2 block means (D of eq. 4)."""
    return F.avg_pool2d(image, 2)


def upsample(image: torch.Tensor) -> torch.Tensor:
    """(N, C, h, w) -> (N, C, 2h, 2w) bilinear, half-pixel centres, edges replicated (U of eq. 4)."""
    return F.interpolate(image, scale_factor=2.0, mode="bilinear", align_corners=False)


def combine_scales(fine: torch.Tensor, coarse: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
    """Zeng 2023 eq. 4: fine (N, C, H, W), coarse (N, C, H/2, W/2), alpha (N, 1, H/2, W/2) ->
    fine + U[alpha (coarse - D fine)]."""
    return fine + upsample(alpha * (coarse - downsample(fine)))


def kernel_filter(noisy: torch.Tensor, previous: torch.Tensor, fine: torch.Tensor, half: torch.Tensor,
                  quarter: torch.Tensor, space_to_depth: int = 1) -> torch.Tensor:
    """noisy, previous (N, 3, H, W) log1p demodulated radiance, H and W multiples of 4 and of s =
    `space_to_depth`; fine (N, 51 s^2, H / s, W / s) (pixel-shuffle order), half (N, 26, H/2, W/2), quarter
    (N, 26, H/4, W/4): the network's raw predictions (models/nets/kpn.py). Returns (N, 3, H, W) filtered log1p
    demodulated radiance."""
    fine = F.pixel_shuffle(fine, space_to_depth)
    half_noisy = downsample(noisy)
    coarse = apply_kernel(downsample(half_noisy), quarter[:, COARSE["kernel"]])
    coarse = combine_scales(apply_kernel(half_noisy, half[:, COARSE["kernel"]]), coarse,
                            torch.sigmoid(quarter[:, COARSE["alpha"]]))
    spatial = combine_scales(apply_kernel(noisy, fine[:, FINE["kernel"]]), coarse,
                             torch.sigmoid(half[:, COARSE["alpha"]]))
    temporal = apply_kernel(previous, fine[:, FINE["temporal"]])
    alpha = torch.sigmoid(fine[:, FINE["alpha"]])
    return alpha * spatial + (1.0 - alpha) * temporal
