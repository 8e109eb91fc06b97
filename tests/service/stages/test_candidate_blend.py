"""The per-tile blend of candidates with the least estimated error, and the choice of the set to run."""

import numpy as np
import pytest

from service.stages.candidate_blend import choose, positive_definite, support_optima, supports

COSTS = np.array([1.0, 1.1, 4.0, 7.0])  # flr, bmfr, svgf, kpn (tiled.COSTS' ratios, rounded)


def _tiles(*matrices: np.ndarray) -> np.ndarray:
    """(K, K, 1, T) from T (K, K) matrices."""
    return np.stack(matrices, axis=-1)[:, :, None, :]


def test_supports_are_every_nonempty_subset():
    assert supports(2) == ((0,), (1,), (0, 1))
    assert len(supports(4)) == 15 and len(set(supports(4))) == 15


def test_two_independent_errors_blend_by_inverse_variance():
    # errors of variance 1 and 3, uncorrelated: w = (3/4, 1/4), w^T C w = 3/4, below either alone
    covariance = _tiles(np.diag([1.0, 3.0]))
    values, weights = support_optima(positive_definite(covariance))
    assert values[2, 0] == pytest.approx(0.75)
    np.testing.assert_allclose(weights[2, 0], [0.75, 0.25])
    np.testing.assert_allclose(values[:2, 0], [1.0, 3.0])  # each alone


def test_the_simplex_optimum_drops_a_candidate_whose_weight_would_be_negative():
    # strongly correlated errors, the second much larger: the unconstrained optimum puts a negative weight on it
    covariance = _tiles(np.array([[1.0, 1.5], [1.5, 4.0]]))
    values, _ = support_optima(positive_definite(covariance))
    assert values[2, 0] == np.inf  # w = C^-1 1 / ... has a negative component
    weights, members = choose(covariance, COSTS[:2], 0.0, 100.0)
    assert members == (0,)
    np.testing.assert_allclose(weights[:, 0, 0], [1.0, 0.0])


def test_a_covariance_with_a_negative_eigenvalue_is_projected():
    noisy = np.array([[0.01, 0.02], [0.02, 0.01]])  # eigenvalues 0.03 and -0.01: not a covariance
    projected = positive_definite(_tiles(noisy))[0]
    assert np.linalg.eigvalsh(projected).min() > 0
    np.testing.assert_allclose(projected, [[0.015, 0.015], [0.015, 0.015]], atol=1e-9)
    weights, _ = choose(_tiles(noisy), COSTS[:2], 0.0, 100.0)
    assert np.isfinite(weights).all() and weights.sum(axis=0) == pytest.approx(1.0)
    zero = choose(np.zeros((2, 2, 3, 4)), COSTS[:2], 0.05, 100.0)  # a black region: no error anywhere
    assert zero[1] == (0,) and np.isfinite(zero[0]).all()  # the cheapest, alone


def test_the_cheapest_near_best_set_runs_and_the_blend_is_per_tile():
    # tile 0: flr and kpn equally good and independent (blend halves the error); tile 1: kpn far better
    tile0 = np.diag([1.0, 9.0, 9.0, 1.0])
    tile1 = np.diag([4.0, 9.0, 9.0, 0.5])
    covariance = _tiles(tile0, tile1)
    weights, members = choose(covariance, COSTS, 0.0, 100.0)
    assert members == (0, 1, 2, 3)  # with no tolerance every candidate that lowers the total runs
    # summed tile optima (inverse-variance blends): all four 0.855, flr + bmfr + kpn 0.897, flr + kpn 0.944
    assert choose(covariance, COSTS, 0.02, 100.0)[1] == (0, 1, 2, 3)  # only all four within 2%
    weights, members = choose(covariance, COSTS, 0.15, 100.0)  # within 15%: flr + kpn, the cheapest of those
    assert members == (0, 3)
    np.testing.assert_allclose(weights[:, 0, 0], [0.5, 0, 0, 0.5])
    np.testing.assert_allclose(weights[:, 0, 1], [0.5 / 4.5, 0, 0, 4 / 4.5])


def test_the_budget_is_against_the_member_that_serves_most():
    covariance = _tiles(np.diag([1.0, 1.0]))  # two equal, independent: the blend is 0.5 with weights 1/2, 1/2
    costs = np.array([1.0, 7.0])
    assert choose(covariance, costs, 0.0, 100.0)[1] == (0, 1)
    assert choose(covariance, costs, 0.0, 1.25)[1] == (0,)  # equal weights, flr first: 8 > 1.25 x 1
    lopsided = _tiles(np.diag([4.0, 1.0]))  # kpn serves 80%: flr beside it costs 8 / 7
    assert choose(lopsided, costs, 0.0, 1.25)[1] == (0, 1)


def test_the_previous_set_stays_while_it_is_near_the_lowest():
    covariance = _tiles(np.diag([1.0, 1.02, 3.0]))
    assert choose(covariance, COSTS[:3], 0.05, 1.0)[1] == (0,)
    assert choose(covariance, COSTS[:3], 0.05, 1.0, previous=(1,))[1] == (1,)  # bmfr ran: it stays
    assert choose(covariance, COSTS[:3], 0.05, 1.0, previous=(2,))[1] == (0,)  # svgf is not near
    assert choose(covariance, COSTS[:3], 0.05, 1.0, previous=(0, 1))[1] == (0,)  # over the budget now: not kept


def test_weights_are_convex_per_tile_on_random_covariances():
    rng = np.random.default_rng(3)
    factors = rng.normal(size=(4, 6, 2, 5))
    covariance = np.einsum("iayx,jayx->ijyx", factors, factors) + rng.normal(0, 0.3, (4, 4, 2, 5))
    covariance = 0.5 * (covariance + covariance.transpose(1, 0, 2, 3))
    weights, members = choose(covariance, COSTS, 0.0, 100.0)
    assert (weights >= 0).all()
    np.testing.assert_allclose(weights.sum(axis=0), 1.0)
    assert set(np.flatnonzero(weights.reshape(4, -1).sum(axis=1))) == set(members)
    # with every candidate in the set, no weights on the simplex do better in any tile than the blend there
    matrices = positive_definite(covariance)
    blend = np.einsum("kt,tkj,jt->t", weights.reshape(4, -1), matrices, weights.reshape(4, -1))
    trials = rng.dirichlet(np.full(4, 0.5), size=4000)  # (N, K), many near the simplex's faces
    trials = np.concatenate([trials, np.eye(4)])
    values = np.einsum("nk,tkj,nj->tn", trials, matrices, trials)
    assert (blend <= values.min(axis=1) * (1 + 1e-9) + 1e-15).all()
