"""The multi-scale kernel-predicting network of neural temporal denoising with dual motion vectors (Zeng et
al. 2023, "Neural Temporal Denoising for Indirect Illumination", sec. 4, Figs. 4 and 6), sized for CPU
inference.

As in the paper: a U-Net takes the noisy radiance, the G-buffer and the previous output warped to this frame
(through dual motion vectors: models/train/kpn.py, service/pipelines/kpn.py) and predicts, at its last three
decoder layers, per-pixel 5x5 kernels for the noisy image at 1, 1/2 and 1/4 of the frame's resolution with a
coarse/fine blending weight at each coarser scale (eq. 4), and at the finest scale a 5x5 temporal kernel
for the warped previous output and the temporal weight alpha_t (Fig. 6: 26 = 25 + alpha, 51 = 2 x 25 +
alpha_t). The filter that applies them is service/stages/kernel_filter.py (torch twin:
models/train/kernel_filter.py); this module only predicts.

Departures from the paper and choices where it is silent:
- Space-to-depth, as models/nets/rae.py: the trunk runs at half resolution (2x2 pixels -> 4x the channels
  in); the finest predictions come out at half resolution 4x over (pixel-shuffle order), and the filter
  reads each pixel's where it lies.
  The 1/2-scale kernels are predicted by the trunk's first level, the 1/4-scale ones by its second.
- Widths `KpnConfig.widths` (24, 32, 48, 64): three poolings below the half-resolution level, two 3x3
  convolutions with leaky ReLU per level (the FLNR `Block`), max pooling in the trunk, nearest upsampling,
  concatenated skips. The paper gives no widths; ours keep the network within half of OIDN-high's time.
- Prediction heads are 1x1 convolutions that start at zero: an untrained network filters with 5x5 box
  kernels and weighs every scale and the history by 1/2.
- Kernels are normalised by a softmax over their 25 taps (so a constant image stays constant), the weights
  by a sigmoid (the paper does not say how it normalises them); both in the filter, which takes the
  network's logits (service/stages/kernel_filter.py says why).
- Inputs are the recurrent autoencoder's planes (log1p demodulated radiance, normal, relative depth,
  roughness; service.layout.RAE_INPUTS) and the warped previous output in the same log1p demodulated space
  (KPN_INPUTS): the paper's albedo goes in as demodulation. The filter works in that log1p space.
- He initialisation of the trunk (the paper: Xavier).

Tensors: features (N, 11, H, W) float32 in service.layout.KPN_INPUTS order, H and W multiples of `alignment`
(the caller pads); outputs, all logits: fine (N, 51 * 4, H/2, W/2), the full-resolution KPN_FINE_OUTPUTS in
space-to-depth layout (`F.pixel_shuffle(fine, 2)` is (N, 51, H, W)), half (N, 26, H/2, W/2) and quarter
(N, 26, H/4, W/4) in KPN_COARSE_OUTPUTS order.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from models.nets import from_checkpoint, seeded
from models.nets.flnr import Block, unet
from models.nets.rae import SPACE_TO_DEPTH
from service.layout import KPN_COARSE_OUTPUTS, KPN_FINE_OUTPUTS, KPN_INPUTS, total_channels

FINE = total_channels(KPN_FINE_OUTPUTS)  # 51 (Zeng 2023 Fig. 6)
COARSE = total_channels(KPN_COARSE_OUTPUTS)  # 26 (Zeng 2023 Fig. 6)


@dataclass(frozen=True)
class KpnConfig:
    """Constructor arguments, stored in every checkpoint and in the ONNX metadata."""

    in_channels: int = total_channels(KPN_INPUTS)  # full-resolution input planes (layout.KPN_INPUTS)
    widths: tuple[int, ...] = (24, 32, 48, 64)  # features of each level, half resolution down; the last: bottleneck

    def __post_init__(self):
        if len(self.widths) < 3 or min(self.widths) < 1:
            raise ValueError(f"widths must be three or more positive counts (two decoder levels predict), got "
                             f"{self.widths}")


def _zero_head(cin: int, cout: int) -> nn.Conv2d:
    head = nn.Conv2d(cin, cout, 1)
    nn.init.zeros_(head.weight)
    nn.init.zeros_(head.bias)
    return head


class KernelPredictor(nn.Module):
    """features (N, 11, H, W) -> (fine, half, quarter) kernel and weight logits; shapes in the module docstring."""

    def __init__(self, config: KpnConfig | None = None):
        super().__init__()
        self.config = config or KpnConfig()
        w = self.config.widths
        s2 = SPACE_TO_DEPTH * SPACE_TO_DEPTH
        self.encoder = nn.ModuleList(Block(cin, c) for cin, c in zip((self.config.in_channels * s2, *w[:-2]), w[:-1],
                                                                      strict=True))
        self.bottleneck = Block(w[-2], w[-1])
        self.decoder = nn.ModuleList(Block(up + c, c) for up, c in zip(w[1:], w[:-1], strict=True))
        self.fine_head = _zero_head(w[0], FINE * s2)  # full resolution in space-to-depth layout
        self.half_head = _zero_head(w[0], COARSE)
        self.quarter_head = _zero_head(w[1], COARSE)

    @property
    def alignment(self) -> int:
        """Height and width must be multiples of this: space-to-depth and one 2x pooling per level below it."""
        return SPACE_TO_DEPTH * 2 ** (len(self.config.widths) - 1)

    def forward(self, features: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        decoded = unet(F.pixel_unshuffle(features, SPACE_TO_DEPTH), self.encoder, self.bottleneck, self.decoder)
        half_res, quarter_res = decoded[-1], decoded[-2]
        return self.fine_head(half_res), self.half_head(half_res), self.quarter_head(quarter_res)


def make_kpn(config: KpnConfig | None = None, *, seed: int | None = None) -> KernelPredictor:
    """A freshly He-initialised network (zero heads); `seed` makes it reproducible."""
    return seeded(lambda: KernelPredictor(config), seed)


def load_network(ckpt: dict) -> KernelPredictor:
    """The network of a checkpoint dict ({'config', 'state_dict'}), weights loaded, in eval mode."""
    return from_checkpoint(KernelPredictor, KpnConfig, ckpt)
