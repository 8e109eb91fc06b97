"""The self-supervised loss of the cross-regression denoiser (Choi et al. 2024, eqs. 11-13).

    L = mean_c 1/2 (L_s + L_t)                                        (eq. 11)
    L_s = 1/2 (rel(fA, pilotB) + rel(fB, pilotA))                      (eq. 12, labels crossed)
    L_t = 1/2 (rel(fA, R pilotB_prev) + rel(fB, R pilotA_prev))        (eq. 13, reprojected previous pilots)
    rel(x, y) = (x - y)^2 / (y^2 + eps),  eps = 1e-2

per channel, averaged over channels and pixels, all in log1p radiance (as the authors' code computes it).
The temporal labels are crossed, as in the paper's eq. 13 and the authors' code (main.py: prev_label1 =
prev_ols2): independent of the current frame's noise in A.
"""

from __future__ import annotations

import torch

LOSS_EPS = 1e-2  # Choi 2024 eqs. 12-13 epsilon; authors' code: square(label) + 1e-2


def relative_l2(x: torch.Tensor, label: torch.Tensor, eps: float = LOSS_EPS) -> torch.Tensor:
    """Per-element (x - label)^2 / (label^2 + eps); label carries no gradient. Same shape as x."""
    label = label.detach()
    return (x - label) ** 2 / (label * label + eps)


def crossreg_loss(
    color_a: torch.Tensor,
    color_b: torch.Tensor,
    pilot_a: torch.Tensor,
    pilot_b: torch.Tensor,
    previous_pilot_a: torch.Tensor,
    previous_pilot_b: torch.Tensor,
) -> torch.Tensor:
    """Scalar loss of eq. 11. All tensors (N, 3, H, W) in log1p radiance: color_a/color_b are the eq. 8
    outputs from pilots A/B; previous_pilot_* the reprojected previous pilots (current ones where the
    reprojection failed)."""
    spatial = 0.5 * (relative_l2(color_a, pilot_b) + relative_l2(color_b, pilot_a))
    temporal = 0.5 * (relative_l2(color_a, previous_pilot_b) + relative_l2(color_b, previous_pilot_a))
    return (0.5 * spatial + 0.5 * temporal).mean()
