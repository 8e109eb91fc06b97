"""How the training loop drives the recurrent autoencoder (models/nets/rae.py): a window through the
network frame by frame with its hidden state (back-propagation through time, Chaitanya 2017 sec. 5.3),
the loss (models/train/rae_loss.py), and whole held-out sequences denoised for validation scores.

With `warp`, each level's hidden state is moved by the frame's motion before the next frame
(models/nets/warp.py, the twin of what the `rae` pipeline's `warp` option does in numpy), and windows
play forward only (only backward motion is stored).
"""

from __future__ import annotations

from typing import Any

import torch
import torch.nn.functional as F

from models.nets.rae import RaeConfig, RecurrentAutoencoder, load_network, make_rae
from models.nets.warp import warp_level
from models.train.dataset import Sequence, Window
from models.train.rae_loss import TONE_EPS, WEIGHTS, LossTerms, loss_weights, prediction_to_linear, rae_loss

WINDOW_FRAMES = 7  # Chaitanya 2017 sec. 4.3: sequences of 7 consecutive frames
CROP = 96  # training crop side, pixels: a multiple of the alignment (32) that fits the 128x128 renders


class RaeRecipe:
    """The `rae` entry of models.train's network table."""

    name = "rae"
    frames = WINDOW_FRAMES
    crop = CROP

    def __init__(self, warp: bool = False, tone_eps: float = TONE_EPS, temporal_weight: float = WEIGHTS[2]):
        self.warp = warp
        self.reverse = not warp  # backward playback has no motion to warp by
        self.tone_eps = tone_eps  # the loss's (rae_loss.tone)
        self.weights = loss_weights(temporal_weight)  # the loss's (ws, wg, wt)

    def build(self, seed: int) -> RecurrentAutoencoder:
        """A freshly initialised network of the default configuration, reproducible in `seed`."""
        return make_rae(RaeConfig(), seed=seed)

    def load(self, state: dict[str, Any]) -> RecurrentAutoencoder:
        """The network of a checkpoint's {'config', 'state_dict'} (models.nets.rae.load_network), weights loaded."""
        return load_network(state)

    @staticmethod
    def inputs(noisy: torch.Tensor, guides: torch.Tensor) -> torch.Tensor:
        """(..., 3, H, W) linear demodulated radiance and (..., 5, H, W) guides -> (..., 8, H, W) network
        input in service.layout.RAE_INPUTS order (the twin of service.stages.rae_inputs.rae_planes)."""
        return torch.cat([torch.log1p(noisy.clamp_min(0)), guides], dim=-3)

    def run(self, net: RecurrentAutoencoder, features: torch.Tensor, motion: torch.Tensor) -> torch.Tensor:
        """features (N, T, 8, H, W), H and W multiples of net.alignment; motion (N, T, 2, H, W) backward,
        pixels (read with `warp` only) -> predictions (N, T, 3, H, W)."""
        n, t, _, h, w = features.shape
        hidden = net.zero_hidden(n, h, w, device=features.device)
        outputs = []
        for i in range(t):
            if self.warp and i > 0:
                hidden = [warp_level(state, motion[:, i], scale)
                          for state, scale in zip(hidden, net.config.scales, strict=True)]
            out, *hidden = net(features[:, i], *hidden)
            outputs.append(out)
        return torch.stack(outputs, dim=1)

    def loss(self, net: RecurrentAutoencoder, batch: Window, step: int = 0) -> LossTerms:
        """The loss of one batch (the same at every optimiser `step`)."""
        return rae_loss(self.run(net, self.inputs(batch.noisy, batch.guides), batch.motion), batch.target,
                        self.tone_eps, self.weights)

    @torch.no_grad()
    def denoise(self, net: RecurrentAutoencoder, seq: Sequence) -> torch.Tensor:
        """The whole sequence denoised from its full `color` on the network's device: (F, 3, H, W) float32 CPU
        tensor of linear radiance with the emission added back, as the serving pipeline returns it (before its
        guards)."""
        device = next(net.parameters()).device
        noisy = torch.from_numpy(seq.noisy[0]).to(device)
        features = self.inputs(noisy, torch.from_numpy(seq.guides).to(device))
        h, w = features.shape[-2:]
        a = net.alignment
        pad = (0, (-w) % a, 0, (-h) % a)
        motion = F.pad(torch.from_numpy(seq.motion).to(device), pad, mode="replicate")
        pred = self.run(net, F.pad(features, pad, mode="replicate")[None], motion[None])[0, :, :, :h, :w]
        return prediction_to_linear(pred).cpu() * torch.from_numpy(seq.albedo) + torch.from_numpy(seq.emission)
