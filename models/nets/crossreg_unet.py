"""The simplified U-Net of the cross-regression denoiser (Choi et al. 2024, sec. 4.4).

Two max-poolings and two upsamplings, 3x3 convolutions with [8, 16, 32, 16, 8] filters and ReLU (two per
level on the way down and at the bottom, as in the authors' code), skip connections by concatenation,
and a final 1x1 convolution to the six per-pixel filter parameters theta. The head turns the five
bandwidths into precisions 1 / (theta^2 + eps) (positive for any theta; eq. 9's denominators) and
theta_alpha into sigmoid(theta_alpha) (sec. 4.4). About 30K parameters.

Upsampling is nearest-neighbour (the authors use a 1x1 transposed convolution with stride 2, which
leaves every other row and column at its bias); it exports to one ONNX Resize and costs no parameters.

Input and output contract: service.layout.CROSSREG_INPUTS / CROSSREG_OUTPUTS; height and width must be
multiples of `alignment` (the caller pads, see service.layout.pad_planes).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import torch
from torch import nn

from models.nets import seeded
from service.layout import CROSSREG_INPUTS, CROSSREG_OUTPUTS, total_channels

BANDWIDTH_EPS = 1e-4  # Choi 2024 eq. 9 epsilon; the authors' code uses 1e-4 (band = 1 / (theta^2 + 1e-4))


@dataclass(frozen=True)
class UNetConfig:
    """Constructor arguments, stored in every checkpoint and in the ONNX metadata."""

    in_channels: int = total_channels(CROSSREG_INPUTS)  # 15: pilots A, B, previous, albedo, normal
    out_channels: int = total_channels(CROSSREG_OUTPUTS)  # 6: five precisions and alpha
    widths: tuple[int, int, int] = (8, 16, 32)  # Choi 2024 sec. 4.4: [8, 16, 32, 16, 8]
    eps: float = BANDWIDTH_EPS  # added to theta^2 before inverting


def _conv(cin: int, cout: int) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(cin, cout, 3, padding=1), nn.ReLU(inplace=True))


class CrossRegUNet(nn.Module):
    """features (N, 15, H, W) float32 -> params (N, 6, H, W) float32; H, W multiples of `alignment`."""

    def __init__(self, config: UNetConfig | None = None):
        super().__init__()
        self.config = config or UNetConfig()
        c1, c2, c3 = self.config.widths
        self.enc1 = nn.Sequential(_conv(self.config.in_channels, c1), _conv(c1, c1))
        self.enc2 = nn.Sequential(_conv(c1, c2), _conv(c2, c2))
        self.bottom = nn.Sequential(_conv(c2, c3), _conv(c3, c3))
        self.dec2 = nn.Sequential(_conv(c3 + c2, c2), _conv(c2, c2))
        self.dec1 = _conv(c2 + c1, c1)
        self.head = nn.Conv2d(c1, self.config.out_channels, 1)
        self.pool = nn.MaxPool2d(2)
        self.up = nn.Upsample(scale_factor=2, mode="nearest")

    alignment = 4  # two 2x poolings: inputs must be multiples of 2^2

    def theta(self, features: torch.Tensor) -> torch.Tensor:
        """Raw theta (N, 6, H, W) before the head's positivity / sigmoid transforms."""
        e1 = self.enc1(features)
        e2 = self.enc2(self.pool(e1))
        b = self.bottom(self.pool(e2))
        d2 = self.dec2(torch.cat([self.up(b), e2], dim=1))
        d1 = self.dec1(torch.cat([self.up(d2), e1], dim=1))
        return self.head(d1)

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        theta = self.theta(features)
        bands, alpha = theta[:, :-1], theta[:, -1:]
        precisions = 1.0 / (bands * bands + self.config.eps)
        return torch.cat([precisions, torch.sigmoid(alpha)], dim=1)


def make_unet(config: UNetConfig | None = None, *, seed: int | None = None) -> CrossRegUNet:
    """A freshly (randomly, PyTorch default) initialised network; `seed` makes it reproducible."""
    return seeded(lambda: CrossRegUNet(config), seed)


def save_checkpoint(path: str, net: CrossRegUNet, **extra: object) -> None:
    """Write {'config': constructor args, 'state_dict': weights, **extra} with torch.save."""
    torch.save({"config": asdict(net.config), "state_dict": net.state_dict(), **extra}, path)


def load_checkpoint(path: str) -> tuple[CrossRegUNet, dict]:
    """(network rebuilt from the stored constructor args with the stored weights, the whole checkpoint)."""
    ckpt = torch.load(path, map_location="cpu", weights_only=True)
    config = dict(ckpt["config"])
    config["widths"] = tuple(config["widths"])
    net = CrossRegUNet(UNetConfig(**config))
    net.load_state_dict(ckpt["state_dict"])
    return net, ckpt
