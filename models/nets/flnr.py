"""The guide network of fast local neural regression (Salmi et al., "Enhancing Local Regression with Neural
Networks"): a small U-Net that turns the G-buffer and the noisy radiance into guide images for FLR.

As in the paper: "a simple U-Net with 4 encoder/decoder blocks and skip connections. Each block comprises
two 3x3 convolution layers followed by a Leaky ReLU", with few channels per layer. Input: the recurrent
autoencoder's planes (service.layout.RAE_INPUTS: log1p demodulated radiance, normal, relative depth,
roughness; the noisy light lets the network adapt the guides to the lighting); output: FLNR_OUTPUTS, the
guides FLR regresses on (it standardises them: any units).

The network transforms the input guides (Salmi: X -> X'): its output is the input's normal and relative
depth plus what the U-Net adds, and the U-Net's last layer starts at zero, so an untrained network is FLR
on the G-buffer and training moves away from it only where the loss says so. (Guides learned from scratch,
tried first, were worse than the G-buffer's after 2,000 steps: each guide is one more slope per channel for
a window of a few dozen pixels to fit, and a guide that does not follow the image only adds variance.)

Choices where the paper is silent:
- Space-to-depth, as in models/nets/rae.py: the network runs at half resolution (2x2 pixels -> 4x the
  channels in, and back out by pixel shuffle), so that the network and FLR together stay within a quarter
  of OIDN-high's time at 1280x720 on a 2-core CPU.
- Max pooling down, nearest upsampling, concatenated skips; leaky ReLU slope 0.1; He initialisation (the
  recurrent autoencoder's `conv3x3`); the head is linear and starts at zero.

Tensors: features (N, in_channels, H, W) float32, H and W multiples of `alignment` (the caller pads);
output (N, guides, H, W) float32.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from models.nets import from_checkpoint, seeded
from models.nets.rae import LEAKY_SLOPE, SPACE_TO_DEPTH, conv3x3
from service.layout import FLNR_OUTPUTS, RAE_INPUTS, channel_slices, total_channels

# The input planes the output starts from: normal and relative depth, adjacent in RAE_INPUTS
BASE_GUIDES = slice(channel_slices(RAE_INPUTS)["normal"].start, channel_slices(RAE_INPUTS)["depth"].stop)


@dataclass(frozen=True)
class FlnrConfig:
    """Constructor arguments, stored in every checkpoint and in the ONNX metadata."""

    in_channels: int = total_channels(RAE_INPUTS)  # full-resolution input planes (layout.RAE_INPUTS)
    guides: int = total_channels(FLNR_OUTPUTS)  # learned guide planes (layout.FLNR_OUTPUTS)
    widths: tuple[int, ...] = (12, 16, 24, 32)  # features of each encoder block (the paper: 4 blocks, few)
    space_to_depth: int = SPACE_TO_DEPTH  # the network runs at 1 / this of the frame's resolution

    def __post_init__(self):
        if len(self.widths) < 1 or min(self.widths) < 1 or self.space_to_depth < 1:
            raise ValueError(f"widths must be one or more positive counts, got {self}")
        base = BASE_GUIDES.stop - BASE_GUIDES.start
        if self.guides != base:
            raise ValueError(f"guides must be {base} (normal, depth), got {self.guides}")

    @property
    def levels(self) -> int:
        return len(self.widths)


class Block(nn.Module):
    """Two 3x3 convolutions, each followed by a leaky ReLU (Salmi et al.)."""

    def __init__(self, cin: int, cout: int):
        super().__init__()
        self.first, self.second = conv3x3(cin, cout), conv3x3(cout, cout)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.leaky_relu(self.second(F.leaky_relu(self.first(x), LEAKY_SLOPE)), LEAKY_SLOPE)


def unet(x: torch.Tensor, encoder: nn.ModuleList, bottleneck: nn.Module, decoder: nn.ModuleList) -> list[torch.Tensor]:
    """A U-Net pass: each encoder block then 2x max pooling, the bottleneck, then per level from the coarsest
    nearest 2x upsampling, the skip concatenated and that level's decoder block. x (N, C, h, w), h and w
    multiples of 2^len(encoder). Returns the decoder levels' outputs, coarsest first (the last is at x's
    resolution)."""
    skips = []
    for block in encoder:
        x = block(x)
        skips.append(x)
        x = F.max_pool2d(x, 2)
    x = bottleneck(x)
    decoded = []
    for level in reversed(range(len(decoder))):
        x = F.interpolate(x, scale_factor=2.0, mode="nearest")
        x = decoder[level](torch.cat([x, skips[level]], dim=1))
        decoded.append(x)
    return decoded


class GuideNet(nn.Module):
    """features (N, in_channels, H, W) -> guides (N, guides, H, W); shapes in the module docstring."""

    def __init__(self, config: FlnrConfig | None = None):
        super().__init__()
        self.config = config or FlnrConfig()
        w = self.config.widths
        s2 = self.config.space_to_depth**2
        self.encoder = nn.ModuleList(Block(cin, c) for cin, c in zip((self.config.in_channels * s2, *w[:-1]), w,
                                                                      strict=True))
        self.bottleneck = Block(w[-1], w[-1])
        self.decoder = nn.ModuleList(Block(up + c, c) for up, c in zip((*w[1:], w[-1]), w, strict=True))
        self.head = nn.Conv2d(w[0], self.config.guides * s2, 3, padding=1)
        nn.init.zeros_(self.head.weight)  # starts as the identity on the G-buffer guides (module docstring)
        nn.init.zeros_(self.head.bias)

    @property
    def alignment(self) -> int:
        """Height and width must be multiples of this: space-to-depth and one 2x pooling per level."""
        return self.config.space_to_depth * 2**self.config.levels

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        x = F.pixel_unshuffle(features, self.config.space_to_depth)
        x = unet(x, self.encoder, self.bottleneck, self.decoder)[-1]
        return features[:, BASE_GUIDES] + F.pixel_shuffle(self.head(x), self.config.space_to_depth)


def make_flnr(config: FlnrConfig | None = None, *, seed: int | None = None) -> GuideNet:
    """A freshly He-initialised network; `seed` makes it reproducible."""
    return seeded(lambda: GuideNet(config), seed)


def load_network(ckpt: dict) -> GuideNet:
    """The network of a checkpoint dict ({'config', 'state_dict'}), weights loaded, in eval mode."""
    return from_checkpoint(GuideNet, FlnrConfig, ckpt)
