"""The error of a predicted crack-length history, its scale marginalised above the lengths' resolution.

The MD crack length L_t and a PD run's l_t differ by e_t = L_t - l_t, iid N(0, sigma^2) over the
fitted frames from the one before MD's first break (``first`` - 1: before it neither record has a
crack to err about, and a run that cracked early shows there as e = -l), with p(sigma) ~ 1/sigma on
sigma >= q: q is the resolution of a length (a PD tip moves by half a grid step h, so q = (h / 2) /
sqrt(12), the sd of rounding to it), below which no record resolves the error. With S = sum_t
e_t^2 over the n fitted frames, a = n / 2 and x = S / (2 q^2):

    p(e) = int_q^inf sigma^-1 (2 pi sigma^2)^(-n/2) exp(-S / (2 sigma^2)) d sigma
         = Gamma(a) P(a, x) / (2 (pi S)^a),

P the regularised lower incomplete gamma function; as S -> 0 it tends to (2 pi q^2)^-a / (2 a),
finite. A run that never cracks where MD's crack runs has e_t = L_t, a large S. Given e,
y = S / sigma^2 is chi^2_n truncated to y <= S / q^2 (sigma is Pareto, q U^(-1/n), when S = 0).
Forecast of frames from ``end`` on: sigma drawn given e, then L_t = l_t + e_t.
"""
from __future__ import annotations

import numpy as np
from scipy import special, stats

from bayespd.validate import positive


def length_resolution(h: float) -> float:
    """q = (h / 2) / sqrt(12): the sd of rounding a length to the half-step a PD tip moves by."""
    return positive("the grid step h", h, "pass the coarse grid's spacing") / 2 / np.sqrt(12.0)


def fitted_errors(md, run, first: int, end: int) -> np.ndarray:
    """e_t = L_t - l_t over frames ``first`` - 1 .. ``end`` - 1 (none if MD's crack starts after)."""
    md, run = np.asarray(md, float), np.asarray(run, float)
    if md.shape != run.shape or not 1 <= first < len(md):
        raise ValueError("pass MD's and the run's lengths per frame (same shape) and MD's first cracked frame >= 1")
    return md[first - 1:end] - run[first - 1:end]


def log_evidence(errors, q: float) -> float:
    """log p(e) of the module docstring for the errors (n,) and resolution ``q``; 0 for none."""
    e = np.asarray(errors, float).ravel()
    n, s = e.size, float(e @ e)
    if n == 0:
        return 0.0
    a, x = n / 2, s / (2 * positive("the resolution q", q) ** 2)
    return float(special.gammaln(a) - np.log(2) - a * np.log(np.pi) + _minus_a_log_s_plus_log_p(a, x, q))


def draw_scale(rng, errors, q: float, count: int) -> np.ndarray:
    """``count`` draws of sigma from p(sigma | e) (module docstring)."""
    e = np.asarray(errors, float).ravel()
    if e.size == 0:
        raise ValueError("no fitted frame with a crack: MD's crack starts after the fitted frames, so the "
                         "error's scale is unknown; fit more frames")
    n, s = e.size, float(e @ e)
    u = rng.uniform(size=count)
    if s == 0:
        return q * u ** (-1.0 / n)
    y = stats.chi2.ppf(u * stats.chi2.cdf(s / q**2, n), n)
    return np.sqrt(s / np.maximum(y, np.finfo(float).tiny))


def forecast(rng, md, run, first: int, end: int, q: float) -> np.ndarray:
    """One draw of L_t for frames ``end`` .. F - 1 given frames to end - 1 (module docstring)."""
    sigma = draw_scale(rng, fitted_errors(md, run, first, end), q, 1)[0]
    l = np.asarray(run, float)[end:]
    return l + sigma * rng.standard_normal(l.shape)


def _minus_a_log_s_plus_log_p(a: float, x: float, q: float) -> float:
    """-a log S + log P(a, x) with S = 2 q^2 x, finite as x -> 0: P(a, x) = x^a e^-x 1F1(1; a + 1; x) /
    Gamma(a + 1) (DLMF 8.5.1 and 13.6.5) where P underflows."""
    p = special.gammainc(a, x)
    if p > 1e-250:
        return -a * np.log(2 * q * q * x) + np.log(p)
    return -a * np.log(2 * q * q) - x + np.log(special.hyp1f1(1.0, a + 1, x)) - special.gammaln(a + 1)
