"""numba (inference, service/stages/kernel_filter.py) vs torch (training, models/train/kernel_filter.py) kernel
filter of the `kpn` pipeline: random kernels and weights, odd sizes, edges; and its gradient."""

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from models.train import kernel_filter as twin  # noqa: E402
from service.stages import kernel_filter as served  # noqa: E402
from tests.tolerances import TWIN_ATOL  # noqa: E402


def _kernels(rng, taps_and_alpha: int, height: int, width: int, alphas: int) -> np.ndarray:
    """(taps_and_alpha, h, w) float32: softmax-normalised kernels (any sign of logits), alphas in (0, 1) last."""
    logits = rng.normal(0, 2, (taps_and_alpha - alphas, height, width))
    kernels = np.exp(logits - logits.max(0)) / np.exp(logits - logits.max(0)).sum(0)
    return np.concatenate([kernels, rng.random((alphas, height, width))]).astype(np.float32)


def _case(height, width, seed):
    rng = np.random.default_rng(seed)
    noisy = rng.random((3, height, width), np.float32) * 3
    previous = rng.random((3, height, width), np.float32) * 3
    fine = np.concatenate([_kernels(rng, 26, height, width, 1)[:25], _kernels(rng, 26, height, width, 1)])
    half = _kernels(rng, 26, height // 2, width // 2, 1)
    quarter = _kernels(rng, 26, height // 4, width // 4, 1)
    return noisy, previous, fine, half, quarter


def _t(a):
    return torch.from_numpy(np.ascontiguousarray(a[None]))


@pytest.mark.parametrize("size", [(7, 9), (3, 2), (1, 1), (12, 5)])
def test_kernel_application_agrees(size):
    """Odd and tiny sizes: every tap of a 5x5 window reaches past an edge somewhere (edge replication)."""
    rng = np.random.default_rng(sum(size))
    image = rng.standard_normal((3, *size)).astype(np.float32)
    kernel = rng.standard_normal((25, *size)).astype(np.float32)  # any weights, not only normalised ones
    ref = served.apply_kernel(image, kernel)
    np.testing.assert_allclose(twin.apply_kernel(_t(image), _t(kernel))[0].numpy(), ref, atol=TWIN_ATOL)
    # the edge rule by hand: a kernel all on tap (dy, dx) = (-2, -2) shifts the image, clamped at the edges
    corner = np.zeros((25, *size), np.float32)
    corner[0] = 1
    rows = np.maximum(np.arange(size[0]) - 2, 0)
    cols = np.maximum(np.arange(size[1]) - 2, 0)
    np.testing.assert_array_equal(served.apply_kernel(image, corner), image[:, rows][:, :, cols])


@pytest.mark.parametrize("size", [(6, 10), (2, 4), (8, 2)])
def test_resampling_agrees(size):
    rng = np.random.default_rng(1)
    image = rng.standard_normal((3, *size)).astype(np.float32)
    np.testing.assert_allclose(twin.upsample(_t(image))[0].numpy(), served.upsample(image), atol=TWIN_ATOL)
    np.testing.assert_allclose(twin.downsample(_t(image))[0].numpy(), served.downsample(image), atol=TWIN_ATOL)


@pytest.mark.parametrize("size", [(20, 12), (4, 4), (28, 36)])
def test_whole_filter_agrees(size):
    noisy, previous, fine, half, quarter = _case(*size, seed=size[0])
    ref = served.kernel_filter(noisy, previous, fine, half, quarter)
    out = twin.kernel_filter(*(_t(a) for a in (noisy, previous, fine, half, quarter)))
    np.testing.assert_allclose(out[0].numpy(), ref, atol=TWIN_ATOL)


def test_constants_stay_constant():
    """Kernels that sum to 1 and alphas in (0, 1): a constant noisy image and history give that constant."""
    noisy, _, fine, half, quarter = _case(16, 24, seed=5)
    flat = np.full_like(noisy, 0.7)
    out = served.kernel_filter(flat, flat, fine, half, quarter)
    np.testing.assert_allclose(out, 0.7, atol=1e-6)


def test_alpha_selects_scales_and_history():
    """alpha_t = 1: no history; alpha_t -> 0: the filtered history alone; coarse alphas 0: the fine scale alone."""
    noisy, previous, fine, half, quarter = _case(16, 16, seed=6)
    half[-1], quarter[-1] = 0, 0
    fine[-1] = 1
    np.testing.assert_allclose(served.kernel_filter(noisy, previous, fine, half, quarter),
                               served.apply_kernel(noisy, fine[:25]), atol=1e-6)
    fine[-1] = 0
    np.testing.assert_allclose(served.kernel_filter(noisy, previous, fine, half, quarter),
                               served.apply_kernel(previous, fine[25:50]), atol=1e-6)


def test_gradient_reaches_every_input():
    noisy, previous, fine, half, quarter = (_t(a).requires_grad_() for a in _case(8, 12, seed=7))
    twin.kernel_filter(noisy, previous, fine, half, quarter).square().sum().backward()
    for tensor in (noisy, previous, fine, half, quarter):
        assert torch.isfinite(tensor.grad).all() and tensor.grad.abs().sum() > 0
