"""Coverage of credible intervals: the counter and its binomial tolerance (fast), and the
90 % intervals of NUTS on the calibration plate (slow)."""
import math
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy import stats

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "experiments"))
from bayespd.infer.calibration import binomial_band, central_interval, coverage, interval_score, probability_in  # noqa: E402


def test_coverage_counts_and_binomial_sd():
    c = coverage([True] * 9 + [False])
    assert (c["n"], c["covered"], c["rate"]) == (10, 9, 0.9)
    assert c["sd"] == pytest.approx(math.sqrt(0.09 / 10))


def test_probability_in_band_is_the_binomial_sum():
    direct = sum(stats.binom.pmf(k, 100, 0.9) for k in range(85, 96))
    assert probability_in(100, 0.9, 0.85, 0.95) == pytest.approx(direct, rel=1e-12)
    lo, hi = binomial_band(100, 0.9, 0.99)
    assert lo < 0.9 < hi and probability_in(100, 0.9, lo, hi) >= 0.99


@pytest.mark.parametrize("spread", [0.5, 1.0, 2.0])
def test_interval_score_is_its_gaussian_closed_form_lowest_at_the_true_spread(spread):
    """Forecast N(0, s^2) (20,000 draws), data N(0, 1) (200,000 values), 90 % intervals: E[score] =
    2 s z + (4 / alpha)(phi(s z) - s z (1 - Phi(s z))), z = Phi^-1(0.95), which is 4 phi(z) / alpha
    = 4.125 at s = 1 and 6.28, 6.59 at s = 0.5, 2 (the score is proper). The per-value score has sd
    <= 3.5, so the mean's sd <= 0.008; the draws' quantile error enters at second order. Tolerance 0.04."""
    rng = np.random.default_rng(3)
    draws = spread * rng.standard_normal((20000, 1))
    data = rng.standard_normal(200000)
    alpha, q = 0.1, spread * stats.norm.ppf(0.95)
    expected = 2 * q + 4 / alpha * (stats.norm.pdf(q) - q * stats.norm.sf(q))
    assert interval_score(draws, data) == pytest.approx(expected, abs=0.04)
    assert expected >= 4 * stats.norm.pdf(stats.norm.ppf(0.95)) / alpha - 1e-12


def test_exact_intervals_cover_at_the_nominal_rate():
    """Conjugate Gaussian (mu* ~ N(0, 1), 10 observations of N(mu*, 1)), 90 % intervals from
    400 exact posterior draws, 1000 replications: the observed rate lies in the 99.9 % binomial
    range of Binomial(1000, 0.9) (draw quantiles add a little spread; deterministic seed)."""
    rng = np.random.default_rng(11)
    covered = []
    for _ in range(1000):
        mu = rng.standard_normal()
        y = mu + rng.standard_normal(10)
        draws = y.sum() / 11 + 11**-0.5 * rng.standard_normal(400)
        lo, hi = central_interval(draws, 0.9)
        covered.append(lo <= mu <= hi)
    lo, hi = binomial_band(1000, 0.9, 0.999)
    assert lo <= coverage(covered)["rate"] <= hi


@pytest.mark.slow
def test_nuts_intervals_cover(tmp_path_factory):
    """50 replications on the calibration plate (truth from the prior; NUTS fits shared with
    test_sbc.py within a session): each parameter's coverage lies in the 99 % range of
    Binomial(50, 0.9) / 50, i.e. [0.78, 1.0] (sd sqrt(0.09 / 50) = 0.042)."""
    from bayespd.scenes import calibration_scene as cs

    n = 50
    records = cs.replications("nuts", n, root=tmp_path_factory.getbasetemp() / "calibration", log=None)
    lo, hi = binomial_band(n, 0.9, 0.99)
    for k in cs.names(False):
        rate = coverage([r.get("params", {}).get(k, {}).get("covered", False) for r in records])["rate"]
        assert lo <= rate <= hi, (k, rate)
