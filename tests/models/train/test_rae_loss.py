"""The recurrent autoencoder's loss (Chaitanya 2017 sec. 4.4): the paper's frame weights, the HFEN kernel,
and each term's analytic behaviour."""

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from models.train.rae_loss import (  # noqa: E402
    GAMMA,
    TONE_EPS,
    WEIGHTS,
    frame_weights,
    hfen,
    log_kernel,
    loss_weights,
    rae_loss,
)


def test_frame_weights_are_the_papers_for_seven_frames():
    paper = (0.011, 0.044, 0.135, 0.325, 0.607, 0.882, 1.0)
    np.testing.assert_allclose(frame_weights(7).numpy(), paper, atol=6e-4)


def test_log_kernel_sees_no_edge_in_a_constant_or_a_ramp():
    assert abs(log_kernel().sum().item()) < 1e-6
    ramp = torch.arange(32.0).view(1, 1, 1, 32).expand(1, 1, 32, 32)
    assert hfen(ramp)[..., 8:-8, 8:-8].abs().max() < 1e-4  # the Laplacian of a linear function is 0
    step = (torch.arange(32.0) >= 16).float().view(1, 1, 1, 32).expand(1, 1, 32, 32)
    assert hfen(step)[..., 16, 14:18].abs().max() > 0.05


def _window(n=1, t=3, h=16, w=16, seed=0):
    g = torch.Generator().manual_seed(seed)
    return torch.rand(n, t, 3, h, w, generator=g) * 4


def test_a_perfect_prediction_costs_nothing():
    target = _window()
    terms = rae_loss(torch.log1p(target), target)
    assert terms.total.item() < 1e-5


def test_spatial_term_is_the_mean_absolute_error_after_the_power():
    target = torch.zeros(1, 1, 3, 8, 8)
    pred = torch.log1p(torch.full_like(target, 1.0))  # predicts 1 everywhere
    terms = rae_loss(pred, target)
    expected = (1 + TONE_EPS) ** GAMMA - TONE_EPS**GAMMA
    assert terms.spatial.item() == pytest.approx(expected, rel=1e-5)
    assert terms.gradient.item() < 1e-6 and terms.temporal.item() == 0.0  # constant, one frame
    assert terms.total.item() == pytest.approx(WEIGHTS[0] * expected, rel=1e-5)


def test_temporal_term_ignores_a_steady_bias_and_sees_flicker():
    target = _window(t=4, seed=1)
    steady = ((target + TONE_EPS) ** GAMMA + 0.1) ** (1 / GAMMA) - TONE_EPS  # +0.1 in the loss's domain, every frame
    biased = rae_loss(torch.log1p(steady), target)
    assert biased.spatial.item() == pytest.approx(0.1, rel=1e-3)
    flicker = torch.stack([target[:, i] * (1.5 if i % 2 else 1.0) for i in range(4)], dim=1)
    flickering = rae_loss(torch.log1p(flicker), target)
    assert biased.temporal.item() < 1e-6
    assert flickering.temporal.item() > 0.05


def test_loss_is_finite_for_extreme_predictions():
    target = _window(seed=2)
    pred = torch.tensor([-1e30, 1e30, 3e38]).repeat(target.numel() // 3 + 1)[: target.numel()]
    pred = pred.view_as(target).requires_grad_()
    terms = rae_loss(pred, target)
    terms.total.backward()
    assert torch.isfinite(terms.total) and torch.isfinite(pred.grad).all()


@pytest.mark.parametrize("eps", [TONE_EPS, 1e-2])
def test_tone_eps_bounds_the_pull_of_a_black_pixel(eps):
    """A prediction just above a black target pulls with the power's slope at eps, 0.2 eps^-0.8 (times
    expm1's slope, 1 at 0): a larger eps weighs near-black pixels less."""
    target = torch.zeros(1, 1, 3, 8, 8)
    pred = torch.full((1, 1, 3, 8, 8), 1e-6, requires_grad=True)  # log1p radiance, ~1e-6
    rae_loss(pred, target, eps).spatial.backward()
    slope = pred.grad.abs().max().item() * pred.numel()  # the spatial term is a mean over the pixels
    assert slope == pytest.approx(GAMMA * eps ** (GAMMA - 1), rel=1e-3)


def test_loss_weights_are_the_papers_at_wt_0_1_and_keep_their_sum():
    assert loss_weights() == pytest.approx(WEIGHTS)
    for wt in (0.0, 0.3, 0.9):
        ws, wg, got = loss_weights(wt)
        assert got == wt and wg == WEIGHTS[1] and ws + wg + wt == pytest.approx(1.0) and ws >= 0
    for bad in (-0.1, 0.95):
        with pytest.raises(ValueError, match="temporal weight must be in"):
            loss_weights(bad)


def test_a_larger_temporal_weight_charges_flicker_more():
    """The total is ws Ls + wg Lg + wt Lt with the weights given: a prediction that flickers (its temporal term
    above its spatial one) costs more as wt grows; one that is off by a steady factor (temporal term below the
    spatial one) costs less, as ws shrinks."""
    target = _window(t=4, seed=3)
    flicker = torch.log1p(torch.stack([target[:, i] * (1.5 if i % 2 else 1.0) for i in range(4)], dim=1))
    steady = torch.log1p(target * 1.5)
    for pred, grows in ((flicker, True), (steady, False)):
        paper, heavy = rae_loss(pred, target), rae_loss(pred, target, weights=loss_weights(0.5))
        for terms, (ws, wg, wt) in ((paper, WEIGHTS), (heavy, loss_weights(0.5))):
            expected = ws * terms.spatial + wg * terms.gradient + wt * terms.temporal
            assert terms.total.item() == pytest.approx(expected.item(), rel=1e-6)
        assert (heavy.total > paper.total).item() == grows
