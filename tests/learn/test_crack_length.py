"""The crack-length error: its evidence and scale draws against direct integration over sigma, its
fitted frames and forecast."""
import numpy as np
import pytest
from scipy import integrate, stats

from bayespd.learn.crack_length import draw_scale, fitted_errors, forecast, length_resolution, log_evidence

Q = length_resolution(5.0)


def density(sigma, s, n):
    """The integrand of the module docstring's p(e): sigma^-1 N(e; 0, sigma^2)."""
    return sigma ** (-1.0 - n) * (2 * np.pi) ** (-n / 2) * np.exp(-s / (2 * sigma**2))


def by_quadrature(e):
    e = np.asarray(e, float)
    s, n = float(e @ e), e.size
    peak = max(np.sqrt(s / (n + 1)), Q)  # the integrand's mode on sigma >= q
    value = sum(integrate.quad(density, lo, hi, args=(s, n), epsabs=0, epsrel=1e-12, limit=200)[0]
                for lo, hi in ((Q, peak), (peak, 10 * peak), (10 * peak, np.inf)))
    return np.log(value)


@pytest.mark.parametrize("e", [np.zeros(20), np.r_[0.0, 2.3, -0.5, 1.6, 4.1, 0.8, -2.0],
                               np.r_[np.zeros(5), 1e-3, -2e-3], np.full(9, 15.0), [0.3]])
def test_log_evidence_matches_quadrature(e):
    assert log_evidence(e, Q) == pytest.approx(by_quadrature(e), abs=1e-9)


def test_exact_match_is_the_limit_of_small_errors():
    """S = 0 is the limit (2 pi q^2)^-a / (2 a), continuous in S."""
    n = 12
    limit = -n / 2 * np.log(2 * np.pi * Q**2) - np.log(n)
    assert log_evidence(np.zeros(n), Q) == pytest.approx(limit, abs=1e-12)
    assert log_evidence(np.full(n, 1e-7), Q) == pytest.approx(limit, abs=1e-9)


@pytest.mark.parametrize("e", [np.r_[0.0, 2.3, -0.5, 1.6, 4.1, 0.8, -2.0], np.zeros(10)])
def test_scale_draws_follow_the_posterior(e):
    """KS against the posterior CDF by quadrature, at 1 %: 4,000 draws detect a CDF off by 0.03
    anywhere (critical value 1.63 / sqrt(4000) = 0.026)."""
    e = np.asarray(e, float)
    s, n = float(e @ e), e.size
    draws = draw_scale(np.random.default_rng(3), e, Q, 4000)
    assert draws.min() >= Q
    total = np.exp(by_quadrature(e))

    def cdf(x):
        return np.array([integrate.quad(density, Q, v, args=(s, n), epsabs=0, epsrel=1e-10)[0] for v in np.atleast_1d(x)]) / total
    assert stats.kstest(draws, cdf).pvalue > 0.01


MD = np.r_[np.zeros(15), 2.3, 4.5, 6.6, 8.7, 10.8, 15.1, 17.2, 19.3]
EARLY = np.r_[np.zeros(13), 2.5, 2.5, 5.0, 5.0, 7.5, 10.0, 15.0, 15.0, 20.0, 20.0]


def test_fitted_frames_start_before_md_cracks():
    np.testing.assert_allclose(fitted_errors(MD, EARLY, 15, 21), MD[14:21] - EARLY[14:21])
    assert fitted_errors(MD, EARLY, 15, 10).size == 0 and log_evidence(fitted_errors(MD, EARLY, 15, 10), Q) == 0.0
    # a run without a crack explains a 15 A MD crack only by a large error: e^9 less evidence than
    # a run that cracked a frame early and a few A ahead
    assert log_evidence(fitted_errors(MD, np.zeros(23), 15, 21), Q) < log_evidence(fitted_errors(MD, EARLY, 15, 21), Q) - 9


def test_forecast_moments():
    """Mean l_t, sd sqrt(E[sigma^2 | e]) = sqrt(S / (n - 2)) (the untruncated posterior; q is far
    below it here): 5,000 draws give the mean to 4 sd / sqrt(5000) and the sd to 4 % (the scale
    mixture's sd has a standard error of about 2 % here; sqrt(S / n), the plug-in scale, is 15 %
    smaller)."""
    e = fitted_errors(MD, EARLY, 15, 21)
    sd = np.sqrt(e @ e / (e.size - 2))
    draws = np.stack([forecast(np.random.default_rng(k), MD, EARLY, 15, 21, Q) for k in range(5000)])
    np.testing.assert_allclose(draws.mean(0), EARLY[21:], atol=4 * sd / np.sqrt(5000))
    np.testing.assert_allclose(draws.std(0), sd, rtol=0.04)


def test_bad_input_is_named():
    with pytest.raises(ValueError, match="no fitted frame"):
        draw_scale(np.random.default_rng(0), [], Q, 1)
    with pytest.raises(ValueError, match="grid step"):
        length_resolution(0.0)
    with pytest.raises(ValueError, match="same shape"):
        fitted_errors(MD, EARLY[:-1], 15, 21)
