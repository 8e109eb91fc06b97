"""How the training loop drives the kernel-predicting network with dual motion vectors (Zeng et al. 2023):
a window frame by frame, each frame's filtered output warped to the next frame and fed back (the recurrent
feedback of sec. 4.2, back-propagated through), the multi-scale kernel filter (models/train/kernel_filter.py)
on the network's kernels, and the loss of eqs. 5-6 (models/train/kpn_loss.py).

Per frame, in log1p demodulated radiance (the twin of service/pipelines/kpn.py):
  previous = the last output warped by `motionDual` (`motion` with motion="plain"), bilinear
             (models/nets/warp.py, the twin of service.stages.reprojection.reproject without G-buffer tests);
             where the warp fails (off screen), the current noisy radiance; at the first frame, the noisy
             radiance (Zeng 2023 sec. 5)
  kernels  = network(noisy planes, guides, previous), all edge-padded to the network's alignment
  output   = kernel_filter(noisy, previous, kernels), cropped back
Windows play forward only (only backward motion is stored).
"""

from __future__ import annotations

from typing import Any

import torch
import torch.nn.functional as F

from models.nets.kpn import KernelPredictor, KpnConfig, load_network, make_kpn
from models.nets.rae import SPACE_TO_DEPTH
from models.nets.warp import warp_valid
from models.train.dataset import Sequence, Window
from models.train.kernel_filter import kernel_filter
from models.train.kpn_loss import kpn_loss, occlusion_weights
from models.train.rae import RaeRecipe
from models.train.rae_loss import TONE_EPS, LossTerms, prediction_to_linear
from service.layout import KPN_INPUTS, channel_slices

WINDOW_FRAMES = 7  # frames per training window (the recurrent autoencoder's; the paper trains on 9 of 10)
CROP = 64  # training crop side, pixels: a multiple of the alignment (16)
MOTIONS = ("dual", "plain")  # which motion warps the previous output: `motionDual` (where given) or `motion`
PLANES = channel_slices(KPN_INPUTS)


def warped_previous(previous: torch.Tensor, motion: torch.Tensor, noisy: torch.Tensor) -> torch.Tensor:
    """previous: (N, 3, H, W) last output, log1p demodulated; motion: (N, 2, H, W) backward motion, pixels;
    noisy: (N, 3, H, W) this frame's log1p demodulated radiance. Returns (N, 3, H, W): previous warped to
    this frame, the noisy radiance where the warp fails."""
    warped, valid = warp_valid(previous, motion)
    return torch.where(valid, warped, noisy)


def filter_window(net: KernelPredictor, noisy: torch.Tensor, guides: torch.Tensor,
                  motion: torch.Tensor) -> torch.Tensor:
    """noisy (N, T, 3, H, W) linear demodulated radiance; guides (N, T, 5, H, W) (dataset order); motion
    (N, T, 2, H, W) the motion that warps the previous output, pixels. Returns (N, T, 3, H, W) filtered
    log1p demodulated radiance (module docstring)."""
    h, w = noisy.shape[-2:]
    a = net.alignment
    pad = (0, (-w) % a, 0, (-h) % a)
    outputs: list[torch.Tensor] = []
    for i in range(noisy.shape[1]):
        planes = RaeRecipe.inputs(noisy[:, i], guides[:, i])
        radiance = planes[:, PLANES["radiance"]]
        previous = radiance if i == 0 else warped_previous(outputs[-1], motion[:, i], radiance)
        features = F.pad(torch.cat([planes, previous], dim=1), pad, mode="replicate")
        kernels = net(features)
        out = kernel_filter(features[:, PLANES["radiance"]], features[:, PLANES["previous"]], *kernels,
                            space_to_depth=SPACE_TO_DEPTH)
        outputs.append(out[..., :h, :w])
    return torch.stack(outputs, dim=1)


class KpnRecipe:
    """The `kpn` entry of models.train's network table."""

    name = "kpn"
    frames = WINDOW_FRAMES
    crop = CROP
    reverse = False  # the previous output is warped by backward motion

    def __init__(self, warp: bool = False, motion: str = "dual", occlusion_step: int = 0, tone_eps: float = TONE_EPS):
        """motion: one of MOTIONS; occlusion_step: the optimiser step from which the loss has its
        motion-occlusion term (Zeng 2023 sec. 5: half of the training); tone_eps: the loss's (rae_loss.tone)."""
        if warp:
            raise ValueError("kpn always warps its previous output (--warp is rae's)")
        if motion not in MOTIONS:
            raise ValueError(f"motion must be one of {', '.join(MOTIONS)}, got '{motion}'")
        self.motion = motion
        self.occlusion_step = occlusion_step
        self.tone_eps = tone_eps

    def build(self, seed: int) -> KernelPredictor:
        return make_kpn(KpnConfig(), seed=seed)

    def load(self, state: dict[str, Any]) -> KernelPredictor:
        return load_network(state)

    def warp_motion(self, motion: torch.Tensor, motion_dual: torch.Tensor) -> torch.Tensor:
        """The motion the previous output is warped by: motion_dual, or motion with motion="plain"."""
        return motion_dual if self.motion == "dual" else motion

    def loss(self, net: KernelPredictor, batch: Window, step: int = 0) -> LossTerms:
        pred = filter_window(net, batch.noisy, batch.guides, self.warp_motion(batch.motion, batch.motion_dual))
        weights = occlusion_weights(batch.motion, batch.motion_dual)
        return kpn_loss(pred, batch.target, weights, occlusion=step >= self.occlusion_step, eps=self.tone_eps)

    @torch.no_grad()
    def denoise(self, net: KernelPredictor, seq: Sequence) -> torch.Tensor:
        """The whole sequence denoised from its full `color`: (F, 3, H, W) float32 CPU tensor of linear radiance
        with the albedo and emission put back (before the serving pipeline's guards)."""
        device = next(net.parameters()).device
        motion = self.warp_motion(torch.from_numpy(seq.motion), torch.from_numpy(seq.motion_dual)).to(device)
        pred = filter_window(net, torch.from_numpy(seq.noisy[0]).to(device)[None],
                             torch.from_numpy(seq.guides).to(device)[None], motion[None])[0]
        return prediction_to_linear(pred).cpu() * torch.from_numpy(seq.albedo) + torch.from_numpy(seq.emission)
