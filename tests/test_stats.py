"""Tail probabilities and quantiles of dfxcorr.stats against scipy.stats, and their logs where the tails underflow."""
import numpy as np
import pytest
from scipy import special, stats

from dfxcorr import stats as S


@pytest.mark.parametrize("statistic,dof", [(0.5, 1), (5.0, 4), (40.0, 10), (900.0, 700), (1e3, 4)])
def test_chi2_tail_is_scipys(statistic, dof):
    p, log_p = S.chi2_tail(statistic, dof)
    assert p == pytest.approx(stats.chi2.sf(statistic, dof), rel=1e-12)
    assert log_p == pytest.approx(stats.chi2.logsf(statistic, dof), rel=1e-12)


def test_the_log_tails_continue_where_the_probabilities_underflow():
    # scipy's logsf is -inf out there: two statistics of dof 4 a few hundred apart must still be ordered
    assert stats.chi2.logsf(9e4, 4) == -np.inf
    a, b = S.chi2_tail(89660.0, 4)[1], S.chi2_tail(90310.0, 4)[1]
    assert np.isfinite(a) and np.isfinite(b) and b < a
    # the asymptotic tail of a chi-square of dof 4: Q(2, z) = (1 + z) e^-z, z = x / 2
    z = 45155.0
    assert b == pytest.approx(np.log1p(z) - z, rel=1e-13)
    # an F tail whose probability underflows, against its closed form for 2 numerator dof:
    # P(F > f) = (1 + 2 f / d2)^(-d2 / 2)
    group = np.repeat([0, 1, 2], 3000)
    F, d1, d2, log_p, _, _ = S.one_way_anova(3.0 * group + np.tile([-1.0, 1.0], 4500), np.ones(9000), group, 3)
    assert d1 == 2 and stats.f.sf(F, d1, d2) == 0.0
    assert log_p == pytest.approx(-d2 / 2 * np.log1p(2 * F / d2), rel=1e-12)


def test_the_continued_fractions_match_the_direct_functions(monkeypatch):
    # forced onto the continued-fraction branch where the direct values are representable
    monkeypatch.setattr(S, "_TINY", 2.0)
    for a, z in [(2.0, 10.0), (0.5, 30.0), (50.0, 200.0), (1.5, 3.0), (2e3, 2.5e3)]:
        assert S.log_gamma_q(a, z) == pytest.approx(np.log(special.gammaincc(a, z)), rel=1e-12)
    for a, b, x in [(500.0, 1.5, 0.3), (5.0, 2.0, 0.1), (0.5, 0.5, 0.01), (99.0, 1.5, 0.6)]:
        assert S.log_beta_i(a, b, x) == pytest.approx(np.log(special.betainc(a, b, x)), rel=1e-12)


def test_f_tail_and_binomial_tail_are_scipys():
    rng = np.random.default_rng(3)
    group = np.repeat(np.arange(4), 50)
    y = rng.normal(size=200) + 0.4 * group
    F, d1, d2, log_p, _, _ = S.one_way_anova(y, np.ones(200), group, 4)
    assert (d1, d2) == (3, 196)
    assert log_p == pytest.approx(stats.f.logsf(F, d1, d2), rel=1e-12)
    for k, n, p in [(1, 500, 1e-4), (10, 1000, 1e-3), (200, 10_000, 1e-3), (3, 3, 0.5)]:
        assert S.binomial_log_tail(k, n, p) == pytest.approx(stats.binom.logsf(k - 1, n, p), rel=1e-12)
    assert S.binomial_log_tail(0, 10, 0.1) == 0.0 and S.binomial_log_tail(11, 10, 0.1) == -np.inf


def test_quantiles_and_normal_tail_are_scipys():
    dofs = np.array([1, 5, 30, 4000])
    assert np.allclose(S.chi2_quantile(1e-4, dofs, upper=True), stats.chi2.isf(1e-4, dofs), rtol=1e-12)
    assert float(S.chi2_quantile(1e-6, 10)) == pytest.approx(stats.chi2.ppf(1e-6, 10), rel=1e-12)
    z = np.array([0.0, 1.5, 12.0, 60.0])
    assert np.allclose(S.normal_log_tail(z), stats.norm.logsf(z), rtol=1e-12)


def test_elementwise_log_tails_are_scipys_and_continue_beyond_it():
    x = np.array([0.5, 3.0, 40.0, 180.0, 900.0, 9e4])
    k = np.array([1, 4, 30, 30, 60, 4])
    out = S.chi2_log_tails(x, k)
    np.testing.assert_allclose(out[:5], stats.chi2.logsf(x[:5], k[:5]), rtol=1e-10)
    # the last underflows in scipy; Q(2, z) = (1 + z) e^-z
    assert out[5] == pytest.approx(np.log1p(4.5e4) - 4.5e4, rel=1e-13)
    assert out[5] == pytest.approx(S.chi2_tail(9e4, 4)[1], rel=1e-15)


def test_digitize_is_numpys_for_a_few_edges():
    rng = np.random.default_rng(5)
    edges = np.sort(rng.uniform(-2, 2, 12))
    # values on the edges, between and beyond them, and NaN
    value = np.concatenate([edges, rng.uniform(-3, 3, 500), [np.nan, -np.inf, np.inf]]).reshape(-1, 5)
    got = S.digitize(value, edges)
    assert got.shape == value.shape
    np.testing.assert_array_equal(got, np.digitize(value, edges))
    with pytest.raises(ValueError, match="126"):
        S.digitize(value, np.arange(127.0))
