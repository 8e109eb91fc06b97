"""One self-supervised training step of the cross-regression denoiser, shared by the online worker and
the offline warm-start training: network -> spatiotemporal filter -> loss (Choi 2024 eqs. 8-13) -> Adam.

A training sample is one (H, W, 22) float32 array in service.layout.CROSSREG_SAMPLE order: the 15
network-input channels, then `valid` and the two reprojected previous pilots. H and W must be multiples
of the network's alignment (random crops are drawn that way).
"""

from __future__ import annotations

import numpy as np
import torch

from models.nets.crossreg_unet import CrossRegUNet
from models.train.filter import FilterResult, spatiotemporal_filter
from models.train.loss import crossreg_loss
from service.layout import CROSSREG_INPUTS, CROSSREG_SAMPLE, channel_slices, total_channels

LEARNING_RATE = 1e-3  # Choi 2024 sec. 4.4, Adam
SLICES = channel_slices(CROSSREG_SAMPLE)
N_INPUTS = total_channels(CROSSREG_INPUTS)


def make_optimizer(net: CrossRegUNet, lr: float = LEARNING_RATE) -> torch.optim.Optimizer:
    return torch.optim.Adam(net.parameters(), lr=lr)


def samples_to_tensor(samples: list[np.ndarray] | np.ndarray) -> torch.Tensor:
    """(H, W, 22) float32 array(s) -> (N, 22, H, W) tensor."""
    arr = np.stack(samples) if isinstance(samples, list) else samples[None]
    return torch.from_numpy(np.ascontiguousarray(arr.transpose(0, 3, 1, 2), dtype=np.float32))


def forward(net: CrossRegUNet, batch: torch.Tensor, min_alpha: float = 0.0) -> tuple[torch.Tensor, FilterResult]:
    """(loss, filter result) for batch (N, 22, H, W) in CROSSREG_SAMPLE order; min_alpha: the served
    filter's floor of alpha (crossreg's option). The pilot-colour precisions are the network's, unfloored
    (crossreg's `pilot_bandwidth` applies when serving only: trained through it, online training did worse,
    docs/benchmarks.md)."""
    s = SLICES
    params = net(batch[:, :N_INPUTS])
    result = spatiotemporal_filter(
        batch[:, s["pilotA"]], batch[:, s["pilotB"]], batch[:, s["albedo"]], batch[:, s["normal"]],
        params, batch[:, s["previous"]], batch[:, s["valid"]], min_alpha=min_alpha,
    )  # fmt: skip
    loss = crossreg_loss(
        result.color_a, result.color_b, batch[:, s["pilotA"]], batch[:, s["pilotB"]],
        batch[:, s["previousPilotA"]], batch[:, s["previousPilotB"]],
    )  # fmt: skip
    return loss, result


def train_step(net: CrossRegUNet, optimizer: torch.optim.Optimizer, batch: torch.Tensor,
               min_alpha: float = 0.0) -> float:
    """One gradient step on `batch` (through the filter with the floor `min_alpha`); returns the loss
    before the step."""
    net.train()
    optimizer.zero_grad(set_to_none=True)
    loss, _ = forward(net, batch, min_alpha)
    loss.backward()
    optimizer.step()
    return float(loss.detach())


def weights_numpy(net: CrossRegUNet) -> dict[str, np.ndarray]:
    """name -> float32 copy of every parameter (the names the ONNX initializers carry)."""
    return {name: p.detach().cpu().numpy().astype(np.float32, copy=True) for name, p in net.named_parameters()}


def load_weights_numpy(net: CrossRegUNet, weights: dict[str, np.ndarray]) -> None:
    """Copy `weights` (from `weights_numpy` or an ONNX file's initializers) into `net`."""
    state = {name: torch.from_numpy(np.array(value, np.float32)) for name, value in weights.items()}
    net.load_state_dict(state, strict=True)

