"""models/elastic_plate.py: the Pyro model's sites, priors and likelihood, checked against
the Gaussian log density written out from the scene's own solve."""
import math

import pyro.distributions as dist
import pytest
import torch
from pyro import poutine
from pyro.poutine.util import site_is_subsample

import bayespd as bp
from bayespd.models.elastic_plate import ElasticPlate, default_priors, elastic_plate
from bayespd.reduced.trend import LinearTrend
from tests.conftest import plate_scene

NOMINAL = {"K": 3000.0, "G": 1400.0}
AT = {"K": torch.tensor(2800.0), "G": torch.tensor(1500.0), "delta": torch.tensor(2.2), "sigma": torch.tensor(0.01)}


@pytest.fixture(scope="module")
def scene():
    return plate_scene()


def traced(model, y=None, mask=None):
    return poutine.trace(poutine.condition(model, data=AT)).get_trace(y=y, mask=mask)


def test_sites_are_the_scene_parameters_sigma_and_the_data(scene):
    """One sample site per scene parameter plus sigma, with the default priors, and y of
    shape (points, dim) inside the point and component plates."""
    model = elastic_plate(scene, NOMINAL, 0.01)
    assert isinstance(model, ElasticPlate)
    tr = traced(model)
    sites = [n for n, s in tr.nodes.items() if s["type"] == "sample" and not site_is_subsample(s)]
    assert sites == ["K", "G", "delta", "sigma", "y"]
    defaults = default_priors(scene, NOMINAL, 0.01)
    for k in ("K", "G", "delta", "sigma"):
        assert type(tr.nodes[k]["fn"]) is type(defaults[k])
    assert tr.nodes["y"]["value"].shape == scene.observation.points.shape


def test_likelihood_is_the_gaussian_of_the_scene_solve(scene):
    """log p(y | params) = sum N(y; H u(params), sigma^2) with u from scene.solve (1e-12);
    a mask drops exactly the masked entries' terms."""
    model = elastic_plate(scene, NOMINAL, 0.01)
    with torch.no_grad():
        mean = scene.observe(scene.solve({k: AT[k] for k in ("K", "G", "delta")}))
    y = mean + 0.01 * torch.randn(mean.shape, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    tr = traced(model, y)
    tr.compute_log_prob()
    z = (y - mean) / 0.01
    exact = -0.5 * z.square() - math.log(0.01) - 0.5 * math.log(2 * math.pi)
    assert float(tr.nodes["y"]["log_prob_sum"]) == pytest.approx(float(exact.sum()), rel=1e-12)
    mask = torch.zeros(mean.shape, dtype=torch.bool)
    mask[::3] = True
    tr = traced(model, y, mask)
    tr.compute_log_prob()
    assert float(tr.nodes["y"]["log_prob_sum"]) == pytest.approx(float(exact[mask].sum()), rel=1e-12)


def test_a_prior_can_be_replaced(scene):
    """priors={"K": ...} replaces K's prior only: its log density at K enters the joint."""
    mine = dist.Gamma(30.0, 0.01)
    model = elastic_plate(scene, NOMINAL, 0.01, priors={"K": mine})
    tr = traced(model)
    tr.compute_log_prob()
    assert tr.nodes["K"]["fn"] is mine
    assert float(tr.nodes["K"]["log_prob_sum"]) == pytest.approx(float(mine.log_prob(AT["K"])), rel=1e-14)
    assert isinstance(tr.nodes["G"]["fn"], dist.LogNormal)
    with pytest.raises(ValueError, match="includes negative moduli"):
        elastic_plate(scene, NOMINAL, 0.01, priors={"G": dist.Normal(1400.0, 10.0)})


def term_for(scene, seed=0, slope=True, relative=False):
    """A Discrepancy on the scene's observation points: random mean, rank-3 W, d, and a
    linear dependence on (log K, log G, log delta) when ``slope`` (scaled by 1 / rms(prediction)
    when ``relative``)."""
    g = torch.Generator().manual_seed(seed)
    points = scene.observation.points
    n = points.shape[0] * scene.particles.dim
    mean = 1e-3 * torch.randn(points.shape[0], scene.particles.dim, generator=g)
    factor, diag = 3e-3 * torch.randn(n, 3, generator=g), 1e-5 * torch.rand(n, generator=g) + 1e-6
    trend = LinearTrend(bp.LogFeatures(("K", "G", "delta")), mean.reshape(-1), 1e-3 * torch.randn(n, 3, generator=g),
                        torch.tensor([8.0, 7.2, 0.8]))
    return bp.Discrepancy(mean=mean, factor=factor, diag=diag, rms=1e-3, explained=0.9, num_draws=40,
                          trend=trend if slope else None, points=torch.as_tensor(points).clone(), relative=relative)


@pytest.mark.parametrize("relative", [False, True])
def test_discrepancy_likelihood_is_the_dense_gaussian(scene, relative):
    """With discrepancy=, log p(y | params) = log N(vec y; vec(H u + s (mu + B (phi - phi_bar))),
    s^2 W W^T + diag(s^2 d + sigma^2)) written densely (1e-10), s = 1 or rms(H u) if relative;
    a mask gives the dense Gaussian of the kept entries (rows and columns selected);
    replicated data keep shape (points, dim)."""
    term = term_for(scene, relative=relative)
    model = elastic_plate(scene, NOMINAL, 0.01, discrepancy=term)
    params = {k: AT[k] for k in ("K", "G", "delta")}
    with torch.no_grad():
        mean = scene.observe(scene.solve(params))
    phi = torch.log(torch.stack([AT["K"], AT["G"], AT["delta"]]))
    s = float(mean.square().mean().sqrt()) if relative else 1.0
    loc = mean.reshape(-1) + s * (term.mean.reshape(-1) + term.trend.slope @ (phi - term.trend.centre))
    cov = s**2 * term.covariance() + AT["sigma"] ** 2 * torch.eye(loc.shape[0])
    y = (loc + torch.linalg.cholesky(cov) @ torch.randn(loc.shape[0], generator=torch.Generator().manual_seed(1))
         ).reshape(mean.shape)
    tr = traced(model, y)
    tr.compute_log_prob()
    exact = dist.MultivariateNormal(loc, cov).log_prob(y.reshape(-1))
    assert float(tr.nodes["y"]["log_prob_sum"]) == pytest.approx(float(exact), abs=1e-10, rel=0)
    assert tr.nodes["y"]["fn"].sample().shape == mean.shape
    mask = torch.zeros(mean.shape, dtype=torch.bool)
    mask[::3] = True
    mask[1::4, 0] = True
    keep = mask.reshape(-1)
    tr = traced(model, y, mask)
    tr.compute_log_prob()
    kept = dist.MultivariateNormal(loc[keep], cov[keep][:, keep]).log_prob(y.reshape(-1)[keep])
    assert float(tr.nodes["y"]["log_prob_sum"]) == pytest.approx(float(kept), abs=1e-10, rel=0)


def test_discrepancy_of_other_points_is_refused(scene):
    """A term estimated at other points, or at a different number of them: a clear error."""
    term = term_for(scene, slope=False)
    moved = bp.Discrepancy(**{**term.__dict__, "points": term.points + 0.5})
    with pytest.raises(ValueError, match="other observation points"):
        elastic_plate(scene, NOMINAL, 0.01, discrepancy=moved)
    fewer = bp.Discrepancy(mean=term.mean[1:], factor=term.factor[2:], diag=term.diag[2:], rms=1e-3,
                           explained=0.9, num_draws=40)
    with pytest.raises(ValueError, match="estimate it with reference and model observed at the data's points"):
        elastic_plate(scene, NOMINAL, 0.01, discrepancy=fewer)
    with pytest.raises(TypeError, match="bayespd.Discrepancy"):
        elastic_plate(scene, NOMINAL, 0.01, discrepancy={"mean": term.mean})


def test_fit_with_a_discrepancy_keeps_the_data_shape(scene):
    """fit (Laplace, masked) runs through the checks and the replay: posterior predictive and
    observed data (points, dim), one log-likelihood value per draw."""
    from bayespd.infer import fit

    term = term_for(scene, slope=False)
    model = elastic_plate(scene, NOMINAL, 0.01, discrepancy=term)
    with torch.no_grad():
        y = scene.observe(scene.solve({k: AT[k] for k in ("K", "G", "delta")})) + term.mean
    mask = torch.ones(y.shape, dtype=torch.bool)
    mask[0] = False
    tree = fit(model, {"y": y, "mask": mask}, "laplace", num_samples=20, seed=0,
               init_values={k: AT[k] for k in ("K", "G", "delta", "sigma")})
    assert tree["posterior_predictive"]["y"].shape == (1, 20, *y.shape)
    assert tree["observed_data"]["y"].shape == y.shape
    assert tree["log_likelihood"]["y"].shape == (1, 20)
