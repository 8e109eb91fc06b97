"""Student's t-distribution in numpy: the critical values t_{1-alpha/2, nu} of the Welch test in
Sakai et al. 2024 (sec. 4.2, Algorithm 2), without scipy at serving time.

The CDF is exact: P(|T| > t) = I_x(nu/2, 1/2) with x = nu / (nu + t^2) (Abramowitz & Stegun 26.7.1
with 26.5.27), and the regularised incomplete beta I_x(a, b) is evaluated by its continued fraction
(A&S 26.5.8, modified Lentz; Numerical Recipes 3rd ed. sec. 6.4). The quantile inverts it by
bisection on x, so it is as accurate as float64 allows (tests hold it to scipy.stats.t.ppf).
The filter looks critical values up per pixel pair by nu = n_i + n_j - 2 in a table built once per
alpha: exact quantiles up to nu = EXACT_NU_MAX, the Cornish-Fisher expansion of A&S 26.7.5 (relative
error < 1e-9 there) beyond.
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np

EXACT_NU_MAX = 256  # degrees of freedom up to which the table holds exact (bisected) quantiles
_CF_MAX_ITER = 1000  # continued-fraction terms; converges in O(sqrt(max(a, b))) terms (NR sec. 6.4)
_CF_EPS = 1e-15  # relative convergence threshold of the continued fraction
_TINY = 1e-300  # Lentz's guard against division by zero
_BISECT_ITER = 1100  # bisection steps on x in (0, 1): enough to reach the smallest float64; stops early


def _betacf(a: np.ndarray, b: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Continued fraction of the incomplete beta function (A&S 26.5.8), modified Lentz; float64 arrays."""
    qab, qap, qam = a + b, a + 1.0, a - 1.0
    c = np.ones_like(x)
    d = 1.0 - qab * x / qap
    d = 1.0 / np.where(np.abs(d) < _TINY, _TINY, d)
    h = d.copy()
    for m in range(1, _CF_MAX_ITER + 1):
        m2 = 2.0 * m
        for aa in (m * (b - m) * x / ((qam + m2) * (a + m2)), -(a + m) * (qab + m) * x / ((a + m2) * (qap + m2))):
            d = 1.0 + aa * d
            d = 1.0 / np.where(np.abs(d) < _TINY, _TINY, d)
            c = 1.0 + aa / c
            c = np.where(np.abs(c) < _TINY, _TINY, c)
            delta = d * c
            h *= delta
        if np.all(np.abs(delta - 1.0) < _CF_EPS):
            break
    return h


def _lbeta(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """log B(a, b) elementwise (float64), via math.lgamma (numpy has no lgamma)."""
    lg = np.vectorize(math.lgamma, otypes=[np.float64])
    return lg(a) + lg(b) - lg(a + b)


def betainc(
    a: np.ndarray | float, b: np.ndarray | float, x: np.ndarray | float, lbeta: np.ndarray | None = None
) -> np.ndarray:
    """Regularised incomplete beta I_x(a, b) for a, b > 0 and x in [0, 1]; float64, broadcast shapes.

    lbeta: log B(a, b) when the caller has it already (the quantile's bisection calls this repeatedly).
    """
    a, b, x = (np.asarray(v, np.float64) for v in np.broadcast_arrays(a, b, x))
    x = np.clip(x, 0.0, 1.0)
    inner = (x > 0.0) & (x < 1.0)
    xs = np.where(inner, x, 0.5)
    front = np.exp(a * np.log(xs) + b * np.log1p(-xs) - (_lbeta(a, b) if lbeta is None else lbeta))
    direct = xs < (a + 1.0) / (a + b + 2.0)  # where the fraction converges fast; else use I_x(a,b) = 1 - I_1-x(b,a)
    aa, bb, xx = np.where(direct, a, b), np.where(direct, b, a), np.where(direct, xs, 1.0 - xs)
    cf = front * _betacf(aa, bb, xx)
    value = np.where(direct, cf / aa, 1.0 - cf / aa)
    return np.where(inner, value, x)  # I_0 = 0, I_1 = 1


def t_sf(t: np.ndarray | float, nu: np.ndarray | float) -> np.ndarray:
    """Upper tail P(T > t) of Student's t with `nu` > 0 degrees of freedom; float64, broadcast shapes."""
    t, nu = (np.asarray(v, np.float64) for v in np.broadcast_arrays(t, nu))
    two_sided = betainc(nu / 2.0, 0.5, nu / (nu + t * t))  # P(|T| > |t|), A&S 26.7.1
    return np.where(t >= 0.0, 0.5 * two_sided, 1.0 - 0.5 * two_sided)


def t_quantile(p: np.ndarray | float, nu: np.ndarray | float) -> np.ndarray:
    """Quantile t_{p, nu} of Student's t: P(T <= t) = p, for p in (0, 1) and nu > 0; float64.

    Solves I_x(nu/2, 1/2) = 2 min(p, 1 - p) for x = nu / (nu + t^2) by bisection (I_x increases with
    x). Near the median, where x is close to 1, it solves the mirrored I_y(1/2, nu/2) = |2p - 1| for
    y = 1 - x instead, so small t keep full relative precision.
    """
    p, nu = (np.asarray(v, np.float64) for v in np.broadcast_arrays(p, nu))
    if np.any((p <= 0.0) | (p >= 1.0)) or np.any(nu <= 0.0):
        raise ValueError("t_quantile needs 0 < p < 1 and nu > 0")
    tail = 2.0 * np.minimum(p, 1.0 - p)
    mirrored = tail > 0.5
    half = np.full_like(nu, 0.5)
    a = np.where(mirrored, half, nu / 2.0)
    b = np.where(mirrored, nu / 2.0, half)
    target = np.where(mirrored, np.abs(2.0 * p - 1.0), tail)
    lbeta = _lbeta(a, b)
    lo, hi = np.zeros_like(p), np.ones_like(p)
    for _ in range(_BISECT_ITER):
        mid = 0.5 * (lo + hi)
        if np.all((mid == lo) | (mid == hi)):  # no representable midpoint left anywhere
            break
        below = betainc(a, b, mid, lbeta) < target
        lo, hi = np.where(below, mid, lo), np.where(below, hi, mid)
    z = 0.5 * (lo + hi)  # x, or y = 1 - x where mirrored
    t = np.where(mirrored, np.sqrt(nu * z / (1.0 - z)), np.sqrt(nu * (1.0 - z) / z))
    return np.where(p >= 0.5, t, -t)


def normal_quantile(p: float) -> float:
    """Standard normal quantile z_p for 0 < p < 1 (float64), by bisection on math.erfc."""
    if not 0.0 < p < 1.0:
        raise ValueError(f"normal_quantile needs 0 < p < 1, got {p}")
    lo, hi = -40.0, 40.0
    while True:
        mid = 0.5 * (lo + hi)
        if mid in (lo, hi):
            return mid
        if 0.5 * math.erfc(-mid / math.sqrt(2.0)) < p:
            lo = mid
        else:
            hi = mid


def t_quantile_cornish_fisher(p: float, nu: np.ndarray) -> np.ndarray:
    """Cornish-Fisher expansion of t_{p, nu} in powers of 1/nu (A&S 26.7.5, terms to nu^-4); float64.

    Accurate for large nu (relative error < 1e-9 for nu > 256 at p = 0.9975); used beyond EXACT_NU_MAX.
    """
    x = normal_quantile(p)
    nu = np.asarray(nu, np.float64)
    g1 = (x**3 + x) / 4.0
    g2 = (5 * x**5 + 16 * x**3 + 3 * x) / 96.0
    g3 = (3 * x**7 + 19 * x**5 + 17 * x**3 - 15 * x) / 384.0
    g4 = (79 * x**9 + 776 * x**7 + 1482 * x**5 - 1920 * x**3 - 945 * x) / 92160.0
    return x + g1 / nu + g2 / nu**2 + g3 / nu**3 + g4 / nu**4


@lru_cache(maxsize=16)
def critical_value_table(alpha: float, nu_max: int) -> np.ndarray:
    """Two-sided critical values t_{1-alpha/2, nu} for nu = 0 .. nu_max (Sakai 2024 sec. 4.2).

    Returns (nu_max + 1,) float64, read-only; entry 0 (no degrees of freedom: no test possible) is +inf.
    Exact up to EXACT_NU_MAX, Cornish-Fisher beyond. Cached per (alpha, nu_max): callers round nu_max up.
    """
    if not 0.0 < alpha < 1.0:
        raise ValueError(f"alpha must be in (0, 1), got {alpha}")
    if nu_max < 0:
        raise ValueError(f"nu_max must be >= 0, got {nu_max}")
    p = 1.0 - alpha / 2.0
    exact = min(nu_max, EXACT_NU_MAX)
    table = np.empty(nu_max + 1, np.float64)
    table[0] = np.inf
    table[1 : exact + 1] = t_quantile(p, np.arange(1, exact + 1, dtype=np.float64))
    table[exact + 1 :] = t_quantile_cornish_fisher(p, np.arange(exact + 1, nu_max + 1, dtype=np.float64))
    table.flags.writeable = False
    return table
