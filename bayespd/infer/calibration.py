"""Statistics of calibration checks: SBC ranks, their chi-square uniformity test and its power,
and credible-interval coverage with its binomial tolerance (Talts et al. 2018, "Validating
Bayesian inference algorithms with simulation-based calibration").

If theta* ~ prior, y ~ p(y | theta*) and theta_1..theta_L are draws from the exact posterior
p(theta | y), the rank #{l : theta_l < theta*} is uniform on {0, ..., L}; an interval holding
posterior mass 1 - alpha covers theta* with probability exactly 1 - alpha.
"""
from __future__ import annotations

import math

import numpy as np
from scipy import stats


def rank(truth: float, draws) -> int:
    """#{l : draws_l < truth}, in {0, ..., len(draws)}."""
    return int(np.sum(np.asarray(draws) < truth))


def thin(draws, num: int) -> np.ndarray:
    """``num`` draws evenly spaced through a chain (fewer autocorrelated neighbours)."""
    draws = np.asarray(draws).reshape(-1)
    if len(draws) < num:
        raise ValueError(f"cannot thin {len(draws)} draws to {num}")
    return draws[np.linspace(0, len(draws) - 1, num).round().astype(int)]


def rank_counts(ranks, num_draws: int, bins: int) -> np.ndarray:
    """Counts of ranks in ``bins`` equal groups of the L + 1 possible values."""
    if (num_draws + 1) % bins:
        raise ValueError(f"L + 1 = {num_draws + 1} possible ranks do not split into {bins} equal bins")
    ranks = np.asarray(ranks)
    if ranks.min() < 0 or ranks.max() > num_draws:
        raise ValueError("ranks must lie in 0..L")
    return np.bincount(ranks * bins // (num_draws + 1), minlength=bins)


def chi2_uniformity(ranks, num_draws: int, bins: int) -> float:
    """p-value of Pearson's chi-square test that the binned ranks are uniform (bins - 1 df)."""
    counts = rank_counts(ranks, num_draws, bins)
    return float(stats.chisquare(counts).pvalue)


def chi2_power_overconfident(n: int, bins: int, scale: float, alpha: float = 0.01) -> float:
    """Power of the chi-square test at level ``alpha`` with ``n`` ranks against a posterior
    whose sd is ``scale`` times the true one (Gaussian; scale < 1: over-confident): its rank
    quantile is Phi(z / scale), z ~ N(0, 1); noncentral chi-square approximation."""
    edges = stats.norm.ppf(np.linspace(0, 1, bins + 1)) * scale
    probs = np.diff(stats.norm.cdf(edges))
    noncentrality = n * bins * np.sum((probs - 1 / bins) ** 2)
    critical = stats.chi2.ppf(1 - alpha, bins - 1)
    return float(stats.ncx2.sf(critical, bins - 1, noncentrality))


def central_interval(draws, mass: float = 0.9) -> tuple[float, float]:
    """Equal-tailed interval holding ``mass`` of the draws."""
    lo, hi = np.quantile(np.asarray(draws).reshape(-1), [(1 - mass) / 2, (1 + mass) / 2])
    return float(lo), float(hi)


def interval_score(draws, data, mass: float = 0.9) -> float:
    """Mean interval score of the equal-tailed intervals holding ``mass`` of ``draws`` (draws along
    axis 0, one interval per value of ``data``): (hi - lo) + 2 / alpha ((lo - x)_+ + (x - hi)_+),
    alpha = 1 - mass, a proper score of the interval (Gneiting & Raftery 2007 eq 43): lowest in
    expectation for the true quantiles, so it ranks predictive models by width and miss together."""
    alpha = 1 - mass
    lo, hi = np.quantile(np.asarray(draws), [alpha / 2, 1 - alpha / 2], axis=0)
    x = np.asarray(data)
    return float(((hi - lo) + 2 / alpha * (np.maximum(lo - x, 0) + np.maximum(x - hi, 0))).mean())


def coverage(covered) -> dict:
    """Observed coverage of n intervals and its binomial sd sqrt(c (1 - c) / n)."""
    covered = np.asarray(covered, dtype=bool)
    n = len(covered)
    rate = float(covered.mean())
    return {"n": n, "covered": int(covered.sum()), "rate": rate,
            "sd": math.sqrt(max(rate * (1 - rate), 1e-12) / n)}


def binomial_band(n: int, p: float, level: float = 0.99) -> tuple[float, float]:
    """Central ``level`` range of the observed rate of Binomial(n, p) / n."""
    lo, hi = stats.binom.interval(level, n, p)
    return float(lo / n), float(hi / n)


def probability_in(n: int, p: float, lo: float, hi: float) -> float:
    """P(lo <= X / n <= hi) for X ~ Binomial(n, p): the chance a correct method passes."""
    k_lo, k_hi = math.ceil(lo * n - 1e-9), math.floor(hi * n + 1e-9)
    return float(stats.binom.cdf(k_hi, n, p) - stats.binom.cdf(k_lo - 1, n, p))
