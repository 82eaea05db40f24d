"""Brownian-bias likelihoods (Dodwell 2019 eqs 3-4): the stationary marginal and the Euler-Maruyama
transition against dense references, their gradients, and recovery of eta from simulated data
(the Pyro models of ``models/brownian_bias.py`` are tested in ``tests/models/test_brownian_bias.py``).

The recovery tests use data from the calibrated model itself (same discretisation): they check
that likelihood, gradients and optimiser find the truth within the Laplace posterior sd. Data
from a finer discretisation, where eta is no longer exactly the same parameter, are the
experiment's business (experiments/brownian_bias.py).
"""
import numpy as np
import pytest
import scipy.optimize
import scipy.stats as st
import torch

import bayespd as bp
from bayespd.infer.likelihoods import NoiseCovariance, StationaryMarginal, transition_log_likelihood
from bayespd.solvers import karhunen_loeve
from bayespd.models.brownian_bias import stationary

EPS = 0.05
TRUTH = {"K": 3000.0, "G": 1400.0, "delta": 2.2, "eta": 0.002, "sigma": 2e-4, "sigma_c": 0.3, "length": 1.5}
MATERIAL = ("K", "G", "delta")


def make_scene(points=None):
    """An 8 x 4 LPS plate, clamped on the left, a prescribed vertical displacement at the top
    right corner (so the K_fc u_c part of the load is exercised), pulled on the right."""
    p = bp.grid_2d(8.0, 4.0, 1.0)
    corner = (p.x[:, 0] > 7.4) & (p.x[:, 1] > 3.4)
    points = p.x[p.x[:, 0] > 2.5] if points is None else points
    return bp.Scene(bp.LPS(p, bp.find_bonds(p, 2.5)),
                    [bp.Dirichlet.layer(p, "left", 2.5), bp.Dirichlet(corner, (None, 0.02))],
                    [bp.Load(p.layer("right", 1.0), (30.0, 10.0))], bp.Observation(p, points), eps=EPS)


def tensors(names, values=TRUTH):
    return {k: torch.tensor(values[k]) for k in names}


@pytest.fixture(scope="module")
def scene():
    # interpolated points (not on particles) next to particle points
    return make_scene(np.array([[3.3, 1.7], [5.5, 2.2], [6.1, 0.8], [7.0, 3.0], [4.0, 2.0], [7.5, 0.5]]))


def dense_operator(scene, params):
    """A = K_ff + eps I, p_f = f_f - K_fc u_c, and H (columns: observed unit free dofs) densely."""
    c, mat = scene.constraints, scene.material
    K = mat.pattern.matrix(mat.numeric_stiffness(params)).toarray()
    free, fixed = c.free_dofs, np.flatnonzero(~c.free_mask)
    A = K[np.ix_(free, free)] + EPS * np.eye(len(free))
    p = scene.force.reshape(-1).numpy()[free] - K[np.ix_(free, fixed)] @ c.prescribed.reshape(-1).numpy()[fixed]
    H = np.stack([scene.observe(c.embed(e)).reshape(-1).numpy() for e in torch.eye(len(free))], axis=1)
    return A, p, H, scene.observe(c.prescribed).reshape(-1).numpy()


def test_stationary_marginal_equals_dense_reference(scene):
    params = tensors(MATERIAL)
    A, p, H, u_c = dense_operator(scene, params)
    mean = H @ np.linalg.solve(A, p) + u_c
    cov = TRUTH["eta"] * H @ np.linalg.solve(A, H.T) + TRUTH["sigma"] ** 2 * np.eye(len(mean))
    y = st.multivariate_normal(mean, cov).rvs(3, random_state=1)
    reference = st.multivariate_normal(mean, cov).logpdf(y).sum()
    got = StationaryMarginal(scene).log_likelihood(torch.as_tensor(y), params, TRUTH["eta"], TRUTH["sigma"])
    assert abs(float(got) - reference) < 1e-10 * abs(reference), (float(got), reference)


def test_stationary_marginal_gradient(scene):
    """gradcheck in (K, G, delta, eta, sigma), each scaled to O(1) (delta away from the
    partial-volume kinks at |xi| +- h/2), and a Taylor remainder of slope 2."""
    marginal = StationaryMarginal(scene)
    scale = torch.tensor([TRUTH[k] for k in (*MATERIAL, "eta", "sigma")])
    with torch.random.fork_rng():  # a fixed draw: the check must not depend on earlier tests
        torch.manual_seed(0)
        y = marginal(tensors(MATERIAL), TRUTH["eta"], TRUTH["sigma"]).sample((2,)).detach()

    def ll(x):
        v = x * scale
        return marginal.log_likelihood(y, dict(zip(MATERIAL, v[:3])), v[3], v[4])

    x0 = torch.tensor([1.05, 0.95, 1.02, 1.3, 0.8], requires_grad=True)
    assert torch.autograd.gradcheck(ll, (x0,), eps=1e-6, atol=1e-6, rtol=1e-4)
    g = torch.autograd.grad(ll(x0), x0)[0]
    d = torch.randn(5, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        r = [abs(float(ll(x0 + t * d) - ll(x0) - t * (g @ d))) for t in (1e-2, 5e-3)]
    assert 3.0 < r[0] / r[1] < 5.0, r  # second order: halving t quarters the remainder


def kl_covariance(scene, sigma_c, length):
    return NoiseCovariance.karhunen_loeve(scene.particles.x, sigma_c, length, rank=6, nugget=0.05,
                                          dofs=scene.constraints.free_dofs, dim=2)


def test_kl_covariance_is_the_simulators(scene):
    """The likelihood's differentiable Karhunen-Loeve C is the Langevin simulator's C (same rank,
    no kernel cut-off), so simulated paths and the likelihood agree."""
    c = scene.constraints
    ours = kl_covariance(scene, torch.tensor(0.3), torch.tensor(1.5))
    dense = (torch.diag(ours.d) + ours.G @ ours.G.T).numpy()
    sim = karhunen_loeve(scene.particles.x, 0.3, 1.5, rank=6, nugget=0.05, cutoff=50.0, dofs=c.free_dofs).dense()
    np.testing.assert_allclose(dense, sim, atol=1e-10 * np.abs(sim).max())


@pytest.mark.parametrize("noise", ["white", "kl"])
def test_transition_equals_dense_reference(scene, noise):
    params = tensors(MATERIAL)
    A, p, _, _ = dense_operator(scene, params)
    sigma_c, length = torch.tensor(0.3), torch.tensor(1.5)
    n = len(p)
    C = NoiseCovariance.white(sigma_c, n) if noise == "white" else kl_covariance(scene, sigma_c, length)
    C_dense = np.diag(np.broadcast_to(C.d.numpy(), (n,))) + (0 if C.G is None else (C.G @ C.G.T).numpy())
    dt, eta = 2e-6, TRUTH["eta"]
    U = np.random.default_rng(2).standard_normal((5, n)) * 1e-3
    reference = sum(st.multivariate_normal(U[k] + dt / eta * C_dense @ (p - A @ U[k]), 2 * dt * C_dense).logpdf(U[k + 1])
                    for k in range(4))
    got = transition_log_likelihood(torch.as_tensor(U), scene, params, eta, C, dt)
    assert abs(float(got) - reference) < 1e-10 * abs(reference), (float(got), reference)


def test_transition_gradient(scene):
    """gradcheck of the Karhunen-Loeve transition likelihood in (K, G, delta, eta, sigma_c, length)."""
    names = (*MATERIAL, "eta", "sigma_c", "length")
    scale = torch.tensor([TRUTH[k] for k in names])
    U = torch.as_tensor(np.random.default_rng(3).standard_normal((4, len(scene.constraints.free_dofs))) * 1e-3)

    def ll(x):
        v = x * scale
        return transition_log_likelihood(U, scene, dict(zip(MATERIAL, v[:3])), v[3], kl_covariance(scene, v[4], v[5]), 1e-5)

    x0 = torch.tensor([1.05, 0.95, 1.02, 1.3, 0.8, 1.1], requires_grad=True)
    assert torch.autograd.gradcheck(ll, (x0,), eps=1e-6, atol=1e-6, rtol=1e-4)


def laplace(log_posterior, names, truth):
    """MAP of log_posterior over log-parameters (L-BFGS from a factor 1.5 off the truth) and
    the Laplace sd of each parameter (delta method: sd = value * sd of its log)."""
    def f(z):
        x = torch.tensor(z, requires_grad=True)
        v = -log_posterior(dict(zip(names, torch.exp(x))))
        return float(v.detach()), torch.autograd.grad(v, x)[0].numpy()

    z0 = np.log([truth[k] for k in names]) + np.log(1.5) * (-1) ** np.arange(len(names))
    res = scipy.optimize.minimize(f, z0, jac=True, method="L-BFGS-B", options={"gtol": 1e-9, "maxiter": 500})
    z = torch.tensor(res.x)
    hess = torch.autograd.functional.hessian(lambda x: -log_posterior(dict(zip(names, torch.exp(x)))), z)
    sd_log = torch.linalg.inv(hess).diagonal().sqrt()
    return {k: (float(np.exp(res.x[i])), float(np.exp(res.x[i]) * sd_log[i])) for i, k in enumerate(names)}


@pytest.fixture(scope="module")
def frames():
    """40 stationary frames of the scene observed at its particles right of the clamp, exact
    draws of N(H A^-1 p, eta H A^-1 H^T + sigma^2 I) (the calibrated model: see module doc)."""
    scene = make_scene()
    law = StationaryMarginal(scene)(tensors(MATERIAL), TRUTH["eta"], TRUTH["sigma"])
    torch.manual_seed(0)
    return scene, law.sample((40,)).detach()


def test_stationary_recovery_and_separability(frames):
    """MAP of (K, G, eta, sigma) (delta known) lies within 3 Laplace sd of the truth with 40
    frames, and the sd of eta and sigma shrink like 1/sqrt(F): 10 -> 40 frames halves them
    (band 1.5-2.7 allows the observed information's sampling spread)."""
    scene, y = frames
    names = ("K", "G", "eta", "sigma")
    model = stationary(scene, {"K": 2500.0, "G": 1200.0}, eta_nominal=0.005, noise_scale=1e-3)
    marginal = model.marginal
    priors = {"K": torch.distributions.LogNormal(np.log(2500.0), 0.5),
              "G": torch.distributions.LogNormal(np.log(1200.0), 0.5),
              "eta": torch.distributions.LogNormal(np.log(0.005), 1.0),
              "sigma": torch.distributions.HalfNormal(1e-3)}
    fits = {}
    for F in (10, 40):
        def log_posterior(v, F=F):
            params = {"K": v["K"], "G": v["G"], "delta": torch.tensor(TRUTH["delta"])}
            return (marginal.log_likelihood(y[:F], params, v["eta"], v["sigma"])
                    + sum(priors[k].log_prob(v[k]) + torch.log(v[k]) for k in names))  # Jacobian of exp
        fits[F] = laplace(log_posterior, names, TRUTH)
    for k in names:
        value, sd = fits[40][k]
        assert abs(value - TRUTH[k]) < 3 * sd, (k, value, sd, TRUTH[k])
    for k in ("eta", "sigma"):
        ratio = fits[10][k][1] / fits[40][k][1]
        assert 1.5 < ratio < 2.7, (k, ratio, fits)
