"""The rigid-body nuisance: exact marginal (eq 1 of bayespd.rigid), invariance, estimates."""
import numpy as np
import pytest
import torch

import bayespd as bp
from bayespd.rigid import RigidNuisance, rigid_modes
from tests.conftest import plate_scene


def _setup(rng, rotation=True):
    scene = plate_scene()
    u = scene.solve({"K": 2000.0, "G": 900.0, "delta": 2.0})
    obs = scene.observation
    mask = rng.random(obs.points.shape) > 0.2
    return scene, u, obs, mask, RigidNuisance(obs, mask, rotation)


def _rigid(nuisance, r):
    return rigid_modes(nuisance.points, nuisance.centre, nuisance.rotation) @ r


def test_data_invariant_to_rigid_motion(rng):
    scene, u, obs, mask, nuisance = _setup(rng)
    y = obs(u).numpy() + 1e-3 * rng.standard_normal(obs.points.shape)
    r = np.array([0.3, -0.7, 0.05])
    a, b = nuisance.data(y), nuisance.data(y + _rigid(nuisance, r))
    assert torch.equal(a["mask"], b["mask"])
    assert float((a["y"] - b["y"]).abs().max()) < 1e-12 * float(np.abs(y).max() + 1)
    # the model side too: a rigid displacement of every particle observes 0 on the kept entries
    rigid_u = torch.as_tensor(rigid_modes(scene.particles.x, nuisance.centre) @ r)
    assert float(nuisance(rigid_u)[torch.as_tensor(nuisance.mask)].abs().max()) < 1e-12


def test_masked_gaussian_is_the_flat_prior_marginal(rng):
    """log N(Q2^T y; Q2^T H u, sigma^2 I) - log|T| = lim_tau log p_tau(y) + k/2 log(2 pi tau^2),
    p_tau the Gaussian marginal under r ~ N(0, tau^2 I); the limit is reached to O(sigma^2 / (tau^2 |R|^2))."""
    _, u, obs, mask, nuisance = _setup(rng)
    sigma, tau = 0.5, 1e3
    y = obs(u).numpy() + sigma * rng.standard_normal(obs.points.shape)
    data = nuisance.data(y)
    z = torch.distributions.Normal(nuisance(u), sigma).log_prob(data["y"])[data["mask"]].sum()
    flat = mask.reshape(-1)
    R = rigid_modes(obs.points, nuisance.centre).reshape(-1, 3)[flat]
    mean = obs(u).numpy().reshape(-1)[flat]
    cov = sigma**2 * np.eye(len(mean)) + tau**2 * R @ R.T
    wide = torch.distributions.MultivariateNormal(torch.as_tensor(mean), torch.as_tensor(cov))
    limit = wide.log_prob(torch.as_tensor(y.reshape(-1)[flat])) + 1.5 * np.log(2 * np.pi * tau**2)
    log_det_t = np.log(np.abs(np.diag(nuisance.T))).sum()
    assert abs(float(z) - log_det_t - float(limit)) < 1e-6
    assert int(data["mask"].sum()) == flat.sum() - 3


def test_elastic_plate_scores_the_marginal(rng):
    """models.elastic_plate, unchanged, evaluates eq 1 when the scene observes through the nuisance."""
    import pyro
    from bayespd.models.elastic_plate import elastic_plate
    scene, u, obs, mask, nuisance = _setup(rng)
    y = obs(u).numpy() + 0.05 * rng.standard_normal(obs.points.shape) + _rigid(nuisance, [1.0, 2.0, 0.01])
    marginal = bp.Scene(scene.material, scene.dirichlet, scene.loads, nuisance)
    model = elastic_plate(marginal, {"K": 2000.0, "G": 900.0}, 0.05)
    params = {k: torch.tensor(v) for k, v in {"K": 2000.0, "G": 900.0, "delta": 2.0, "sigma": 0.05}.items()}
    trace = pyro.poutine.trace(pyro.poutine.condition(model, params)).get_trace(**nuisance.data(y))
    trace.compute_log_prob()
    data = nuisance.data(y)
    expected = torch.distributions.Normal(nuisance(u), 0.05).log_prob(data["y"])[data["mask"]].sum()
    assert abs(float(trace.nodes["y"]["log_prob_sum"] - expected)) < 1e-9


def test_least_squares_estimate_recovers_the_motion(rng):
    _, u, obs, mask, nuisance = _setup(rng)
    r = np.array([-0.2, 0.4, 0.003])
    prediction = obs(u).numpy()
    y = prediction + _rigid(nuisance, r)
    assert np.abs(nuisance.estimate(y, prediction) - r).max() < 1e-12
    assert np.abs(nuisance.motion(r) - np.where(mask, _rigid(nuisance, r), 0.0)).max() < 1e-14
    translation = RigidNuisance(obs, mask, rotation=False)
    assert np.abs(translation.estimate(prediction + [0.1, -0.3], prediction) - [0.1, -0.3]).max() < 1e-12


def test_observation_matrix_is_the_operator(rng):
    """Scene.observation_matrix of the nuisance scene reproduces nuisance(u) (Q^T H, the reduced
    model and the Brownian-bias likelihood read it)."""
    scene, u, obs, mask, nuisance = _setup(rng)
    marginal = bp.Scene(scene.material, scene.dirichlet, scene.loads, nuisance)
    H = marginal.observation_matrix().to_dense()
    c = marginal.constraints
    direct = nuisance(u).reshape(-1)
    assert float((H @ c.free(u) - direct).abs().max()) < 1e-12 * float(direct.abs().max())


def test_refuses_what_cannot_be_marginalised(rng):
    p = bp.grid_2d(4.0, 4.0, 1.0)
    line = bp.ParticleObservation(p, np.flatnonzero(p.x[:, 1] == 0.5))
    with pytest.raises(ValueError, match="cannot tell the rigid modes apart"):
        RigidNuisance(line, np.column_stack([np.zeros(4, bool), np.ones(4, bool)]))
    with pytest.raises(ValueError, match="needs more than 3"):
        RigidNuisance(bp.ParticleObservation(p, [0]))
    with pytest.raises(ValueError, match="mask must be boolean of shape"):
        RigidNuisance(line, np.ones((3, 2), bool))
    nuisance = RigidNuisance(line, np.column_stack([np.ones(4, bool), np.arange(4) > 0]))
    with pytest.raises(ValueError, match="NaN or inf on entries the mask keeps"):
        nuisance.data(np.full((4, 2), np.nan))
