"""The reference-free error estimate from the half buffers: unbiased against known truth, calibrated variance."""

import numpy as np
import pytest

from service.metrics import REL_L2_EPS
from service.stages.error_estimate import (
    control_term,
    cross_tile_error,
    pixel_error,
    tile_covariance,
    tile_error,
    tile_sums,
)


def _halves(rng, mu, sigma):
    """Two independent unbiased halves of the pixel means `mu` with noise `sigma` (arrays (H, W, 3))."""
    return [(mu + sigma * rng.standard_normal(mu.shape)).astype(np.float32) for _ in range(2)]


def _scene(rng, height=96, width=128):
    y, x = np.mgrid[0:height, 0:width] / 40.0
    mu = np.stack([1.0 + 0.5 * np.sin(x), 0.5 + 0.4 * np.cos(y), 0.8 + 0.3 * np.sin(x + y)], axis=-1)
    sigma = 0.3 * mu  # relative noise, like a path tracer's
    return mu.astype(np.float32), sigma.astype(np.float32)


def _truth(out, mu, tile):
    """Per-tile true relative squared error of `out`, normalised as the estimate is here (by `mu`)."""
    scale = mu.astype(np.float64).mean(axis=-1, keepdims=True)
    err = (((out - mu) ** 2) / (scale * scale + REL_L2_EPS)).mean(axis=-1)
    sums, counts = tile_sums(err, tile)
    return sums / counts


@pytest.mark.parametrize("kind", ["biased", "identity", "perfect"])
def test_estimate_is_unbiased_and_its_variance_calibrated(kind):
    rng = np.random.default_rng(1)
    mu, sigma = _scene(rng)
    z = []
    for _ in range(20):
        a, b = _halves(rng, mu, sigma)
        out = {"biased": mu * 1.1 + 0.05, "identity": a, "perfect": mu}[kind].astype(np.float32)
        est = tile_error(out, a, b, mu, tile=32)
        truth = _truth(out, mu, 32)
        z.append((est.mean - truth) / np.sqrt(est.variance))
    z = np.array(z)
    assert abs(z.mean()) < 0.15  # unbiased: 20 frames x 12 tiles of z-scores average to ~0
    assert 0.6 < (z * z).mean() < 1.6  # the variance matches the scatter


@pytest.mark.parametrize("kind", ["biased", "identity", "perfect"])
def test_the_estimate_both_ways_is_unbiased_calibrated_and_steadier_than_one_way(kind):
    rng = np.random.default_rng(4)
    mu, sigma = _scene(rng)
    z, one_way, both_ways = [], [], []
    for _ in range(20):
        a, b = _halves(rng, mu, sigma)
        f = {"biased": lambda h: mu * 1.1 + 0.05, "identity": lambda h: h, "perfect": lambda h: mu}[kind]
        out_a, out_b = (np.asarray(f(h), np.float32) for h in (a, b))
        est = cross_tile_error(out_a, out_b, a, b, mu, tile=32)
        truth = 0.5 * (_truth(out_a, mu, 32) + _truth(out_b, mu, 32))
        z.append((est.mean - truth) / np.sqrt(est.variance))
        one_way.append(tile_error(out_a, a, b, mu, tile=32).mean - _truth(out_a, mu, 32))
        both_ways.append(est.mean - truth)
    z = np.array(z)
    assert abs(z.mean()) < 0.15
    assert 0.5 < (z * z).mean() < 1.6
    if kind == "perfect":  # the halves' own noise cancels: 2 sigma^4 -> sigma^4 per pixel (module docstring)
        assert np.var(both_ways) < 0.6 * np.var(one_way)


def test_estimate_ranks_a_better_denoiser_below_a_worse_one_in_every_tile():
    rng = np.random.default_rng(2)
    mu, sigma = _scene(rng)
    a, b = _halves(rng, mu, sigma)
    good = (mu * 1.02).astype(np.float32)
    bad = (mu * 1.25).astype(np.float32)
    assert (tile_error(good, a, b, mu).mean < tile_error(bad, a, b, mu).mean).all()


def test_tiles_cover_ragged_borders_and_the_pixel_estimate_is_per_pixel():
    values = np.arange(70 * 45, dtype=np.float64).reshape(70, 45)
    sums, counts = tile_sums(values, 32)
    assert sums.shape == counts.shape == (3, 2)
    assert counts.tolist() == [[32 * 32, 32 * 13], [32 * 32, 32 * 13], [6 * 32, 6 * 13]]
    assert sums.sum() == pytest.approx(values.sum())
    one = np.ones((5, 7, 3), np.float32)
    assert pixel_error(one, one, one, one).shape == (5, 7)
    assert np.all(pixel_error(one, one, one, one) == 0.0)
    with pytest.raises(ValueError, match="tile must be >= 1"):
        tile_error(one, one, one, one, tile=0)


def test_with_a_cap_fireflies_in_one_half_do_not_decide_the_ranking():
    rng = np.random.default_rng(3)
    mu, sigma = _scene(rng, 32, 32)
    a, b = _halves(rng, mu, 0.05 * mu)
    b[5, 7] = 1e3  # a firefly in half B
    good = mu.copy()
    brighter = (mu * 1.3).astype(np.float32)
    brighter[5, 7] = 50.0  # the worse candidate also spreads the firefly a little
    plain = [tile_error(x, a, b, mu, tile=32).mean[0, 0] for x in (good, brighter)]
    capped = [tile_error(x, a, b, mu, tile=32, cap=4.0).mean[0, 0] for x in (good, brighter)]
    assert plain[0] > plain[1]  # without the cap the firefly makes the worse candidate look better
    assert capped[0] < capped[1]


def _denoisers(rng, mu):
    """Three denoisers' outputs (per half: f(A), f(B)): a bias, independent noise, and a mix of the two, so
    that their errors are partly correlated."""
    bias = (0.05 * mu).astype(np.float32)
    def run(h):
        own = (0.1 * mu * rng.standard_normal(mu.shape)).astype(np.float32)
        return [mu + bias, mu + own, mu + 0.5 * bias + 0.5 * own]
    return run


@pytest.mark.parametrize("both", [False, True])
def test_a_blends_estimate_is_w_c_w_of_the_covariance(both):
    """The covariance's quadratic form in per-tile weights is exactly the estimate of the blended output (one
    way: `tile_error`; both ways: `cross_tile_error`), and its diagonal is each denoiser's."""
    rng = np.random.default_rng(5)
    mu, sigma = _scene(rng, 70, 90)
    a, b = _halves(rng, mu, sigma)
    run = _denoisers(rng, mu)
    outs_a, outs_b = run(a), run(b)
    cov = tile_covariance(outs_a, a, b, mu, 32, cap=4.0, outs_b=outs_b if both else None)
    assert cov.shape == (3, 3, 3, 3)
    np.testing.assert_array_equal(cov, cov.transpose(1, 0, 2, 3))
    weights = rng.dirichlet(np.ones(3), size=(3, 3)).transpose(2, 0, 1)  # (3, th, tw), summing to 1 per tile
    per_pixel = np.repeat(np.repeat(weights, 32, axis=1), 32, axis=2)[:, :70, :90, None]
    blend_a, blend_b = (sum(w * o for w, o in zip(per_pixel, outs, strict=True)) for outs in (outs_a, outs_b))
    if both:
        direct = cross_tile_error(blend_a, blend_b, a, b, mu, 32, cap=4.0).mean
        diagonal = [cross_tile_error(outs_a[k], outs_b[k], a, b, mu, 32, cap=4.0).mean for k in range(3)]
    else:
        direct = tile_error(blend_a, a, b, mu, 32, cap=4.0).mean
        diagonal = [tile_error(outs_a[k], a, b, mu, 32, cap=4.0).mean for k in range(3)]
    np.testing.assert_allclose(np.einsum("jyx,jkyx,kyx->yx", weights, cov, weights), direct, rtol=1e-9, atol=1e-12)
    for k in range(3):
        np.testing.assert_allclose(cov[k, k], diagonal[k], rtol=1e-9, atol=1e-12)


def test_the_covariance_is_unbiased_off_the_diagonal():
    """Averaged over frames, each off-diagonal entry matches the true covariance of the two denoisers' errors."""
    rng = np.random.default_rng(6)
    mu, sigma = _scene(rng, 64, 64)
    scale = mu.astype(np.float64).mean(axis=-1, keepdims=True)
    weight = 1.0 / (scale * scale + REL_L2_EPS)
    estimates, truths = [], []
    for _ in range(40):
        a, b = _halves(rng, mu, sigma)
        run = _denoisers(rng, mu)
        outs_a, outs_b = run(a), run(b)
        estimates.append(tile_covariance(outs_a, a, b, mu, 64, outs_b=outs_b)[:, :, 0, 0])
        errors = [[o.astype(np.float64) - mu for o in outs] for outs in (outs_a, outs_b)]
        truths.append(np.array([[np.mean([((e[j] * e[k]) * weight).mean() for e in errors]) for k in range(3)]
                                for j in range(3)]))
    estimate, truth = np.mean(estimates, axis=0), np.mean(truths, axis=0)
    spread = np.std(estimates, axis=0) / np.sqrt(len(estimates))
    assert (np.abs(estimate - truth) < 4 * spread + 1e-6).all(), (estimate - truth) / spread
    assert truth[0, 2] > 5 * spread[0, 2] and abs(truth[0, 1]) < truth[0, 2]  # a real correlation, measured


def _box(image, radius=3):
    """(H, W, 3) mean over the in-frame (2 radius + 1)^2 window: a crude denoiser of both halves' mean."""
    padded = np.pad(image.astype(np.float64), ((radius, radius), (radius, radius), (0, 0)), mode="edge")
    size = 2 * radius + 1
    windows = np.lib.stride_tricks.sliding_window_view(padded, (size, size), axis=(0, 1))
    return windows.mean(axis=(-2, -1)).astype(np.float32)


def test_the_control_variate_with_the_truth_is_unbiased_and_far_steadier():
    """m = mu (independent of the halves): E[(A - mu)(B - mu)] = 0, so subtracting it leaves the estimate
    unbiased, and it removes the halves' product term, the largest where the denoiser is good."""
    rng = np.random.default_rng(7)
    mu, sigma = _scene(rng)
    plain, controlled = [], []
    for _ in range(20):
        a, b = _halves(rng, mu, sigma)
        out_a, out_b = (mu * 1.05).astype(np.float32), (mu * 1.05).astype(np.float32)
        truth = _truth(out_a, mu, 32)
        plain.append(cross_tile_error(out_a, out_b, a, b, mu, tile=32).mean - truth)
        controlled.append(cross_tile_error(out_a, out_b, a, b, mu, tile=32, control=mu).mean - truth)
    controlled = np.array(controlled)
    assert abs(controlled.mean()) < 3 * controlled.std() / np.sqrt(controlled.size)
    assert np.var(controlled) < 0.1 * np.var(plain)


def test_the_control_variate_is_one_term_per_tile_for_every_denoiser_and_ranks_tiles_better():
    """With m a denoised mean of both halves (as auto's candidates' median is), the estimate moves by the term's
    tile mean, whatever the denoiser (it changes no choice), and it ranks the tiles of a denoiser whose
    error varies from tile to tile closer to the truth than without it (Spearman over 20 frames x 12 tiles)."""
    from bench.error_estimate import spearman

    rng = np.random.default_rng(8)
    mu, sigma = _scene(rng)
    bias = 1.0 + np.repeat(np.repeat(rng.uniform(0.0, 0.1, (3, 4)), 32, axis=0), 32, axis=1)[..., None]
    est_plain, est_ctrl, truths = [], [], []
    for _ in range(20):
        a, b = _halves(rng, mu, sigma)
        m = _box((a + b) / 2)
        outs = [(mu * bias).astype(np.float32), (mu * 1.02).astype(np.float32)]
        term = control_term(a, b, m, m)  # the same for both denoisers: their estimates move by its tile means
        shift = cross_tile_error(outs[1], outs[1], a, b, m, tile=32, control=m).mean
        np.testing.assert_allclose(cross_tile_error(outs[1], outs[1], a, b, m, tile=32).mean - shift,
                                   tile_sums(term, 32)[0] / tile_sums(np.ones_like(term), 32)[0], rtol=1e-9)
        est_plain.append(cross_tile_error(outs[0], outs[0], a, b, m, tile=32).mean)
        est_ctrl.append(cross_tile_error(outs[0], outs[0], a, b, m, tile=32, control=m).mean)
        truths.append(_truth(outs[0], mu, 32))
    truths = np.ravel(truths)
    assert spearman(np.ravel(est_ctrl), truths) > spearman(np.ravel(est_plain), truths) + 0.1  # 0.89 against 0.73
