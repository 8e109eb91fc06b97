"""numba (inference, service/stages/kernel_filter.py) vs torch (training, models/train/kernel_filter.py) kernel
filter of the `kpn` pipeline: random logits, odd sizes, edges, the space-to-depth layout; and its gradient."""

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from models.train import kernel_filter as twin  # noqa: E402
from service.stages import kernel_filter as served  # noqa: E402
from tests.tolerances import TWIN_ATOL  # noqa: E402

BIG = 200.0  # a logit this far below another gets exp(-200) = 0 in float32: the kernel is one tap exactly


def _case(height, width, seed, s=1):
    """Images and raw predictions; `fine` in the space-to-depth layout of factor s."""
    rng = np.random.default_rng(seed)
    noisy = rng.random((3, height, width), np.float32) * 3
    previous = rng.random((3, height, width), np.float32) * 3
    fine = rng.normal(0, 2, (51 * s * s, height // s, width // s)).astype(np.float32)
    half = rng.normal(0, 2, (26, height // 2, width // 2)).astype(np.float32)
    quarter = rng.normal(0, 2, (26, height // 4, width // 4)).astype(np.float32)
    return noisy, previous, fine, half, quarter


def _t(a):
    return torch.from_numpy(np.ascontiguousarray(a[None]))


def _pixel_shuffle(planes, s):
    """(C s^2, h, w) -> (C, h s, w s), torch's pixel_shuffle order."""
    c, h, w = planes.shape
    return planes.reshape(c // (s * s), s, s, h, w).transpose(0, 3, 1, 4, 2).reshape(c // (s * s), h * s, w * s)


@pytest.mark.parametrize("size", [(7, 9), (3, 2), (1, 1), (12, 5)])
def test_kernel_application_agrees(size):
    """Odd and tiny sizes: every tap of a 5x5 window reaches past an edge somewhere (edge replication)."""
    rng = np.random.default_rng(sum(size))
    image = rng.standard_normal((3, *size)).astype(np.float32)
    logits = rng.normal(0, 3, (25, *size)).astype(np.float32)
    ref = served.apply_kernel(image, logits)
    np.testing.assert_allclose(twin.apply_kernel(_t(image), _t(logits))[0].numpy(), ref, atol=TWIN_ATOL)
    # the edge rule by hand: a kernel all on tap (dy, dx) = (-2, -2) shifts the image, clamped at the edges
    corner = np.full((25, *size), -BIG, np.float32)
    corner[0] = 0
    rows = np.maximum(np.arange(size[0]) - 2, 0)
    cols = np.maximum(np.arange(size[1]) - 2, 0)
    np.testing.assert_array_equal(served.apply_kernel(image, corner), image[:, rows][:, :, cols])


def test_space_to_depth_layout_is_read_as_pixel_shuffle_lays_it_out():
    rng = np.random.default_rng(2)
    image = rng.standard_normal((3, 10, 14)).astype(np.float32)
    packed = rng.normal(0, 2, (51 * 4, 5, 7)).astype(np.float32)
    full = _pixel_shuffle(packed, 2)
    np.testing.assert_array_equal(_pixel_shuffle(packed, 2), torch.pixel_shuffle(_t(packed), 2)[0].numpy())
    for first in (0, 25):
        np.testing.assert_allclose(served.apply_kernel(image, packed, first=first, space_to_depth=2),
                                   served.apply_kernel(image, full, first=first), atol=1e-6)
    np.testing.assert_array_equal(served.weight(packed, 50, 2), served.weight(full, 50))


@pytest.mark.parametrize("size", [(6, 10), (2, 4), (8, 2)])
def test_resampling_agrees(size):
    rng = np.random.default_rng(1)
    image = rng.standard_normal((3, *size)).astype(np.float32)
    np.testing.assert_allclose(twin.upsample(_t(image))[0].numpy(), served.upsample(image), atol=TWIN_ATOL)
    np.testing.assert_allclose(twin.downsample(_t(image))[0].numpy(), served.downsample(image), atol=TWIN_ATOL)


@pytest.mark.parametrize(("size", "s"), [((20, 12), 1), ((4, 4), 2), ((28, 36), 2)])
def test_whole_filter_agrees(size, s):
    noisy, previous, fine, half, quarter = _case(*size, seed=size[0], s=s)
    ref = served.kernel_filter(noisy, previous, fine, half, quarter, space_to_depth=s)
    out = twin.kernel_filter(*(_t(a) for a in (noisy, previous, fine, half, quarter)), space_to_depth=s)
    np.testing.assert_allclose(out[0].numpy(), ref, atol=TWIN_ATOL)


def test_constants_stay_constant():
    """Any logits: kernels that sum to 1, weights in (0, 1); a constant noisy image and history give that constant."""
    _, _, fine, half, quarter = _case(16, 24, seed=5, s=2)
    flat = np.full((3, 16, 24), 0.7, np.float32)
    out = served.kernel_filter(flat, flat, fine * 10, half * 10, quarter * 10, space_to_depth=2)
    np.testing.assert_allclose(out, 0.7, atol=1e-6)


def test_alpha_selects_scales_and_history():
    """alpha_t -> 1: no history; alpha_t -> 0: the filtered history alone; coarse alphas -> 0: the fine scale."""
    noisy, previous, fine, half, quarter = _case(16, 16, seed=6)
    half[-1], quarter[-1] = -BIG, -BIG
    fine[-1] = BIG
    np.testing.assert_allclose(served.kernel_filter(noisy, previous, fine, half, quarter),
                               served.apply_kernel(noisy, fine), atol=1e-6)
    fine[-1] = -BIG
    np.testing.assert_allclose(served.kernel_filter(noisy, previous, fine, half, quarter),
                               served.apply_kernel(previous, fine, first=25), atol=1e-6)


def test_gradient_reaches_every_input():
    noisy, previous, fine, half, quarter = (_t(a).requires_grad_() for a in _case(8, 12, seed=7, s=2))
    twin.kernel_filter(noisy, previous, fine, half, quarter, space_to_depth=2).square().sum().backward()
    for tensor in (noisy, previous, fine, half, quarter):
        assert torch.isfinite(tensor.grad).all() and tensor.grad.abs().sum() > 0
