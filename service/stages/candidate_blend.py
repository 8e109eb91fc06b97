"""Which denoisers to run on a frame, and per tile the blend of them with the least estimated error.

Given K candidate denoisers and, per tile, the estimated covariance C of their relative errors
(`error_estimate.tile_covariance`), a blend sum_k w_k f_k with weights w >= 0 summing to 1 has the estimated
squared error w^T C w. Two denoisers whose errors are not fully correlated (a network's residual speckle,
a regression's blur) blend to less error than either alone.

Per tile, C is first made positive definite (its eigenvalues raised to at least EIGEN_FLOOR times the
largest: a noisy estimate can have a negative one, for which w^T C w would have no minimum), then the
minimum over the simplex is found exactly: it is the equality-constrained minimum w = C_U^-1 1 / (1^T
C_U^-1 1), of value 1 / (1^T C_U^-1 1), on some support U, the one of least value among those whose w is
non-negative (for K <= 4, 15 supports, each solved for every tile at once).

`choose` picks the set of candidates to run: a set costs the sum of its members' costs, and every frame
runs each member on the whole frame however few tiles it serves. Among the sets that cost at most `budget`
times the member of largest total weight (the one it serves most), those whose summed tile optimum is
within `tolerance` of the lowest (or within NEGLIGIBLE per tile: a black region) are near-best; the
previous set stays while it is near-best (a switch costs a temporal candidate its history), else the
cheapest near-best set is taken.
"""

from __future__ import annotations

import itertools
from functools import cache

import numpy as np

EIGEN_FLOOR = 1e-9  # per tile, eigenvalues of the covariance raised to at least this times the largest
TINY = 1e-300  # ... and above this, so that an all-zero tile still solves
NEGLIGIBLE = 1e-9  # relL2 per tile: sets whose totals differ by less than this per tile are equally good


@cache
def supports(count: int) -> tuple[tuple[int, ...], ...]:
    """Every non-empty subset of range(count), as sorted tuples, smallest first."""
    return tuple(s for r in range(1, count + 1) for s in itertools.combinations(range(count), r))


def positive_definite(covariance: np.ndarray) -> np.ndarray:
    """(K, K, th, tw) symmetric matrices per tile -> (th * tw, K, K) float64, each with its eigenvalues raised to
    at least EIGEN_FLOOR times its largest magnitude (and TINY)."""
    count = covariance.shape[0]
    matrices = np.moveaxis(covariance.reshape(count, count, -1), -1, 0).astype(np.float64)
    matrices = 0.5 * (matrices + np.swapaxes(matrices, 1, 2))
    values, vectors = np.linalg.eigh(matrices)
    floor = np.maximum(EIGEN_FLOOR * np.abs(values).max(axis=1, keepdims=True), TINY)
    return (vectors * np.maximum(values, floor)[:, None, :]) @ np.swapaxes(vectors, 1, 2)


def support_optima(matrices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For every support U of `supports(K)` and every tile, the minimum of w^T C w over weights >= 0 on U summing
    to 1 with an interior optimum (module docstring). matrices: (T, K, K) positive definite. Returns (values
    (U, T) float64, inf where the equality-constrained optimum has a negative weight; weights (U, T, K)
    float64, zero off U)."""
    tiles, count = matrices.shape[:2]
    subsets = supports(count)
    values = np.full((len(subsets), tiles), np.inf)
    weights = np.zeros((len(subsets), tiles, count))
    for u, subset in enumerate(subsets):
        index = np.array(subset)
        solved = np.linalg.solve(matrices[:, index][:, :, index], np.ones((tiles, len(index), 1)))[..., 0]
        total = solved.sum(axis=1)
        valid = (total > 0) & (solved >= 0).all(axis=1)
        values[u] = np.where(valid, 1.0 / np.where(valid, total, 1.0), np.inf)
        weights[u][:, index] = np.where(valid[:, None], solved / np.where(valid, total, 1.0)[:, None], 0.0)
    return values, weights


def choose(covariance: np.ndarray, costs: np.ndarray, tolerance: float, budget: float,
           previous: tuple[int, ...] | None = None) -> tuple[np.ndarray, tuple[int, ...]]:
    """The candidates to run and their per-tile blend (module docstring). covariance: (K, K, th, tw) finite
    estimated error covariance per tile; costs: (K,) the candidates' relative costs, > 0; tolerance >= 0;
    budget >= 1; previous: the last evaluation's members, or None. Returns (weights (K, th, tw) float64, >= 0,
    summing to 1 per tile, zero outside the members; the members, a sorted tuple of indices, each with weight
    somewhere)."""
    count, _, rows, cols = covariance.shape
    values, weights = support_optima(positive_definite(covariance))
    subsets = supports(count)
    options = {}  # members -> (summed tile optimum, cost, (T, K) weights)
    for members in subsets:
        inside = [u for u, s in enumerate(subsets) if set(s) <= set(members)]
        best = np.asarray(inside)[values[inside].argmin(axis=0)]  # (T,) the best support per tile
        tile_weights = weights[best, np.arange(best.size)]
        used = tuple(int(k) for k in np.flatnonzero(tile_weights.sum(axis=0) > 0))
        served_most = int(np.argmax(tile_weights.sum(axis=0)))
        cost = float(costs[list(used)].sum())
        if used == members and cost <= budget * costs[served_most] * (1 + 1e-9):
            options[members] = (float(values[best, np.arange(best.size)].sum()), cost, tile_weights)
    lowest = min(total for total, _, _ in options.values())
    slack = tolerance * abs(lowest) + NEGLIGIBLE * rows * cols
    near = {m: o for m, o in options.items() if o[0] <= lowest + slack}
    members = previous if previous in near else min(near, key=lambda m: (near[m][1], near[m][0]))
    return near[members][2].T.reshape(count, rows, cols), members
