"""The torch twin of the served fast local regression (service/stages/flr.py), differentiable in the guides.

FLNR (Salmi et al.) trains its guide network end to end through the regression: the loss is taken on what
FLR makes of the learned guides, so the gradient reaches the network through the per-pixel least squares.
Every step is the served one (tests/models/train/test_flr_twin.py holds them to the numba kernels):

  1. guides standardised per image and plane (`regression.planes.standardise`);
  2. the moments [1, x, y, x x^T (upper triangle), x y^T] summed over `scale` x `scale` cells, the last
     row and column of cells partial (`flr.cell_sums`);
  3. a separable Gaussian over the cell grid, truncated at the border, taps exp(-d^2 / 2 sigma^2) with the
     centre tap 1: weights, not averages (`flr.gaussian_blur`);
  4. per cell, in float64, cov(x, x) a = cov(x, y) with the ridge on the slopes, b = mean(y) - a . mean(x)
     (`flr.solve_cells`, `regression.solve`);
  5. the coefficients bilinearly upsampled with the served taps and I = b + a . x (`flr.apply_coefficients`).

The served stage also clamps fireflies in y and demodulates by the albedo before this, and remodulates
after; the caller does those here (y is the demodulated radiance, the output is too).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from service.stages.flr import FlrParams, bilinear_taps, gaussian_taps

STD_FLOOR = 1e-12  # relative: a plane whose std is below this times (|mean| + 1) does not vary (becomes 0)


def standardise(x: torch.Tensor) -> torch.Tensor:
    """(N, Q, H, W) guides -> each image's planes minus their mean over their std (0 where constant)."""
    mean = x.mean(dim=(-2, -1), keepdim=True)
    centred = x - mean
    std = centred.square().mean(dim=(-2, -1), keepdim=True).sqrt()
    varies = std > STD_FLOOR * (mean.abs() + 1.0)
    return torch.where(varies, centred / torch.where(varies, std, torch.ones_like(std)), torch.zeros_like(x))


def moments(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """(N, Q, H, W) standardised guides and (N, C, H, W) signal -> (N, E, H, W) per-pixel moments in the
    order of `flr.cell_sums`: 1, x, y, x_i x_j (i <= j), x_i y_k."""
    q, c = x.shape[1], y.shape[1]
    planes = [torch.ones_like(x[:, :1]), x, y]
    planes += [x[:, i : i + 1] * x[:, j : j + 1] for i in range(q) for j in range(i, q)]
    planes += [x[:, i : i + 1] * y[:, k : k + 1] for i in range(q) for k in range(c)]
    return torch.cat(planes, dim=1)


def cell_sums(m: torch.Tensor, scale: int) -> torch.Tensor:
    """(N, E, H, W) -> (N, E, ceil(H / scale), ceil(W / scale)) sums over each cell's pixels."""
    h, w = m.shape[-2:]
    padded = F.pad(m, (0, (-w) % scale, 0, (-h) % scale))
    n, e, hp, wp = padded.shape
    return padded.reshape(n, e, hp // scale, scale, wp // scale, scale).sum(dim=(3, 5))


def gaussian_blur(sums: torch.Tensor, sigma: float, truncate: float) -> torch.Tensor:
    """(N, E, h, w) cell sums blurred by the served taps along both axes, zero beyond the border."""
    taps = torch.from_numpy(gaussian_taps(sigma, truncate)).to(sums)
    radius = taps.shape[0] - 1
    kernel = torch.cat([taps.flip(0), taps[1:]])  # (2R + 1,): symmetric
    e = sums.shape[1]
    out = F.conv2d(sums, kernel.view(1, 1, -1, 1).expand(e, 1, -1, 1), padding=(radius, 0), groups=e)
    return F.conv2d(out, kernel.view(1, 1, 1, -1).expand(e, 1, 1, -1), padding=(0, radius), groups=e)


def solve_cells(sums: torch.Tensor, q: int, c: int, ridge_relative: float, ridge_absolute: float) -> torch.Tensor:
    """(N, E, h, w) blurred sums -> (N, 1 + Q, C, h, w) coefficients (offsets, then each guide's slopes),
    solved in float64 and returned in the input's dtype."""
    s = sums.double().permute(0, 2, 3, 1)  # (N, h, w, E)
    s0 = s[..., :1].clamp_min(1e-30)
    mean_x, mean_y = s[..., 1 : 1 + q] / s0, s[..., 1 + q : 1 + q + c] / s0
    upper = [(i, j) for i in range(q) for j in range(i, q)]
    index = {pair: 1 + q + c + k for k, pair in enumerate(upper)}
    pick = torch.tensor([[index[(min(i, j), max(i, j))] for j in range(q)] for i in range(q)], dtype=torch.long)
    sum_xx = s[..., pick.flatten()].reshape(*s.shape[:3], q, q)
    cov_xx = sum_xx / s0[..., None] - mean_x[..., :, None] * mean_x[..., None, :]
    first_xy = 1 + q + c + len(upper)
    sum_xy = s[..., first_xy : first_xy + q * c].reshape(*s.shape[:3], q, c)
    cov_xy = sum_xy / s0[..., None] - mean_x[..., :, None] * mean_y[..., None, :]
    diagonal = torch.diagonal(cov_xx, dim1=-2, dim2=-1)
    ridge = ridge_relative * diagonal.clamp_min(0.0) + ridge_absolute
    slopes = torch.linalg.solve(cov_xx + torch.diag_embed(ridge), cov_xy)  # (N, h, w, Q, C)
    offsets = mean_y - (mean_x[..., :, None] * slopes).sum(dim=-2)
    coefs = torch.cat([offsets[..., None, :], slopes], dim=-2)  # (N, h, w, 1 + Q, C)
    return coefs.permute(0, 3, 4, 1, 2).to(sums.dtype)


def upsample(coefs: torch.Tensor, height: int, width: int, scale: int) -> torch.Tensor:
    """(N, K, C, h, w) cell coefficients -> (N, K, C, H, W), bilinear with the served taps."""
    hs, ws = coefs.shape[-2:]
    y0, y1, fy = (torch.from_numpy(t) for t in bilinear_taps(height, hs, scale))
    x0, x1, fx = (torch.from_numpy(t) for t in bilinear_taps(width, ws, scale))
    fy, fx = fy.to(coefs)[:, None], fx.to(coefs)
    rows = coefs[..., y0, :] + fy * (coefs[..., y1, :] - coefs[..., y0, :])
    return rows[..., x0] + fx * (rows[..., x1] - rows[..., x0])


def local_linear_regression(y: torch.Tensor, guides: torch.Tensor, params: FlrParams | None = None) -> torch.Tensor:
    """FLR of y on guides. y: (N, C, H, W) linear signal (demodulated radiance, fireflies already clamped);
    guides: (N, Q, H, W), any units (standardised here). Returns (N, C, H, W): I_k = x_k A_k."""
    params = params or FlrParams()
    x = standardise(guides)
    q, c = x.shape[1], y.shape[1]
    sums = gaussian_blur(cell_sums(moments(x, y), params.scale), params.sigma, params.truncate)
    coefs = upsample(solve_cells(sums, q, c, params.ridge_relative, params.ridge_absolute), *y.shape[-2:], params.scale)
    return coefs[:, 0] + (coefs[:, 1:] * x[:, :, None]).sum(dim=1)

