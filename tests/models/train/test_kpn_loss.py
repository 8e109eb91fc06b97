"""The kpn loss (Zeng 2023 eqs. 5-6): occlusion masks by hand, zero for a perfect prediction, the occlusion
term only where the masks are and only when switched on."""

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from models.train.kpn_loss import MASK_WEIGHTS, kpn_loss, occlusion_weights  # noqa: E402


def test_occlusion_weights_by_hand():
    """One pixel occluded at frame 1 only (|dual - motion| = 0.6 > 0.5 px); another at 0.4 px (not)."""
    motion = torch.zeros(1, 4, 2, 2, 2)
    dual = motion.clone()
    dual[0, 1, 0, 0, 0] = 0.6
    dual[0, 2, 1, 1, 1] = 0.4
    w = occlusion_weights(motion, dual)[0, :, 0, 0, 0]
    # frame 0: none; 1: M^0 and, frame -1 lying outside the window, M^0 again for M^2; 2: M^1; 3: M^2
    w0, w1, w2 = MASK_WEIGHTS
    torch.testing.assert_close(w, torch.tensor([0.0, w0 + w2, w1, w2]))
    assert (occlusion_weights(motion, dual)[0, :, 0, 1, 1] == 0).all()
    dual[0, 0, 0, 0, 0] = 1.0  # occluded at the window's first frame: it stands in for frames -1 and -2
    assert float(occlusion_weights(motion, dual)[0, 0, 0, 0, 0]) == pytest.approx(sum(MASK_WEIGHTS))


def test_loss_terms():
    gen = torch.Generator().manual_seed(0)
    target = torch.rand(2, 3, 3, 8, 8, generator=gen)
    perfect = torch.log1p(target)
    weights = torch.zeros(2, 3, 1, 8, 8)
    zero = kpn_loss(perfect, target, weights, occlusion=True)
    assert float(zero.total) == pytest.approx(0.0, abs=1e-6)
    wrong = perfect.clone()
    wrong[..., :4, :] += 0.5
    off = kpn_loss(wrong, target, weights, occlusion=True)
    assert float(off.occlusion) == 0 and float(off.spatial) > 0 and float(off.gradient) == 0
    weights[..., :4, :] = 1.0  # the wrong half is occluded
    on = kpn_loss(wrong, target, weights, occlusion=True)
    np.testing.assert_allclose(float(on.occlusion), float(on.spatial), rtol=1e-5)  # the error is all masked
    np.testing.assert_allclose(float(on.total), float(on.spatial + on.temporal + on.occlusion), rtol=1e-6)
    later = kpn_loss(wrong, target, weights, occlusion=False)
    np.testing.assert_allclose(float(later.total), float(on.spatial + on.temporal), rtol=1e-6)
