"""The kernel-predicting network (models/nets/kpn.py): output shapes at the three scales, normalised kernels
and weights, the untrained box filter, and its training loop's recurrence (models/train/kpn.py)."""

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from models.nets.kpn import KpnConfig, make_kpn  # noqa: E402
from models.train.kpn import filter_window, warped_previous  # noqa: E402
from tests.export.test_kpn_export import random_heads  # noqa: E402


def test_outputs_are_logits_at_three_scales():
    net = random_heads(make_kpn(KpnConfig(widths=(6, 8, 10, 12)), seed=1))
    assert net.alignment == 16
    fine, half, quarter = net(torch.randn(2, 11, 32, 48))
    assert fine.shape == (2, 51 * 4, 16, 24) and half.shape == (2, 26, 16, 24) and quarter.shape == (2, 26, 8, 12)
    for logits in (fine, half, quarter):
        assert logits.std(dim=(2, 3)).min() > 0  # per pixel, not constant


def test_untrained_network_predicts_box_filters_with_even_weights():
    """Zero heads: every logit 0, so softmax kernels of 1/25 and sigmoid weights of 1/2 in the filter."""
    for logits in make_kpn(seed=0)(torch.randn(1, 11, 16, 16)):
        assert (logits == 0).all()


def test_widths_are_checked():
    with pytest.raises(ValueError, match="three or more"):
        KpnConfig(widths=(4, 8))


def test_constant_radiance_stays_constant_through_a_window():
    """Any kernels (sum 1) and weights in (0, 1), any motion: a constant radiance in every frame comes out as
    that constant (the warp's fallback is the noisy radiance, itself the constant)."""
    net = random_heads(make_kpn(KpnConfig(widths=(6, 8, 10)), seed=2))
    noisy = torch.full((1, 3, 3, 21, 19), 2.5)
    guides = torch.randn(1, 3, 5, 21, 19)
    motion = torch.randn(1, 3, 2, 21, 19) * 4
    with torch.no_grad():
        out = filter_window(net, noisy, guides, motion)
    torch.testing.assert_close(out, torch.full_like(out, float(np.log1p(2.5))))


def test_later_frames_depend_on_earlier_ones_and_the_first_does_not():
    net = random_heads(make_kpn(KpnConfig(widths=(6, 8, 10)), seed=3))
    gen = torch.Generator().manual_seed(0)
    noisy = torch.rand(1, 3, 3, 16, 16, generator=gen)
    guides = torch.randn(1, 3, 5, 16, 16, generator=gen)
    motion = torch.zeros(1, 3, 2, 16, 16)
    changed = noisy.clone()
    changed[:, 0] *= 3
    with torch.no_grad():
        a, b = filter_window(net, noisy, guides, motion), filter_window(net, changed, guides, motion)
        second = filter_window(net, noisy[:, 1:], guides[:, 1:], motion[:, 1:])
    assert (a[:, 1] - b[:, 1]).abs().max() > 1e-3  # frame 1 saw frame 0's output
    torch.testing.assert_close(second[:, 0], filter_window(net, noisy[:, 1:2], guides[:, 1:2], motion[:, 1:2])[:, 0])


def test_warp_falls_back_to_the_noisy_radiance_off_screen():
    previous = torch.arange(12.0).view(1, 1, 3, 4).expand(1, 3, 3, 4)
    noisy = torch.full((1, 3, 3, 4), -1.0)
    motion = torch.zeros(1, 2, 3, 4)
    motion[:, 0] = 1.0  # each pixel was one to the right: the last column came from off screen
    out = warped_previous(previous, motion, noisy)
    torch.testing.assert_close(out[..., :-1], previous[..., 1:])
    assert (out[..., -1] == -1).all()
