"""The recurrent denoising autoencoder (Chaitanya et al. 2017, sec. 4, Fig. 2), sized for CPU inference.

As in the paper: a U-Net-like encoder-decoder with skip connections by concatenation; a recurrent
convolutional block at every encoder level, right before its 2x2 max pooling (sec. 4.2):
    h_i = O_i = C3x3(C3x3(C3x3(I_i) ^ h_{i-1}))          (^: channel concatenation)
the decoder upsamples 2x by nearest neighbour, concatenates the skip and applies two 3x3 convolutions;
leaky ReLU (alpha 0.1) after every convolution but the last, which is linear; He initialisation (sec. 5.3).

Choices where the paper is silent or where we depart from it (each tested in tests/models/nets/test_rae.py):
- Space-to-depth: the network runs at half resolution. The input planes are rearranged 2x2 -> 4x the
  channels (pixel unshuffle) and the output 4x3 channels back to full resolution (pixel shuffle). The
  paper's full-resolution first level alone costs ~60K multiply-adds per pixel, about twice OIDN-high's
  whole time on a 2-core CPU at 1280x720; the issue asks for half of OIDN-high's time. Texture detail
  comes back through the albedo remodulation, so the illumination the network sees is smooth enough for
  a half-resolution network whose first layer sees every full-resolution sample.
- Widths: `RaeConfig.widths`, one per encoder level, default (32, 48, 64, 80) with a bottleneck of the last
  width, four levels: the half-resolution input plus four poolings puts the bottleneck at 1/32 of the frame,
  as the paper's five poolings do; its 32...101 widths are trimmed at the coarse end.
- The encoder level is the recurrent block itself: its first convolution maps the level's input to the
  level's width (the paper draws an extra convolution before the block).
- Each decoder level's two convolutions have the width of the encoder level they join.
- The hidden state is zero at the first frame of a sequence (the caller passes zeros).

Tensors: features (N, in_channels, H, W) float32, H and W multiples of `alignment` (the caller pads);
hidden[i] (N, widths[i], H / (2 * 2^i), W / (2 * 2^i)) float32; output (N, out_channels, H, W) float32.
The input and output contract (channel groups, transforms) is service.layout.RAE_INPUTS / RAE_OUTPUTS.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from models.nets import from_checkpoint, seeded
from service.layout import RAE_INPUTS, RAE_OUTPUTS, total_channels

LEAKY_SLOPE = 0.1  # Chaitanya 2017 sec. 5.3: leaky ReLU with alpha = 0.1
SPACE_TO_DEPTH = 2  # the network's resolution is the frame's / 2 (module docstring)


@dataclass(frozen=True)
class RaeConfig:
    """Constructor arguments, stored in every checkpoint and in the ONNX metadata."""

    in_channels: int = total_channels(RAE_INPUTS)  # full-resolution input channels (layout.RAE_INPUTS)
    out_channels: int = total_channels(RAE_OUTPUTS)  # full-resolution output channels (layout.RAE_OUTPUTS)
    widths: tuple[int, ...] = (32, 48, 64, 80)  # features of each encoder level; the last is the bottleneck's too

    def __post_init__(self):
        if len(self.widths) < 1 or min(self.widths) < 1:
            raise ValueError(f"widths must be one or more positive counts, got {self.widths}")

    @property
    def levels(self) -> int:
        return len(self.widths)

    @property
    def scales(self) -> tuple[int, ...]:
        """Each level's (and its hidden state's) downsampling of the frame: space-to-depth, then one 2x
        pooling per level above it."""
        return tuple(SPACE_TO_DEPTH * 2**level for level in range(self.levels))

    def hidden_shapes(self, height: int, width: int) -> list[tuple[int, int, int]]:
        """(channels, rows, columns) of each hidden state for an (aligned) frame of height x width pixels."""
        return [(c, height // s, width // s) for c, s in zip(self.widths, self.scales, strict=True)]


def conv3x3(cin: int, cout: int) -> nn.Conv2d:
    """A 3x3 convolution (padding 1) He-initialised for the leaky ReLU that follows it, bias 0."""
    conv = nn.Conv2d(cin, cout, 3, padding=1)
    nn.init.kaiming_normal_(conv.weight, a=LEAKY_SLOPE, nonlinearity="leaky_relu")  # He et al. 2015b
    nn.init.zeros_(conv.bias)
    return conv


def _act(x: torch.Tensor) -> torch.Tensor:
    return F.leaky_relu(x, LEAKY_SLOPE)


class RecurrentBlock(nn.Module):
    """h_i = O_i = C(C(C(I_i) ^ h_{i-1})) (Chaitanya 2017 sec. 4.2), leaky ReLU after each convolution."""

    def __init__(self, cin: int, width: int):
        super().__init__()
        self.input = conv3x3(cin, width)
        self.mix = conv3x3(2 * width, width)
        self.out = conv3x3(width, width)

    def forward(self, x: torch.Tensor, hidden: torch.Tensor) -> torch.Tensor:
        x = _act(self.input(x))
        x = _act(self.mix(torch.cat([x, hidden], dim=1)))
        return _act(self.out(x))


class RecurrentAutoencoder(nn.Module):
    """(features, hidden_0..hidden_{L-1}) -> (output, new hidden_0..hidden_{L-1}); shapes in the module
    docstring. One call is one frame; a sequence is a loop that feeds each call's hidden outputs to the next."""

    def __init__(self, config: RaeConfig | None = None):
        super().__init__()
        self.config = config or RaeConfig()
        w = self.config.widths
        s2 = SPACE_TO_DEPTH * SPACE_TO_DEPTH
        cins = (self.config.in_channels * s2, *w[:-1])
        self.encoder = nn.ModuleList(RecurrentBlock(cin, c) for cin, c in zip(cins, w, strict=True))
        self.bottleneck = conv3x3(w[-1], w[-1])
        ups = (*w[1:], w[-1])  # channels arriving from below at each level
        self.decoder = nn.ModuleList(
            nn.ModuleList([conv3x3(up + c, c), conv3x3(c, c)]) for up, c in zip(ups, w, strict=True)
        )
        self.head = nn.Conv2d(w[0], self.config.out_channels * s2, 3, padding=1)  # linear (sec. 5.3)
        nn.init.kaiming_normal_(self.head.weight, nonlinearity="linear")
        nn.init.zeros_(self.head.bias)

    @property
    def alignment(self) -> int:
        """Height and width must be multiples of this: space-to-depth and one 2x pooling per level."""
        return SPACE_TO_DEPTH * 2**self.config.levels

    def zero_hidden(self, batch: int, height: int, width: int, *, device=None) -> list[torch.Tensor]:
        """The hidden state of a sequence's first frame: zeros of `hidden_shapes` (aligned height, width)."""
        return [torch.zeros(batch, *shape, device=device) for shape in self.config.hidden_shapes(height, width)]

    def forward(self, features: torch.Tensor, *hidden: torch.Tensor) -> tuple[torch.Tensor, ...]:
        x = F.pixel_unshuffle(features, SPACE_TO_DEPTH)
        skips, new_hidden = [], []
        for level, block in enumerate(self.encoder):
            x = block(x, hidden[level])
            new_hidden.append(x)
            skips.append(x)
            x = F.max_pool2d(x, 2)
        x = _act(self.bottleneck(x))
        for level in reversed(range(self.config.levels)):
            first, second = self.decoder[level]
            x = F.interpolate(x, scale_factor=2.0, mode="nearest")
            x = _act(first(torch.cat([x, skips[level]], dim=1)))
            x = _act(second(x))
        out = F.pixel_shuffle(self.head(x), SPACE_TO_DEPTH)
        return (out, *new_hidden)


def make_rae(config: RaeConfig | None = None, *, seed: int | None = None) -> RecurrentAutoencoder:
    """A freshly He-initialised network; `seed` makes it reproducible."""
    return seeded(lambda: RecurrentAutoencoder(config), seed)


def load_network(ckpt: dict) -> RecurrentAutoencoder:
    """The network of a checkpoint dict (`state_for` keys), weights loaded, in eval mode."""
    return from_checkpoint(RecurrentAutoencoder, RaeConfig, ckpt)
