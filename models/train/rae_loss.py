"""The training loss of the recurrent denoising autoencoder (Chaitanya et al. 2017, sec. 4.4).

Both the prediction and the target are flattened by a power of 0.2 first ("raises both input and target
images into power 0.2"), then, per frame t of a window,

    L_t = ws * Ls + wg * Lg + wt * Lt,   ws/wg/wt = 0.8/0.1/0.1 (the paper's; `--temporal-weight` sets wt,
                                          and ws = 0.9 - wt keeps the sum at 1)
    Ls  = mean |P - T|                                       spatial L1
    Lg  = mean |LoG(P) - LoG(T)|                             HFEN: Laplacian of Gaussian, sigma 1.5
    Lt  = mean |(P_t - P_{t-1}) - (T_t - T_{t-1})|           temporal L1 (0 at the first frame)

and the window's loss is sum_t g_t L_t / sum_t g_t with the paper's Gaussian frame weights g_t
(0.011, 0.044, 0.135, 0.325, 0.607, 0.882, 1) for T = 7, i.e. exp(-(t - T + 1)^2 / 8) for any T. Dividing by
sum_t g_t (the paper does not say) only rescales the loss.

Domain: the network predicts log1p of demodulated radiance (service.layout.RAE_OUTPUTS); it is mapped back
with expm1 (clipped at LOG_RADIANCE_MAX, the serving side's clip) before the power. TONE_EPS keeps the
power's derivative finite at 0.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch
import torch.nn.functional as F

from service.stages.rae_inputs import LOG_RADIANCE_MAX

GAMMA = 0.2  # Chaitanya 2017 sec. 4.4: "a more aggressive value of 0.2"
# added before the power: d/dx (x + eps)^0.2 <= 0.2 * eps^-0.8 ~ 50 at x = 0. The default of the shipped weights;
# `--tone-eps` (models.train) sets it per run, in (0, 1]: a larger one weighs near-black pixels less
# (docs/training.md, "Gradient norms").
TONE_EPS = 1e-3
WEIGHTS = (0.8, 0.1, 0.1)  # ws, wg, wt (Chaitanya 2017 sec. 4.4)
TEMPORAL_WEIGHTS = (0.0, 0.9)  # the range of wt that `loss_weights` takes (ws = 0.9 - wt stays >= 0)
HFEN_SIGMA = 1.5  # Laplacian-of-Gaussian sigma, pixels (Ravishankar and Bresler 2011, as in the paper)
HFEN_RADIUS = 5  # kernel half-width, pixels: 11 taps, out to 3.3 sigma


def loss_weights(temporal: float = WEIGHTS[2]) -> tuple[float, float, float]:
    """(ws, wg, wt) with wt = `temporal` in TEMPORAL_WEIGHTS and ws = 1 - wg - wt: the paper's at wt = 0.1."""
    low, high = TEMPORAL_WEIGHTS
    if not low <= temporal <= high:
        raise ValueError(f"temporal weight must be in [{low}, {high}], got {temporal}")
    return 1.0 - WEIGHTS[1] - temporal, WEIGHTS[1], temporal


def frame_weights(frames: int) -> torch.Tensor:
    """(frames,) float32 Gaussian weights exp(-(t - frames + 1)^2 / 8): the paper's values for 7 frames."""
    t = torch.arange(frames, dtype=torch.float32)
    return torch.exp(-((t - frames + 1) ** 2) / 8.0)


def log_kernel(sigma: float = HFEN_SIGMA, radius: int = HFEN_RADIUS) -> torch.Tensor:
    """(2r+1, 2r+1) float32 Laplacian of Gaussian, shifted to sum to 0 (a constant image has no edges)."""
    r = torch.arange(-radius, radius + 1, dtype=torch.float64)
    y, x = torch.meshgrid(r, r, indexing="ij")
    q = (x * x + y * y) / (2 * sigma * sigma)
    kernel = (q - 1) / (math.pi * sigma**4) * torch.exp(-q)
    return (kernel - kernel.mean()).to(torch.float32)


def tone(x: torch.Tensor, eps: float = TONE_EPS) -> torch.Tensor:
    """Linear demodulated radiance (>= 0) -> (x + eps)^GAMMA, the loss's domain."""
    return (x + eps) ** GAMMA


def prediction_to_linear(pred: torch.Tensor) -> torch.Tensor:
    """The network's log1p output -> linear demodulated radiance, clipped as lighting_from_output clips it.
    The clip passes gradients straight through, so a prediction below 0 still learns where to go."""
    clipped = pred + (pred.clamp(0.0, LOG_RADIANCE_MAX) - pred).detach()
    return torch.expm1(clipped)


def hfen(image: torch.Tensor) -> torch.Tensor:
    """(N, C, H, W) -> LoG-filtered (N, C, H, W), edges replicated."""
    c = image.shape[1]
    kernel = log_kernel().to(image)[None, None].expand(c, 1, -1, -1)
    padded = F.pad(image, (HFEN_RADIUS,) * 4, mode="replicate")
    return F.conv2d(padded, kernel, groups=c)


@dataclass
class LossTerms:
    """The window loss and its terms (each already weighted over frames), scalars. `occlusion` is the `kpn`
    loss's motion-occlusion term (models/train/kpn_loss.py), 0 for the others; `gradient` (HFEN) is 0 for
    `kpn`."""

    total: torch.Tensor
    spatial: torch.Tensor
    gradient: torch.Tensor
    temporal: torch.Tensor
    occlusion: torch.Tensor = field(default_factory=lambda: torch.zeros(()))


def rae_loss(pred: torch.Tensor, target: torch.Tensor, eps: float = TONE_EPS,
             weights: tuple[float, float, float] = WEIGHTS) -> LossTerms:
    """pred: (N, T, 3, H, W) network output (log1p demodulated radiance); target: (N, T, 3, H, W) linear
    demodulated reference; eps: `tone`'s; weights: (ws, wg, wt), `loss_weights`. Returns the loss of the module
    docstring."""
    return tone_loss(prediction_to_linear(pred), target, eps, weights)


def tone_loss(linear: torch.Tensor, target: torch.Tensor, eps: float = TONE_EPS,
              weights: tuple[float, float, float] = WEIGHTS) -> LossTerms:
    """The loss of the module docstring on a linear prediction: linear, target (N, T, 3, H, W) demodulated
    radiance, >= 0 (FLNR's regression output, clipped at 0, takes this entry); eps: `tone`'s; weights: (ws, wg,
    wt)."""
    n, t = linear.shape[:2]
    p = tone(linear, eps)
    q = tone(target, eps)
    spatial = (p - q).abs().mean(dim=(0, 2, 3, 4))  # (T,)
    gradient = (hfen(p.flatten(0, 1)) - hfen(q.flatten(0, 1))).abs().reshape(n, t, -1).mean(dim=(0, 2))
    temporal = torch.zeros_like(spatial)
    if t > 1:
        change = (p[:, 1:] - p[:, :-1]) - (q[:, 1:] - q[:, :-1])
        temporal = torch.cat([temporal[:1], change.abs().mean(dim=(0, 2, 3, 4))])
    g = frame_weights(t).to(linear)
    g = g / g.sum()
    terms = [(g * term).sum() for term in (spatial, gradient, temporal)]
    total = sum(w * term for w, term in zip(weights, terms, strict=True))
    return LossTerms(total, *terms)
