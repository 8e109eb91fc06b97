"""How the training loop drives fast local neural regression (Salmi et al.): the guide network
(models/nets/flnr.py) feeds FLR's torch twin (models/train/flr.py), and the loss is taken on the regression's
output, so the network learns guides that make the regression good ("trained end to end").

A training example is one frame (the paper's FLNR is a spatial denoiser; windows of 1 frame). The noisy
radiance is demodulated by the dataset (models/train/dataset.py), its fireflies clamped as the served FLR
clamps them (`outliers.clamp_outlier_planes`, no gradient needed: it is the regression's data, not the
network's output), and regressed on the network's guides. The loss is the recurrent autoencoder's
(models/train/rae_loss.py `tone_loss`: L1 and HFEN in the power-0.2 domain; its temporal term is 0 for one
frame) on the output clipped at 0. Also tried here, each worse on the held-out set after 1,000-2,000 steps
than FLR on the G-buffer (0.0207 at scale 2, sigma 1): relL2 itself as the loss (0.049), and a term
pulling one learned guide toward the clean radiance's log (0.030).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from models.nets.flnr import FlnrConfig, GuideNet, load_network, make_flnr
from models.train import flr
from models.train.dataset import Sequence, Window
from models.train.rae import RaeRecipe
from models.train.rae_loss import TONE_EPS, LossTerms, tone_loss
from service.stages.flr import FlrParams
from service.stages.outliers import clamp_outlier_planes

CROP = 64  # training crop side, pixels: a multiple of the network's alignment (32), 3.5 of FLR's 18-pixel windows
FLR = FlrParams(scale=2, sigma=1.0)  # the regression trained through (exported into the ONNX metadata)


def clamped(noisy: torch.Tensor) -> torch.Tensor:
    """(..., 3, H, W) demodulated radiance with fireflies and their clusters clamped per image, as the served
    FLR does first (no gradient)."""
    flat = noisy.detach().cpu().reshape(-1, *noisy.shape[-3:]).numpy()
    out = np.stack([clamp_outlier_planes(np.ascontiguousarray(image)) for image in flat])
    return torch.from_numpy(out).reshape(noisy.shape).to(noisy.device)


def regress(net: GuideNet, noisy: torch.Tensor, guides: torch.Tensor) -> torch.Tensor:
    """noisy (N, 3, H, W) demodulated radiance, guides (N, 5, H, W) (dataset order) -> (N, 3, H, W) FLR of the
    clamped radiance on the network's guides (the input edge-padded to the network's alignment for it)."""
    h, w = noisy.shape[-2:]
    a = net.alignment
    features = F.pad(RaeRecipe.inputs(noisy, guides), (0, (-w) % a, 0, (-h) % a), mode="replicate")
    return flr.local_linear_regression(clamped(noisy), net(features)[..., :h, :w], FLR)


class FlnrRecipe:
    """The `flnr` entry of models.train's network table."""

    name = "flnr"
    frames = 1
    crop = CROP
    reverse = False

    def __init__(self, warp: bool = False, tone_eps: float = TONE_EPS):
        if warp:
            raise ValueError("flnr has no recurrent state to warp (--warp is rae's)")
        self.tone_eps = tone_eps  # the loss's (rae_loss.tone)

    def build(self, seed: int) -> GuideNet:
        return make_flnr(FlnrConfig(), seed=seed)

    def load(self, state: dict[str, Any]) -> GuideNet:
        return load_network(state)

    def loss(self, net: GuideNet, batch: Window, step: int = 0) -> LossTerms:
        """The loss of one batch (the same at every optimiser `step`)."""
        pred = regress(net, batch.noisy[:, 0], batch.guides[:, 0])
        return tone_loss(pred.clamp_min(0.0)[:, None], batch.target, self.tone_eps)

    @torch.no_grad()
    def denoise(self, net: GuideNet, seq: Sequence) -> torch.Tensor:
        """The whole sequence, frame by frame, from its full `color`: (F, 3, H, W) float32 CPU tensor of linear
        radiance with the albedo and emission put back (before the serving pipeline's guards)."""
        device = next(net.parameters()).device
        pred = regress(net, torch.from_numpy(seq.noisy[0]).to(device), torch.from_numpy(seq.guides).to(device))
        return pred.cpu() * torch.from_numpy(seq.albedo) + torch.from_numpy(seq.emission)
