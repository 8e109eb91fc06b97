"""The spatiotemporal filter of Choi et al. 2024 (eqs. 8-10) in torch, differentiable in the parameters.

The same filter as service/stages/spatiotemporal_filter.py (numba, inference), written with whole-tensor
shifts over the 11x11 window; tests/models/train/test_filter_parity.py holds the two together. Layout
is (N, C, H, W); neighbours outside the frame are left out, exactly as the inference side does.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

from service.stages.spatiotemporal_filter import (
    FILTER_RADIUS,
    N_PRECISIONS,
    PRECISION_EPS,
    SPREAD_RADIUS,
    check_pilot_bandwidth,
)


@dataclass
class FilterResult:
    """Log1p-space outputs: color (N, 3, H, W) eq. 10; color_a, color_b (N, 3, H, W) eq. 8;
    weight_a, weight_b (N, 1, H, W) >= 1, the weight sums."""

    color: torch.Tensor
    color_a: torch.Tensor
    color_b: torch.Tensor
    weight_a: torch.Tensor
    weight_b: torch.Tensor


def _sq_dist(padded: torch.Tensor, centre: torch.Tensor, dy: int, dx: int, r: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(squared distance summed over channels (N, 1, H, W), the shifted neighbours (N, C, H, W))."""
    height, width = centre.shape[-2:]
    nb = padded[..., r + dy : r + dy + height, r + dx : r + dx + width]
    return ((nb - centre) ** 2).sum(dim=1, keepdim=True), nb


def cross_bilateral_sums(
    pilot_a: torch.Tensor,
    pilot_b: torch.Tensor,
    albedo: torch.Tensor,
    normal: torch.Tensor,
    precisions: torch.Tensor,
    radius: int = FILTER_RADIUS,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Eq. 8-9 weighted sums over the window (the numpy side forms them inside its kernel, see
    service.stages.spatiotemporal_filter._filter_reference).

    pilot_a, pilot_b: (N, 3, H, W) log1p radiance; albedo, normal: (N, 3, H, W);
    precisions: (N, 5, H, W) > 0 (kA, kB, kAlbedo, kNormal, kPosition).
    Returns (sum_a (N, 3, H, W), weight_a (N, 1, H, W), sum_b, weight_b).
    """
    r = radius
    height, width = pilot_a.shape[-2:]
    pad = (r, r, r, r)
    padded = [F.pad(t, pad) for t in (pilot_a, pilot_b, albedo, normal)]
    inside = F.pad(torch.ones_like(pilot_a[:, :1]), pad)
    ka, kb, kalb, kn, kp = precisions.split(1, dim=1)
    sum_a = torch.zeros_like(pilot_a)
    sum_b = torch.zeros_like(pilot_b)
    w_a = torch.zeros_like(ka)
    w_b = torch.zeros_like(kb)
    inv_r2 = 1.0 / float(max(r, 1) ** 2)
    for dy in range(-r, r + 1):
        for dx in range(-r, r + 1):
            with torch.no_grad():
                mask = inside[..., r + dy : r + dy + height, r + dx : r + dx + width]
                d_alb, _ = _sq_dist(padded[2], albedo, dy, dx, r)
                d_n, _ = _sq_dist(padded[3], normal, dy, dx, r)
                d_a, nb_a = _sq_dist(padded[0], pilot_a, dy, dx, r)
                d_b, nb_b = _sq_dist(padded[1], pilot_b, dy, dx, r)
            shared = kalb * d_alb + kn * d_n + kp * ((dx * dx + dy * dy) * inv_r2)
            wgt_a = torch.exp(-(ka * d_a + shared)) * mask
            wgt_b = torch.exp(-(kb * d_b + shared)) * mask
            sum_a = sum_a + wgt_a * nb_a
            sum_b = sum_b + wgt_b * nb_b
            w_a = w_a + wgt_a
            w_b = w_b + wgt_b
    return sum_a, w_a, sum_b, w_b


def pilot_precision_floor(pilot_a: torch.Tensor, pilot_b: torch.Tensor, bandwidth: float) -> torch.Tensor:
    """`service.stages.spatiotemporal_filter.pilot_precision_floor` in torch, without gradient: (N, 1, H, W)
    from (N, 3, H, W) pilots; the 5x5 mean over the in-frame pixels, as `box_mean`."""
    with torch.no_grad():
        disagreement = ((pilot_a - pilot_b) ** 2).mean(dim=1, keepdim=True)
        size = 2 * SPREAD_RADIUS + 1
        spread = 0.5 * F.avg_pool2d(disagreement, size, stride=1, padding=SPREAD_RADIUS, count_include_pad=False)
        return 1.0 / (bandwidth * spread + PRECISION_EPS)


def spatiotemporal_filter(
    pilot_a: torch.Tensor,
    pilot_b: torch.Tensor,
    albedo: torch.Tensor,
    normal: torch.Tensor,
    params: torch.Tensor,
    previous: torch.Tensor | None = None,
    valid: torch.Tensor | None = None,
    radius: int = FILTER_RADIUS,
    min_alpha: float = 0.0,
    pilot_bandwidth: float = 0.0,
) -> FilterResult:
    """Eqs. 8-10 in torch; see service.stages.spatiotemporal_filter.spatiotemporal_filter.

    params: (N, 6, H, W), network output (5 precisions, alpha). previous: (N, 3, H, W) log1p or None;
    valid: (N, 1, H, W) bool/float, 1 where `previous` is usable, or None (nowhere). min_alpha: the floor
    of alpha (no gradient below it), as the numpy filter applies it; pilot_bandwidth: the floor of the
    pilot-colour precisions (`pilot_precision_floor`; no gradient where it holds), 0 for none.
    """
    check_pilot_bandwidth(pilot_bandwidth)
    precisions = params[:, :N_PRECISIONS]
    if pilot_bandwidth > 0:
        floor = pilot_precision_floor(pilot_a, pilot_b, pilot_bandwidth)
        precisions = torch.cat([torch.maximum(precisions[:, :2], floor), precisions[:, 2:]], dim=1)
    sum_a, w_a, sum_b, w_b = cross_bilateral_sums(pilot_a, pilot_b, albedo, normal, precisions, radius)
    spatial_a = sum_a / w_a
    spatial_b = sum_b / w_b
    if previous is None or valid is None:
        color_a, color_b = spatial_a, spatial_b
    else:
        valid = valid.to(params.dtype)
        alpha = valid * params[:, N_PRECISIONS:].clamp_min(min_alpha) + (1.0 - valid)
        history = (1.0 - alpha) * previous
        color_a = alpha * spatial_a + history
        color_b = alpha * spatial_b + history
    color = (color_a * w_a + color_b * w_b) / (w_a + w_b)
    return FilterResult(color, color_a, color_b, w_a, w_b)
