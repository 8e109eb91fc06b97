"""The torch twin of FLR (models/train/flr.py) against the served numba stage (service/stages/flr.py)."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from models.train import flr as twin  # noqa: E402
from service.regression.planes import standardise  # noqa: E402
from service.stages.flr import FlrParams, local_linear_regression  # noqa: E402

RTOL = 2e-3  # float32 moments summed in another order; the solve is float64 on both sides


def _scene(height: int, width: int, q: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:height, 0:width].astype(np.float32)
    guides = np.stack([np.sin(xx / 7 + k) + 0.3 * np.cos(yy / 5 - k) + 0.05 * rng.standard_normal((height, width))
                       for k in range(q)], axis=-1).astype(np.float32)
    radiance = (1.0 + guides[..., :1] ** 2 + 0.2 * rng.standard_normal((height, width, 3))).astype(np.float32)
    return radiance, guides


@pytest.mark.parametrize(("height", "width", "scale", "sigma"), [(37, 53, 4, 0.5), (64, 48, 2, 1.5), (20, 31, 8, 0.7)])
def test_twin_matches_the_served_regression(height: int, width: int, scale: int, sigma: float) -> None:
    radiance, guides = _scene(height, width, 5, seed=height)
    params = FlrParams(scale=scale, sigma=sigma, firefly_k=None, robust_clamp=False)
    served = local_linear_regression(radiance, guides, params)
    y = torch.from_numpy(radiance.transpose(2, 0, 1).copy())[None]
    x = torch.from_numpy(guides.transpose(2, 0, 1).copy())[None]
    ours = twin.local_linear_regression(y, x, params)[0].numpy().transpose(1, 2, 0)
    scale_of = np.abs(served).max()
    np.testing.assert_allclose(ours, served, rtol=0, atol=RTOL * scale_of)


def test_standardise_matches_and_constant_planes_become_zero() -> None:
    _, guides = _scene(17, 23, 3, seed=1)
    planes = guides.transpose(2, 0, 1).copy()
    planes[1] = 4.0  # constant
    ours = twin.standardise(torch.from_numpy(planes)[None])[0].numpy()
    np.testing.assert_allclose(ours, standardise(planes), atol=1e-5)
    assert not ours[1].any()


def test_guides_receive_gradients_and_a_linear_signal_is_reproduced() -> None:
    """A signal that is an affine function of a guide is fitted exactly (up to the ridge), and the loss
    reaches the guides: what FLNR's training needs."""
    _, guides = _scene(32, 32, 2, seed=3)
    x = torch.from_numpy(guides.transpose(2, 0, 1).copy())[None].requires_grad_(True)
    y = (2.0 + 3.0 * x[:, :1].detach()).expand(1, 3, 32, 32).contiguous()
    out = twin.local_linear_regression(y, x, FlrParams())
    np.testing.assert_allclose(out.detach().numpy(), y.numpy(), rtol=0, atol=1e-3 * float(y.abs().max()))
    (out - 1.0).square().mean().backward()
    assert x.grad is not None and torch.isfinite(x.grad).all() and x.grad.abs().sum() > 0
