"""Nested Laplace: exact (up to quadrature) where theta is Gaussian given the scale, on the
common-offset model whose joint MAP collapses the scale (the md_dispersion problem in miniature);
every point searched from init and from its neighbours' modes."""

import math

import numpy as np
import pyro
import pyro.distributions as dist
import pytest
import torch

from bayespd.infer.nested import nested_laplace

N, SIGMA, PRIOR_MU, PRIOR_TAU = 6, 0.1, 10.0, 1.0
GRID = np.geomspace(0.005, 5.0, 49)


def offset(y):
    """mu ~ N(0, 10^2), tau ~ HalfNormal(1), y_i = mu + c + e_i with c ~ N(0, tau^2) common:
    y ~ N(mu 1, SIGMA^2 I + tau^2 1 1^T), so mu and c are confounded."""
    mu = pyro.sample("mu", dist.Normal(torch.tensor(0.0, dtype=torch.float64), PRIOR_MU))
    tau = pyro.sample("tau", dist.HalfNormal(torch.tensor(PRIOR_TAU, dtype=torch.float64)))
    cov = SIGMA**2 * torch.eye(N, dtype=torch.float64) + tau**2
    pyro.sample("y", dist.MultivariateNormal(mu.expand(N), cov), obs=y)


def exact(y, grid):
    """log p(log tau | y) (up to a constant) and mu's conditional mean and variance at each tau:
    mu integrated analytically (y ~ N(0, SIGMA^2 I + (tau^2 + 10^2) 1 1^T))."""
    y = y.numpy()
    one = np.ones(N)
    out = []
    for t in grid:
        marginal = SIGMA**2 * np.eye(N) + (t**2 + PRIOR_MU**2)
        logp = (-0.5 * y @ np.linalg.solve(marginal, y) - 0.5 * np.linalg.slogdet(marginal)[1]
                - t**2 / (2 * PRIOR_TAU**2) + math.log(t))
        precision_y = np.linalg.inv(SIGMA**2 * np.eye(N) + t**2)
        var = 1 / (one @ precision_y @ one + PRIOR_MU**-2)
        out.append((logp, var * one @ precision_y @ y, var))
    return np.array(out).T


@pytest.fixture(scope="module")
def case():
    y = 1.3 + 0.4 * torch.randn(1, dtype=torch.float64, generator=torch.Generator().manual_seed(0)) \
        + SIGMA * torch.randn(N, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    return y, nested_laplace(offset, {"y": y}, "tau", GRID, {"mu": 1.0, "tau": 0.3}, 20000, seed=0)


def test_log_marginal_of_the_scale_is_exact_where_theta_is_gaussian(case):
    """Given tau, mu is Gaussian, so the Laplace in mu is exact: the grid's log marginal matches
    the analytic one to the MAP search's tolerance."""
    y, out = case
    logp, _, _ = exact(y, GRID)
    np.testing.assert_allclose(out["log_marginal"], logp - logp.max(), atol=1e-6)
    assert max(out["end_weights"]) < 1e-3  # the weight in log tau falls like tau towards 0


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
    the first sweep finds it from init at every point, the second continues each to both
    neighbours (trust-region Newton from the mode) and finds nothing new, which ends the search."""
    _, out = case
    assert all(len(m) == 1 for m in out["mode_log_masses"])
    assert out["searches"] == [2] + [3] * (len(GRID) - 2) + [2]
    assert out["sweeps"] == 2


def test_grid_not_uniform_in_log_is_refused():
    with pytest.raises(ValueError, match="uniform in log"):
        nested_laplace(offset, {"y": torch.zeros(N, dtype=torch.float64)}, "tau", [0.1, 0.2, 0.5], {"mu": 0.0, "tau": 0.2}, 10)
