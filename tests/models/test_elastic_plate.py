"""models/elastic_plate.py: the Pyro model's sites, priors and likelihood, checked against
the Gaussian log density written out from the scene's own solve."""
import math

import pyro.distributions as dist
import pytest
import torch
from pyro import poutine
from pyro.poutine.util import site_is_subsample

from bayespd.models.elastic_plate import ElasticPlate, default_priors, elastic_plate
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
