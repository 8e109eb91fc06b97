"""numpy/numba (inference) vs torch (training) spatiotemporal filter, odd sizes; and its gradient."""

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from models.train.filter import spatiotemporal_filter as filter_torch  # noqa: E402
from service.stages.spatiotemporal_filter import spatiotemporal_filter as filter_numpy  # noqa: E402

PARITY_ATOL = 2e-5  # polynomial exp (rel. error < 5e-6) against torch.exp, values O(1) in log1p space


def _case(height, width, seed):
    """Planes (C, H, W) as the numpy filter takes them; valid (H, W) bool."""
    rng = np.random.default_rng(seed)
    pa = rng.random((3, height, width), np.float32) * 3
    pb = pa + 0.3 * rng.standard_normal((3, height, width)).astype(np.float32)
    albedo = rng.random((3, height, width), np.float32)
    normal = rng.standard_normal((3, height, width)).astype(np.float32)
    precisions = np.exp(rng.uniform(-3, 5, (5, height, width))).astype(np.float32)
    alpha = rng.random((1, height, width), np.float32)
    params = np.concatenate([precisions, alpha])
    previous = rng.random((3, height, width), np.float32) * 3
    valid = rng.random((height, width)) > 0.4
    return pa, pb, albedo, normal, params, previous, valid


def _t(a):
    """Planes (C, H, W) or a mask (H, W) -> (1, C, H, W) float32 tensor."""
    return torch.from_numpy(np.ascontiguousarray(a.reshape(-1, *a.shape[-2:])[None], dtype=np.float32))


@pytest.mark.parametrize("size", [(13, 17), (5, 3), (1, 1), (16, 12)])
def test_numpy_and_torch_filters_agree(size):
    pa, pb, albedo, normal, params, previous, valid = _case(*size, seed=sum(size))
    ref = filter_numpy(pa, pb, albedo, normal, params, previous, valid)
    out = filter_torch(_t(pa), _t(pb), _t(albedo), _t(normal), _t(params), _t(previous), _t(valid))
    for name in ("color", "color_a", "color_b"):
        np.testing.assert_allclose(getattr(out, name)[0].numpy(), getattr(ref, name), atol=PARITY_ATOL, err_msg=name)
    np.testing.assert_allclose(out.weight_a[0, 0].numpy(), ref.weight_a, rtol=1e-5)
    np.testing.assert_allclose(out.weight_b[0, 0].numpy(), ref.weight_b, rtol=1e-5)


@pytest.mark.parametrize("min_alpha", [0.3, 1.0])
def test_both_filters_floor_alpha_alike(min_alpha):
    """The floor the served filter applies (crossreg's min_alpha) is the floor online training goes
    through: numpy with min_alpha = numpy on floored params = torch with min_alpha."""
    pa, pb, albedo, normal, params, previous, valid = _case(11, 9, seed=3)
    floored = params.copy()
    floored[-1] = np.maximum(floored[-1], np.float32(min_alpha))
    ref = filter_numpy(pa, pb, albedo, normal, floored, previous, valid)
    got = filter_numpy(pa, pb, albedo, normal, params, previous, valid, min_alpha=min_alpha)
    np.testing.assert_array_equal(got.color, ref.color)
    assert (params[-1] < min_alpha).any()  # the floor had work to do (and params were left as they were)
    assert not np.array_equal(ref.color, filter_numpy(pa, pb, albedo, normal, params, previous, valid).color)
    out = filter_torch(_t(pa), _t(pb), _t(albedo), _t(normal), _t(params), _t(previous), _t(valid),
                       min_alpha=min_alpha)
    np.testing.assert_allclose(out.color[0].numpy(), ref.color, atol=PARITY_ATOL)


@pytest.mark.parametrize("size", [(11, 9), (3, 2)])
def test_both_filters_floor_the_pilot_precisions_alike(size):
    """crossreg's pilot_bandwidth: numpy with it = numpy on params floored by `pilot_precision_floor` = torch
    with it; the floor raised some precisions and left the others."""
    from models.train.filter import pilot_precision_floor as floor_torch
    from service.stages.spatiotemporal_filter import pilot_precision_floor as floor_numpy

    pa, pb, albedo, normal, params, previous, valid = _case(*size, seed=4)
    bandwidth = 32.0
    floor = floor_numpy(pa, pb, bandwidth)
    np.testing.assert_allclose(floor_torch(_t(pa), _t(pb), bandwidth)[0, 0].numpy(), floor, rtol=1e-5)
    floored = params.copy()
    floored[:2] = np.maximum(floored[:2], floor)
    assert (floored[:2] > params[:2]).any() and (floored[:2] == params[:2]).any()
    ref = filter_numpy(pa, pb, albedo, normal, floored, previous, valid)
    got = filter_numpy(pa, pb, albedo, normal, params, previous, valid, pilot_bandwidth=bandwidth)
    np.testing.assert_array_equal(got.color, ref.color)
    out = filter_torch(_t(pa), _t(pb), _t(albedo), _t(normal), _t(params), _t(previous), _t(valid),
                       pilot_bandwidth=bandwidth)
    np.testing.assert_allclose(out.color[0].numpy(), ref.color, atol=PARITY_ATOL)


def test_without_history_torch_matches_numpy():
    pa, pb, albedo, normal, params, _, _ = _case(7, 9, seed=5)
    ref = filter_numpy(pa, pb, albedo, normal, params)
    out = filter_torch(_t(pa), _t(pb), _t(albedo), _t(normal), _t(params))
    np.testing.assert_allclose(out.color[0].numpy(), ref.color, atol=PARITY_ATOL)


def test_gradient_reaches_every_parameter_channel():
    pa, pb, albedo, normal, params, previous, valid = _case(6, 7, seed=9)
    p = _t(params).double().requires_grad_(True)
    args = [_t(a).double() for a in (pa, pb, albedo, normal)]
    out = filter_torch(*args, p, _t(previous).double(), _t(valid).double())
    out.color.sum().backward()
    per_channel = p.grad.abs().sum(dim=(0, 2, 3))
    assert (per_channel > 0).all()


def test_the_pilot_precision_floor_passes_gradient_only_above_it():
    """With pilot_bandwidth, kA and kB get no gradient where the floor holds and keep theirs above it."""
    from models.train.filter import pilot_precision_floor

    pa, pb, albedo, normal, params, previous, valid = _case(9, 8, seed=6)
    args = [_t(a).double() for a in (pa, pb, albedo, normal)]
    p = _t(params).double().requires_grad_(True)
    filter_torch(*args, p, _t(previous).double(), _t(valid).double(), pilot_bandwidth=32.0).color.sum().backward()
    floored = (p[:, :2] < pilot_precision_floor(args[0], args[1], 32.0)).detach()
    grad = p.grad[:, :2]
    assert floored.any() and (~floored).any()
    assert (grad[floored] == 0).all() and (grad[~floored] != 0).float().mean() > 0.9


def test_gradient_matches_finite_differences():
    pa, pb, albedo, normal, params, previous, valid = _case(3, 4, seed=10)
    args = [_t(a).double() for a in (pa, pb, albedo, normal)]

    def check(q):
        return filter_torch(*args, q, _t(previous).double(), _t(valid).double(), radius=2).color_a.sum()

    p = _t(params).double().requires_grad_(True)
    assert torch.autograd.gradcheck(check, (p,), eps=1e-6, atol=1e-4)
