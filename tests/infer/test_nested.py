"""Nested Laplace: exact (up to quadrature) where theta is Gaussian given the grid sites, on the
common-offset model whose joint MAP collapses the scale (the md_dispersion problem in miniature),
with the offset's scale alone on a log grid and with the noise sd beside it on a uniform grid;
every point searched from init and from its neighbours' modes."""

import math
from functools import partial

import numpy as np
import pyro
import pyro.distributions as dist
import pytest
import torch
from scipy.special import logsumexp

from bayespd.infer.grid_axis import GridAxis
from bayespd.infer.nested import nested_laplace

N, SIGMA, PRIOR_MU, PRIOR_TAU = 6, 0.1, 10.0, 1.0
GRID = np.geomspace(0.005, 5.0, 49)


SIGMA_GRID = np.linspace(0.04, 0.4, 19)  # the noise sd on a uniform grid (prior Uniform(0, 1))


def offset(y, free_sigma=False):
    """mu ~ N(0, 10^2), tau ~ HalfNormal(1), y_i = mu + c + e_i with c ~ N(0, tau^2) common:
    y ~ N(mu 1, sigma^2 I + tau^2 1 1^T), so mu and c are confounded; sigma = SIGMA, or
    ``free_sigma``: sigma ~ Uniform(0, 1)."""
    mu = pyro.sample("mu", dist.Normal(torch.tensor(0.0, dtype=torch.float64), PRIOR_MU))
    tau = pyro.sample("tau", dist.HalfNormal(torch.tensor(PRIOR_TAU, dtype=torch.float64)))
    sigma = pyro.sample("sigma", dist.Uniform(torch.tensor(0.0, dtype=torch.float64), 1.0)) if free_sigma else SIGMA
    cov = sigma**2 * torch.eye(N, dtype=torch.float64) + tau**2
    pyro.sample("y", dist.MultivariateNormal(mu.expand(N), cov), obs=y)


def exact(y, grid, sigma=SIGMA):
    """log p(log tau | y) (up to a constant; given sigma) and mu's conditional mean and variance at
    each tau: mu integrated analytically (y ~ N(0, sigma^2 I + (tau^2 + 10^2) 1 1^T))."""
    y = y.numpy()
    one = np.ones(N)
    out = []
    for t in grid:
        marginal = sigma**2 * np.eye(N) + (t**2 + PRIOR_MU**2)
        logp = (-0.5 * y @ np.linalg.solve(marginal, y) - 0.5 * np.linalg.slogdet(marginal)[1]
                - t**2 / (2 * PRIOR_TAU**2) + math.log(t))
        precision_y = np.linalg.inv(sigma**2 * np.eye(N) + t**2)
        var = 1 / (one @ precision_y @ one + PRIOR_MU**-2)
        out.append((logp, var * one @ precision_y @ y, var))
    return np.array(out).T


@pytest.fixture(scope="module")
def case():
    y = 1.3 + 0.4 * torch.randn(1, dtype=torch.float64, generator=torch.Generator().manual_seed(0)) \
        + SIGMA * torch.randn(N, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    return y, nested_laplace(offset, {"y": y}, {"tau": GRID}, {"mu": 1.0, "tau": 0.3}, 20000, seed=0,
                             log=("tau",))


def test_log_marginal_of_the_scale_is_exact_where_theta_is_gaussian(case):
    """Given tau, mu is Gaussian, so the Laplace in mu is exact: the grid's log marginal matches
    the analytic one to the MAP search's tolerance."""
    y, out = case
    logp, _, _ = exact(y, GRID)
    np.testing.assert_allclose(out["log_marginal"], logp - logp.max(), atol=1e-6)
    assert max(out["marginals"]["tau"]["end_weights"]) < 1e-3  # the weight in log tau falls like tau towards 0


def test_mixture_moments_of_theta_match_the_exact_posterior(case):
    """mu's posterior mean and sd against a fine quadrature (4,000 points) of the exact
    mixture: the 49-point grid's quadrature error is < 1e-3 sd, and 20,000 draws give a Monte
    Carlo sd of sd / 141 for the mean (4.5 of those: two-sided 1e-5 false alarm) and about
    sd / 100 for the sd (tolerance 5 %)."""
    y, out = case
    fine = np.geomspace(GRID[0], GRID[-1], 4000)
    logp, m, v = exact(y, fine)
    w = np.exp(logp - logp.max())
    w /= w.sum()
    mean = w @ m
    sd = math.sqrt(w @ (v + m**2) - mean**2)
    draws = out["draws"]["mu"]
    assert abs(draws.mean() - mean) < 4.5 * sd / math.sqrt(len(draws))
    assert abs(draws.std() / sd - 1) < 0.05
    assert sd > 0.2  # the offset's spread (tau ~ 0.4): the collapsed joint MAP would give ~SIGMA / sqrt(N)


def test_every_point_is_searched_from_init_and_from_both_neighbours_modes(case):
    """Given tau the conditional is Gaussian, so every search at a point ends at its one mode:
    point 0's search from init finds it, its continuation to point 1 finds point 1's, and so on
    along the grid; every other search (from init, and each continuation back) ends in the mode
    already found, with the chord iteration: one Hessian per point."""
    _, out = case
    assert all(len(m) == 1 for m in out["mode_log_masses"])
    assert out["searches"] == [2] + [3] * (len(GRID) - 2) + [2]
    assert all(hessians >= 1 for _, hessians in out["evaluations"])


@pytest.fixture(scope="module")
def two_sites(case):
    y, _ = case
    model = partial(offset, free_sigma=True)
    return y, nested_laplace(model, {"y": y}, {"tau": GRID[::4], "sigma": SIGMA_GRID}, {"mu": 1.0, "tau": 0.3, "sigma": 0.1},
                             20000, seed=0, log=("tau",))


def test_a_second_site_on_a_uniform_grid_is_exact_where_theta_is_gaussian(two_sites):
    """Given (tau, sigma), mu is Gaussian: the product grid's log joint matches the analytic one
    (sigma's flat prior, integrated over sigma: no Jacobian; log tau's Jacobian tau) to the search's
    tolerance, and sigma's posterior mean and sd from the draws match a fine quadrature of the exact
    joint (sigma 4x finer, tau 4x finer: its error below 1e-4 sd) within 4.5 Monte Carlo sd of 20,000
    draws plus the coarse grid's own quadrature error (that of the same rule on the exact values)."""
    y, out = two_sites
    tau, sigma = GRID[::4], SIGMA_GRID
    logp = np.array([[exact(y, [t], s)[0][0] for s in sigma] for t in tau])
    np.testing.assert_allclose(np.reshape(out["log_marginal"], logp.shape), logp - logp.max(), atol=1e-6)
    assert out["points"][1] == (0, 1)  # C order: the last site fastest

    def moments(tau, sigma):  # sigma's mean and sd under the grid rule on the exact log joint
        logp = np.array([[exact(y, [t], s)[0][0] for s in sigma] for t in tau])
        axes = GridAxis("tau", tau, log=True), GridAxis("sigma", sigma)
        w = logp + np.apply_along_axis(axes[0].log_weights, 0, logp) + np.apply_along_axis(axes[1].log_weights, 1, logp)
        p = np.exp(logsumexp(w, axis=0) - logsumexp(w))
        return p @ sigma, math.sqrt(p @ sigma**2 - (p @ sigma) ** 2)

    fine = moments(np.geomspace(tau[0], tau[-1], 4 * len(tau) - 3), np.linspace(sigma[0], sigma[-1], 4 * len(sigma) - 3))
    coarse = moments(tau, sigma)
    draws = out["draws"]["sigma"]
    n = len(draws)
    assert abs(draws.mean() - fine[0]) < 4.5 * fine[1] / math.sqrt(n) + abs(coarse[0] - fine[0])
    assert abs(draws.std() - fine[1]) < 4.5 * fine[1] / math.sqrt(2 * n) + abs(coarse[1] - fine[1])


@pytest.mark.parametrize("grid, log, match", [([0.1, 0.2], ("tau",), "increasing"), ([0.3, 0.2, 0.1], (), "increasing"),
                                              ([0.0, 0.2, 0.5], ("tau",), "positive"), ([0.1, 0.2, 0.5], ("mu",), "only grid sites")])
def test_bad_grids_are_refused(grid, log, match):
    with pytest.raises(ValueError, match=match):
        nested_laplace(offset, {"y": torch.zeros(N, dtype=torch.float64)}, {"tau": grid}, {"mu": 0.0, "tau": 0.2}, 10, log=log)
