"""SVI guides on a linear Gaussian model whose posterior N(mean, cov) is known exactly.

The full-rank guide contains the posterior, so its optimum is exact; mean field's optimum is
known too: the exact mean with variances 1 / diag(precision) (reverse-KL mean field on a
Gaussian). What remains is optimiser noise from single-sample ELBO gradients (decaying rate)
and the Monte-Carlo error of the draws, hence the tolerances below (a few percent of the
posterior sd; 3000 steps measured within 3 %), far tighter than a wrong guide (the
posterior correlation -0.81 ignored: mean field's sd is 42 % too small).
"""

import json

import numpy as np
import pyro
import pyro.distributions as dist
import pytest
import torch

from bayespd.infer import fit

A = torch.tensor([[1.0, 0.8], [0.8, 1.0], [0.5, -0.2]])
NOISE = 0.5
Y = torch.tensor([1.2, 0.9, 0.1])
DRAWS = 4000


def linear(y):
    theta = pyro.sample("theta", dist.Normal(0.0, 2.0).expand([2]).to_event(1))
    pyro.sample("y", dist.Normal(A @ theta, NOISE).to_event(1), obs=y)


def exact():
    precision = torch.eye(2) / 4 + A.T @ A / NOISE**2
    cov = torch.linalg.inv(precision)
    return (cov @ A.T @ Y / NOISE**2).numpy(), cov.numpy(), precision.numpy()


def draws(guide, **kw):
    tree = fit(linear, {"y": Y}, "svi", guide=guide, svi_steps=3000, svi_lr=0.02,
               num_samples=DRAWS, seed=3, progress=False, **kw)
    return tree, tree["posterior"]["theta"].values.reshape(-1, 2)


@pytest.mark.parametrize("guide", ["mvn", pytest.param("lowrank", marks=pytest.mark.slow)])
def test_full_covariance_guides_recover_the_posterior(guide):
    """Covariance entries within 0.08 sd_i sd_j (draws' Monte-Carlo error ~0.02-0.03)."""
    mean, cov, _ = exact()
    tree, theta = draws(guide, svi_rank=1)
    sd = np.sqrt(np.diag(cov))
    assert np.all(np.abs(theta.mean(0) - mean) < 0.1 * sd)
    np.testing.assert_allclose(np.cov(theta.T) / np.outer(sd, sd), cov / np.outer(sd, sd), atol=0.08)
    corr = np.corrcoef(theta.T)[0, 1]
    assert corr == pytest.approx(cov[0, 1] / sd.prod(), abs=0.05)
    assert json.loads(tree.attrs["settings"])["guide"] == guide


def test_mean_field_guide_has_the_known_reverse_kl_optimum():
    mean, cov, precision = exact()
    _, theta = draws("normal")
    assert np.all(np.abs(theta.mean(0) - mean) < 0.1 * np.sqrt(np.diag(cov)))
    np.testing.assert_allclose(theta.std(0), 1 / np.sqrt(np.diag(precision)), rtol=0.05)
    assert abs(np.corrcoef(theta.T)[0, 1]) < 0.05
    assert np.all(theta.std(0) < 0.65 * np.sqrt(np.diag(cov)))  # mean field under-covers


@pytest.mark.slow
def test_flow_guide_recovers_the_posterior():
    mean, cov, _ = exact()
    _, theta = draws("flow")
    sd = np.sqrt(np.diag(cov))
    assert np.all(np.abs(theta.mean(0) - mean) < 0.15 * sd)
    np.testing.assert_allclose(theta.std(0), sd, rtol=0.15)


def test_flow_guide_refuses_one_dimension_and_unknown_guides_are_refused():
    def scalar(y):
        mu = pyro.sample("mu", dist.Normal(0.0, 1.0))
        pyro.sample("y", dist.Normal(mu, 1.0), obs=y)

    with pytest.raises(ValueError, match="at least two latent dimensions.*'mvn'"):
        fit(scalar, {"y": torch.tensor(0.5)}, "svi", guide="flow", svi_steps=2, progress=False)
    with pytest.raises(ValueError, match="guide must be one of"):
        fit(scalar, {"y": torch.tensor(0.5)}, "svi", guide="iaf", svi_steps=2, progress=False)
