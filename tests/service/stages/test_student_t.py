import numpy as np
import pytest
from scipy import stats

from service.stages.student_t import EXACT_NU_MAX, critical_value_table, t_quantile, t_sf


@pytest.mark.parametrize("alpha", [0.005, 0.05, 0.2])
def test_critical_values_match_scipy(alpha):
    table = critical_value_table(alpha, 2048)
    nu = np.arange(1, 2049)
    np.testing.assert_allclose(table[1:], stats.t.ppf(1 - alpha / 2, nu), rtol=1e-9)
    assert table[0] == np.inf and not table.flags.writeable


def test_exact_part_is_exact_and_cornish_fisher_part_is_close():
    table = critical_value_table(0.005, 4096)
    ref = stats.t.ppf(1 - 0.0025, np.arange(1, 4097))
    err = np.abs(table[1:] / ref - 1)
    assert err[:EXACT_NU_MAX].max() < 1e-12 and err[EXACT_NU_MAX:].max() < 1e-9


def test_quantile_and_tail_match_scipy_anywhere():
    rng = np.random.default_rng(0)
    p = rng.uniform(1e-6, 1 - 1e-6, 200)
    nu = rng.uniform(0.5, 300, 200)
    np.testing.assert_allclose(t_quantile(p, nu), stats.t.ppf(p, nu), rtol=1e-8, atol=1e-12)
    t = rng.normal(0, 5, 200)
    np.testing.assert_allclose(t_sf(t, nu), stats.t.sf(t, nu), rtol=1e-9, atol=1e-15)
    assert t_quantile(0.5 + 1e-9, 3.0) == pytest.approx(stats.t.ppf(0.5 + 1e-9, 3.0), rel=1e-6)


def test_bad_arguments_are_refused():
    with pytest.raises(ValueError, match="alpha"):
        critical_value_table(0.0, 10)
    with pytest.raises(ValueError, match="0 < p < 1"):
        t_quantile(1.0, 3)
