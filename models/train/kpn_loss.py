"""The training loss of the kernel-predicting network with dual motion vectors (Zeng et al. 2023, eqs. 5-6).

    L     = L_spat + L_temp + L_occ                                   eq. 6, equal weights
    L_spat = mean |I_i - R_i|                                         over the window's frames
    L_temp = mean |(I_i - I_{i-1}) - (R_i - R_{i-1})|                 over frames 1..T-1
    L_occ  = mean |I_i (.) W_i - R_i (.) W_i|,  W_i = sum_k w_k M^k_i  eq. 5, w = 1, 0.8, 0.6

M^k_i is 1 where |motionDual - motion| > DUAL_OCCLUSION_PX (service.stages.reprojection, 0.5 px) at frame
i - k (the pixels that were occluded in the frame before it); as the paper says, a frame without i - k in
the window takes M^0_i in its place. The paper adds L_occ after half of the training (sec. 5), the
`occlusion` argument here (models/train/kpn.py switches it on at TrainOptions.occlusion_from of the steps).

Domain: as the recurrent autoencoder's loss (models/train/rae_loss.py `tone`): prediction and reference are
linear demodulated radiance raised to the power 0.2 (with its epsilon) before the L1; the paper takes L1
on radiance and does not say in which range; the power keeps bright pixels from ruling the mean.
"""

from __future__ import annotations

import torch

from models.train.rae_loss import TONE_EPS, LossTerms, prediction_to_linear, tone
from service.stages.reprojection import DUAL_OCCLUSION_PX

MASK_WEIGHTS = (1.0, 0.8, 0.6)  # w_i^0, w_i^1, w_i^2 (Zeng 2023 sec. 4.4)


def occlusion_weights(motion: torch.Tensor, motion_dual: torch.Tensor) -> torch.Tensor:
    """motion, motion_dual: (N, T, 2, H, W) backward motion, pixels. Returns (N, T, 1, H, W) float32
    sum_k w_k M^k_t (module docstring), in [0, 2.4]."""
    masks = ((motion_dual - motion).square().sum(dim=2, keepdim=True) > DUAL_OCCLUSION_PX**2).to(motion.dtype)
    t = masks.shape[1]
    out = torch.zeros_like(masks)
    for k, weight in enumerate(MASK_WEIGHTS):
        earlier = torch.cat([masks[:, :k], masks[:, : t - k]], dim=1) if k else masks  # M^0 where i - k < 0
        out = out + weight * earlier
    return out


def kpn_loss(pred: torch.Tensor, target: torch.Tensor, weights: torch.Tensor, *, occlusion: bool,
             eps: float = TONE_EPS) -> LossTerms:
    """pred: (N, T, 3, H, W) filtered log1p demodulated radiance; target: (N, T, 3, H, W) linear demodulated
    reference; weights: (N, T, 1, H, W) `occlusion_weights`; occlusion: add L_occ to the total. Returns
    the loss of the module docstring (`gradient` 0: no HFEN term here); eps: `rae_loss.tone`'s."""
    p = tone(prediction_to_linear(pred), eps)
    q = tone(target, eps)
    spatial = (p - q).abs().mean()
    temporal = torch.zeros_like(spatial)
    if p.shape[1] > 1:
        temporal = ((p[:, 1:] - p[:, :-1]) - (q[:, 1:] - q[:, :-1])).abs().mean()
    occ = ((p - q) * weights).abs().mean()
    total = spatial + temporal + (occ if occlusion else 0.0)
    return LossTerms(total, spatial, torch.zeros_like(spatial), temporal, occ)
