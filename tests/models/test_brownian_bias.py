"""``models/brownian_bias.py``: the stationary and trajectory Pyro models of the Brownian
forcing (Dodwell 2019 eq 4) as model discrepancy: their log densities equal the likelihoods
of ``bayespd.infer.likelihoods``, the trajectory model recovers the truth from a simulated
path, and bad data and unknown priors are refused. The scene, truth and Laplace helper are
shared with ``tests/infer/test_likelihoods.py``."""
import numpy as np
import pyro.distributions as dist
import pytest
import torch
from pyro import poutine

from bayespd.solvers import Langevin, linear_elastic, white_noise
from bayespd.models.brownian_bias import frames_data, stationary, trajectory
from tests.infer.test_likelihoods import (EPS, MATERIAL, TRUTH, frames, laplace,  # noqa: F401 (frames: a fixture)
                                          make_scene, tensors)


def test_frames_data_keeps_the_observed_entries(frames):
    """(frames, points, dim) -> (frames, n_obs): the entries of the observation mask, frame by frame."""
    scene, y = frames
    n, d = scene.observation.n, scene.particles.dim
    full = torch.arange(2.0 * n * d).reshape(2, n, d)
    data = frames_data(scene, full)
    mask = scene.observation.mask.reshape(-1)
    assert data["y"].shape == (2, int(mask.sum()))
    assert torch.equal(data["y"][1], full[1].reshape(-1)[mask])
    with pytest.raises(ValueError, match=rf"y must be \(frames, {n}, {d}\), got \(2, {n - 1}, {d}\)"):
        frames_data(scene, full[:, :-1])


def test_unknown_priors_are_refused_naming_the_known_ones(frames):
    scene, _ = frames
    with pytest.raises(ValueError, match=r"no such parameter\(s\) \['mu'\]: priors can be given for .*'eta'"):
        stationary(scene, {"K": 2500.0, "G": 1200.0}, 0.005, 1e-3, priors={"mu": dist.Normal(0.0, 1.0)})
    with pytest.raises(ValueError, match=r"no such parameter\(s\) \['length'\].*'sigma_c'"):
        trajectory(scene, {"K": 2500.0, "G": 1200.0}, 0.02, 0.5, dt=1e-3, priors={"length": dist.LogNormal(0.0, 1.0)})


def test_a_replaced_prior_is_the_one_sampled(frames):
    scene, y = frames
    prior = dist.LogNormal(np.log(0.003), 0.1)
    model = stationary(scene, {"K": 2500.0, "G": 1200.0}, 0.005, 1e-3, priors={"eta": prior})
    data = frames_data(scene, y[:2].reshape(2, -1, 2))
    trace = poutine.trace(poutine.condition(model, data=tensors((*MATERIAL, "eta", "sigma")))).get_trace(**data)
    assert trace.nodes["eta"]["fn"] is prior
    assert isinstance(trace.nodes["sigma"]["fn"], dist.HalfNormal)


# moved from tests/infer/test_likelihoods.py
def test_stationary_model_runs_in_pyro(frames):
    """The Pyro model scores the same log-likelihood (prior terms aside) as the likelihood."""
    from pyro import poutine
    scene, y = frames
    model = stationary(scene, {"K": 2500.0, "G": 1200.0}, eta_nominal=0.005, noise_scale=1e-3)
    data = frames_data(scene, y[:3].reshape(3, -1, 2))
    trace = poutine.trace(poutine.condition(model, data=tensors((*MATERIAL, "eta", "sigma")))).get_trace(**data)
    expected = model.marginal.log_likelihood(y[:3], tensors(MATERIAL), TRUTH["eta"], TRUTH["sigma"])
    assert abs(float(trace.nodes["y"]["fn"].log_prob(data["y"]).sum() - expected)) < 1e-9 * abs(float(expected))


def test_trajectory_recovery_white_noise():
    """MAP of (K, G, eta, sigma_c) (delta known) from a 200-step Euler-Maruyama path simulated
    by bayespd.solvers.Langevin (white C, the model's own chain) lies within 3 Laplace sd."""
    scene = make_scene()
    c = scene.constraints
    params = tensors(MATERIAL)
    force = linear_elastic(scene.material, params, load=scene.force, eps=EPS, constraints=c)
    C = white_noise(TRUTH["sigma_c"], force.n)
    langevin = Langevin(force, C, TRUTH["eta"], operator=force.matrix)
    dt = 0.5 * langevin.explicit_limit()
    path = langevin.euler_maruyama(force.equilibrium(), dt, 200, generator=11, save_every=1).u
    model = trajectory(scene, {"K": 2500.0, "G": 1200.0}, eta_nominal=0.02, sigma_c_nominal=0.5, dt=dt)
    names = ("K", "G", "eta", "sigma_c")

    def log_posterior(v):
        conditioned = dict(v, delta=torch.tensor(TRUTH["delta"]))
        from pyro import poutine
        trace = poutine.trace(poutine.condition(model, data=conditioned)).get_trace(y=path[1:], u0=path[0])
        return trace.log_prob_sum() + sum(torch.log(v[k]) for k in names)  # Jacobian of exp

    fit = laplace(log_posterior, names, TRUTH)
    for k in names:
        value, sd = fit[k]
        assert abs(value - TRUTH[k]) < 3 * sd, (k, value, sd, TRUTH[k])
