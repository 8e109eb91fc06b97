"""The self-supervised loss (Choi 2024 eqs. 11-13) on tiny hand-computed cases, and one training step."""

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from models.nets.crossreg_unet import make_unet  # noqa: E402
from models.train.loss import LOSS_EPS, crossreg_loss, relative_l2  # noqa: E402
from models.train.step import forward, make_optimizer, samples_to_tensor, train_step  # noqa: E402
from service.layout import CROSSREG_SAMPLE, total_channels  # noqa: E402


def test_relative_l2_by_hand():
    x, y = torch.tensor([1.0, 0.0]), torch.tensor([0.5, 0.0])
    np.testing.assert_allclose(relative_l2(x, y).numpy(), [0.25 / (0.25 + LOSS_EPS), 0.0], rtol=1e-6)


def test_loss_crosses_the_labels_and_weighs_space_and_time_equally():
    shape = (1, 3, 1, 1)
    fa, fb = torch.full(shape, 1.0), torch.full(shape, 2.0)
    pa, pb = torch.full(shape, 2.0), torch.full(shape, 1.0)  # crossed labels match exactly: L_s = 0
    prev_a, prev_b = torch.full(shape, 2.0), torch.full(shape, 0.0)
    loss = crossreg_loss(fa, fb, pa, pb, prev_a, prev_b)
    # L_t = 1/2 (rel(fA=1, prevB=0) + rel(fB=2, prevA=2)) = 1/2 (1 / eps + 0); L = 1/2 (0 + L_t)
    np.testing.assert_allclose(float(loss), 0.5 * 0.5 * (1.0 / LOSS_EPS), rtol=1e-6)
    swapped = crossreg_loss(fa, fb, pb, pa, prev_a, prev_b)  # uncrossed labels would cost
    assert float(swapped) > float(loss)


def test_labels_carry_no_gradient():
    fa = torch.ones(1, 3, 2, 2, requires_grad=True)
    label = torch.full((1, 3, 2, 2), 3.0, requires_grad=True)
    crossreg_loss(fa, fa, label, label, label, label).backward()
    assert label.grad is None and fa.grad is not None


def test_one_adam_step_on_a_tiny_sample_lowers_its_loss():
    rng = np.random.default_rng(0)
    n = total_channels(CROSSREG_SAMPLE)
    sample = rng.random((12, 16, n), np.float32)
    sample[..., 15] = 1.0  # valid history
    batch = samples_to_tensor(sample)
    net = make_unet(seed=0)
    opt = make_optimizer(net)
    first = train_step(net, opt, batch)
    for _ in range(5):
        train_step(net, opt, batch)
    with torch.no_grad():
        after, _ = forward(net, batch)
    assert np.isfinite(first) and float(after) < first
