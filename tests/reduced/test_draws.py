"""bayespd/reduced/draws.py: prior draws are reproducible, posterior and Gaussian draws reproduce
their moments on the unconstrained space within sampling error, inflation scales the covariance,
and bad requests are refused."""
import math

import pytest
import torch

from bayespd.infer.datatree import build_tree
from bayespd.reduced.draws import gaussian_draws, posterior_draws, prior_draws


def test_prior_draws_are_reproducible_and_named():
    priors = {"K": torch.distributions.LogNormal(0.0, 0.3), "G": torch.distributions.LogNormal(0.0, 0.3)}
    a, b = prior_draws(priors, 5, seed=3, names=["K"]), prior_draws(priors, 5, seed=3, names=["K"])
    assert [list(p) for p in a] == [["K"]] * 5 and all(float(p["K"]) == float(q["K"]) for p, q in zip(a, b))
    with pytest.raises(ValueError, match="no prior for"):
        prior_draws(priors, 5, seed=3, names=["delta"])


BOUNDS = {"delta": (2.0, 6.0)}
C0 = torch.tensor([[0.04, 0.01, -0.02], [0.01, 0.09, 0.0], [-0.02, 0.0, 0.25]], dtype=torch.float64)
Z0 = torch.tensor([8.0, 7.0, 0.3], dtype=torch.float64)  # log K, log G, logit((delta - 2) / 4)


def unconstrained(draws):
    """(n, 3) log K, log G, logit((delta - 2) / 4) of parameter dicts."""
    x = torch.tensor([[float(p[k]) for k in ("K", "G", "delta")] for p in draws], dtype=torch.float64)
    return torch.stack([x[:, 0].log(), x[:, 1].log(), torch.logit((x[:, 2] - 2) / 4)], 1)


def fitted_tree(num_chains=2, num_draws=500, seed=7):
    """A fit's DataTree whose draws are Gaussian with mean Z0 and covariance C0 on the unconstrained space."""
    g = torch.Generator().manual_seed(seed)
    z = Z0 + torch.randn(num_chains * num_draws, 3, generator=g, dtype=torch.float64) @ torch.linalg.cholesky(C0).T
    x = {"K": z[:, 0].exp(), "G": z[:, 1].exp(), "delta": 2 + 4 * torch.sigmoid(z[:, 2]),
         "sigma": 0.1 * torch.randn(len(z), generator=g, dtype=torch.float64).exp(), "u": torch.zeros(len(z), 4)}
    return build_tree({"posterior": {k: v.reshape(num_chains, num_draws, *v.shape[1:]).numpy() for k, v in x.items()}}), z


def test_posterior_draws_reproduce_the_trees_moments_within_sampling_error():
    """On the unconstrained space the n draws' mean is within 4.5 standard errors sqrt(S_ii / n) of
    the tree's sample mean m, their covariance within 4.5 sds sqrt((S_ij^2 + S_ii S_jj) / (n - 1)) of the tree's
    sample covariance S (the sd of a sample covariance); delta stays inside its bounds."""
    tree, z = fitted_tree()
    n = 4000
    draws = posterior_draws(tree, n, seed=3, names=["K", "G", "delta"], bounds=BOUNDS)
    assert len(draws) == n and list(draws[0]) == ["K", "G", "delta"] and draws[0]["K"].dtype == torch.float64
    m, S = z.mean(0), torch.cov(z.T)
    w = unconstrained(draws)
    assert float(((w.mean(0) - m) / (S.diagonal() / n).sqrt()).abs().max()) < 4.5
    se = ((S.square() + S.diagonal()[:, None] * S.diagonal()[None, :]) / (n - 1)).sqrt()
    assert float(((torch.cov(w.T) - S) / se).abs().max()) < 4.5
    assert all(2.0 < float(p["delta"]) < 6.0 for p in draws)
    again = posterior_draws(tree, n, seed=3, names=["K", "G", "delta"], bounds=BOUNDS)
    assert all(float(p["G"]) == float(q["G"]) for p, q in zip(again, draws))  # reproducible from the seed


def test_inflation_scales_the_covariance_by_its_factor():
    """The same seed draws the same standard normals: with inflate = 4 each unconstrained draw lies
    twice as far from the mean (to rounding), so the covariance is exactly 4 x; the scalar
    parameters are the default names (u, a vector, is left out); a mapping of draws works as a tree."""
    tree, z = fitted_tree()
    one = unconstrained(posterior_draws(tree, 50, seed=1, names=["K", "G", "delta"], bounds=BOUNDS))
    four = unconstrained(posterior_draws(tree, 50, seed=1, names=["K", "G", "delta"], inflate=4.0, bounds=BOUNDS))
    assert torch.allclose(four - z.mean(0), 2 * (one - z.mean(0)), rtol=0, atol=1e-9)
    names = list(posterior_draws(tree, 1, seed=1, bounds=BOUNDS)[0])
    assert sorted(names) == ["G", "K", "delta", "sigma"]
    flat = {k: tree["posterior"][k].values.reshape(-1) for k in ("K", "G", "delta")}
    assert torch.allclose(unconstrained(posterior_draws(flat, 50, seed=1, bounds=BOUNDS)), one, rtol=0, atol=1e-12)


def test_gaussian_draws_from_a_mean_and_covariance():
    """A Laplace-style centre (natural units) and unconstrained covariance: the draws' unconstrained
    mean and covariance are within sampling error of (Z0, 2 C0) with inflate = 2."""
    centre = {"K": math.exp(8.0), "G": math.exp(7.0), "delta": 2 + 4 * float(torch.sigmoid(torch.tensor(0.3)))}
    n = 4000
    w = unconstrained(gaussian_draws(centre, C0, n, seed=5, inflate=2.0, bounds=BOUNDS))
    C = 2 * C0
    assert float(((w.mean(0) - Z0) / (C.diagonal() / n).sqrt()).abs().max()) < 4.5
    se = ((C.square() + C.diagonal()[:, None] * C.diagonal()[None, :]) / (n - 1)).sqrt()
    assert float(((torch.cov(w.T) - C) / se).abs().max()) < 4.5


def test_bad_draw_requests_are_refused():
    tree, _ = fitted_tree(num_draws=20)
    names = ["K", "G", "delta"]
    centre = {"K": 3000.0, "G": 1000.0, "delta": 4.0}
    with pytest.raises(ValueError, match=r"delta = \[.*\] lies on or outside its bounds"):
        posterior_draws(tree, 5, 0, names=names, bounds={"delta": (2.0, 3.0)})
    with pytest.raises(ValueError, match="no posterior draws of \\['E'\\]"):
        posterior_draws(tree, 5, 0, names=["E"])
    with pytest.raises(ValueError, match="more than one value per draw"):
        posterior_draws(tree, 5, 0, names=["K", "u"])
    with pytest.raises(ValueError, match="bounds given for \\['E'\\]"):
        posterior_draws(tree, 5, 0, names=names, bounds={"E": (0, 1)})
    with pytest.raises(ValueError, match="inflate must be > 0"):
        posterior_draws(tree, 5, 0, names=names, inflate=0.0)
    with pytest.raises(ValueError, match="give at least 5"):
        posterior_draws({k: tree["posterior"][k].values.reshape(-1)[:4] for k in names}, 5, 0)
    with pytest.raises(ValueError, match="not positive definite"):
        posterior_draws({"K": tree["posterior"]["K"].values.reshape(-1), "c": torch.full((40,), 0.1)}, 5, 0)
    with pytest.raises(ValueError, match=r"covariance must be \(3, 3\)"):
        gaussian_draws(centre, torch.eye(2), 5, 0)
    with pytest.raises(ValueError, match="low < high"):
        gaussian_draws(centre, C0, 5, 0, bounds={"delta": (6.0, 2.0)})
    with pytest.raises(ValueError, match=r"delta = \[4.0\] lies on or outside its bounds \(2.0, 4.0\)"):
        gaussian_draws(centre, C0, 5, 0, bounds={"delta": (2.0, 4.0)})
