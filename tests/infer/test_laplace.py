"""Laplace approximation: exact on a linear Gaussian model; through the PD adjoint on a scene."""

import json
import math
import warnings

import numpy as np
import pyro
import pyro.distributions as dist
import pytest
import torch
from pyro.infer.autoguide.initialization import init_to_median
from torch.distributions import constraints

import bayespd as bp
from bayespd.infer import NotPositiveDefiniteHessian, ScaledBeta, fit
from bayespd.infer import modes as modes_table
from bayespd.infer.laplace import exact_hessian
from bayespd.infer.space import Unconstrained
from bayespd.models.elastic_plate import elastic_plate

A = torch.tensor([[1.0, 0.5, 0.0], [0.2, 1.0, -0.3], [0.0, 0.4, 1.0], [1.0, -1.0, 0.5], [0.3, 0.3, 0.3]])
M0, S0 = torch.tensor([0.5, -1.0, 2.0]), torch.tensor([[2.0, 0.3, 0.0], [0.3, 1.0, 0.2], [0.0, 0.2, 0.5]])
NOISE = 0.3
Y = A @ torch.tensor([1.0, 0.0, 1.5]) + NOISE * torch.randn(5, generator=torch.Generator().manual_seed(0))


def linear(y):
    """theta ~ N(M0, S0), y ~ N(A theta, NOISE^2 I); s ~ LogNormal(0, 0.5) stays at its prior."""
    theta = pyro.sample("theta", dist.MultivariateNormal(M0, S0))
    pyro.sample("s", dist.LogNormal(0.0, 0.5))
    pyro.sample("y", dist.Normal(A @ theta, NOISE).to_event(1), obs=y)


def exact_posterior():
    precision = torch.linalg.inv(S0) + A.T @ A / NOISE**2
    cov = torch.linalg.inv(precision)
    return cov @ (torch.linalg.solve(S0, M0) + A.T @ Y / NOISE**2), cov


@pytest.mark.parametrize("hessian", ["exact", "gauss-newton"])
def test_laplace_is_exact_on_a_linear_gaussian_model(hessian):
    """The log joint is quadratic in (theta, log s) (log s: LogNormal prior plus the log-
    Jacobian of exp), so the Laplace approximation is the posterior; Gauss-Newton is exact
    too, the mean being linear."""
    tree = fit(linear, {"y": Y}, "laplace", hessian=hessian, num_samples=2000, progress=False)
    mean, cov = exact_posterior()
    st = tree["sample_stats"]
    assert list(st["unconstrained"].values) == ["s", "theta[0]", "theta[1]", "theta[2]"]
    mode, sigma = st["mode_unconstrained"].values, st["covariance_unconstrained"].values
    np.testing.assert_allclose(mode[1:], mean, rtol=0, atol=1e-8)
    np.testing.assert_allclose(sigma[1:, 1:], cov, rtol=1e-8, atol=1e-12)
    assert abs(mode[0]) < 1e-8 and sigma[0, 0] == pytest.approx(0.25, rel=1e-8)
    np.testing.assert_allclose(sigma[0, 1:], 0.0, atol=1e-12)
    # draws: Gaussian in theta, exp(N(0, 0.25)) in s (pushed through the constraint)
    theta = tree["posterior"]["theta"].values.reshape(-1, 3)
    n = theta.shape[0]
    assert np.all(np.abs(theta.mean(0) - mean.numpy()) < 4 * np.sqrt(np.diag(cov.numpy()) / n))
    s = tree["posterior"]["s"].values.reshape(-1)
    assert s.min() > 0 and abs(np.mean(np.log(s))) < 4 * 0.5 / math.sqrt(n)
    assert tree.attrs["map_grad_norm"] < 1e-6  # rounding level: the potential is O(100)


def test_the_seed_fixes_the_start_and_so_the_result():
    """The start is the prior median of 15 prior draws (Pyro's ``init_to_median``): drawn
    with the fit's seed, not from whatever state the global generator is in, so the same call
    gives the same bits in any process (it differed at 1e-9 between processes before)."""
    trees = []
    for state in (1, 2):
        torch.manual_seed(state)
        trees.append(fit(linear, {"y": Y}, "laplace", num_samples=20, seed=3, progress=False))
    a, b = (t["sample_stats"]["mode_unconstrained"].values for t in trees)
    assert np.array_equal(a, b)
    assert np.array_equal(trees[0]["posterior"]["theta"].values, trees[1]["posterior"]["theta"].values)


def test_not_positive_definite_hessian_names_the_site_and_the_fix():
    def ridge(y):
        """Flat priors and a factor in a + b only: the Hessian [[2, 2], [2, 2]] is singular."""
        a, b = (pyro.sample(k, dist.ImproperUniform(constraints.real, (), ())) for k in "ab")
        pyro.factor("sum", -((a + b - 1) ** 2))
        linear(y)

    with pytest.raises(NotPositiveDefiniteHessian, match="along '[ab]'.*[Tt]ighten the prior"):
        fit(ridge, {"y": Y}, "laplace", init_values={"a": 0.3, "b": 0.1}, progress=False)


def test_gauss_newton_refuses_a_non_normal_likelihood():
    def robust(y):
        theta = pyro.sample("theta", dist.MultivariateNormal(M0, S0))
        pyro.sample("y", dist.StudentT(4.0, A @ theta, NOISE).to_event(1), obs=y)

    with pytest.raises(ValueError, match="Normal likelihood.*hessian='exact'"):
        fit(robust, {"y": Y}, "laplace", hessian="gauss-newton", progress=False)


@pytest.fixture(scope="module")
def plate():
    """A small LPS plate (conftest's geometry) with data from the model itself plus 1 % noise."""
    p = bp.grid_2d(10.0, 6.0, 1.0)
    mat = bp.LPS(p, bp.find_bonds(p, 2.5), plane="stress")
    scene = bp.Scene(mat, [bp.Dirichlet.layer(p, "left", 2.5)], [bp.Load(p.layer("right", 1.0), (30.0, 10.0))],
                     bp.Observation(p, p.x[~p.layer("left", 2.5)]))
    with torch.no_grad():
        clean = scene.observe(scene.solve({"K": 3000.0, "G": 1400.0, "delta": 2.0}))
    noise = 0.01 * float(clean.abs().max())
    y = clean + noise * torch.randn(clean.shape, generator=torch.Generator().manual_seed(1))
    model = elastic_plate(scene, {"K": 2500.0, "G": 1200.0}, 5 * noise,
                          priors={"delta": ScaledBeta(1.5, 2.5)})
    return scene, model, {"y": y}


def test_hessian_through_the_adjoint_matches_finite_differences(plate):
    """Hessian of the potential at a generic point (second derivatives of the PD solve) against
    central differences of its gradient: error O(eps^2) ~ 1e-8 relative."""
    _, model, data = plate
    space = Unconstrained(model, data, init_to_median)
    z = space.initial + torch.tensor([0.1, -0.2, 0.05, 0.3])  # sorted: G, K, delta, sigma
    h = exact_hessian(space, z)

    def grad(x):
        x = x.clone().requires_grad_()
        return torch.autograd.grad(space.potential(x), x)[0]

    eps = 1e-4
    fd = torch.stack([(grad(z + eps * e) - grad(z - eps * e)) / (2 * eps) for e in torch.eye(4)], dim=1)
    torch.testing.assert_close(h, h.T, rtol=1e-10, atol=1e-10 * float(h.abs().max()))
    torch.testing.assert_close(h, fd, rtol=1e-5, atol=1e-6 * float(h.abs().max()))


def test_laplace_on_a_scene_and_gauss_newton_close_to_exact(plate):
    """At the MAP of a well-fitting model the Gauss-Newton Hessian differs from the exact one
    only by residual-weighted second derivatives of the mean (residuals ~ noise, 1 % of the
    signal), so the two covariances agree to within 10 % (measured: 6 %)."""
    scene, model, data = plate
    exact = fit(model, data, "laplace", num_samples=400, scene=scene, progress=False)
    gn = fit(model, data, "laplace", hessian="gauss-newton", num_samples=10, scene=scene, progress=False)
    ce, cg = (t["sample_stats"]["covariance_unconstrained"].values for t in (exact, gn))
    np.testing.assert_allclose(exact["sample_stats"]["mode_unconstrained"],
                               gn["sample_stats"]["mode_unconstrained"], atol=1e-6)
    assert np.linalg.norm(ce - cg) < 0.1 * np.linalg.norm(ce)
    post = exact["posterior"]
    assert float(post["K"].min()) > 0 and float(post["G"].min()) > 0
    assert 1.5 < float(post["delta"].min()) and float(post["delta"].max()) < 2.5
    for k, truth in (("K", 3000.0), ("G", 1400.0)):
        draws = post[k].values.reshape(-1)
        assert abs(draws.mean() - truth) < 3 * draws.std()


def two_basins(y, pull_sd):
    """x ~ N(-1/2, 2^2), y ~ N(x^2, 1/2^2) with y = 4 (modes near x = -2 and +2), and a
    second datum 2 ~ N(x, pull_sd^2) that favours +2: potential gap U(-2) - U(+2) =
    8 / pull_sd^2 - 1/2 to leading order (7.5 at pull_sd = 1, 1.5 at 2)."""
    x = pyro.sample("x", dist.Normal(-0.5, 2.0))
    pyro.sample("y", dist.Normal(x**2, 0.5), obs=y)
    pyro.sample("pull", dist.Normal(x, pull_sd), obs=torch.tensor(2.0))


@pytest.mark.parametrize("pull_sd, close", [(1.0, False), (2.0, True)])
def test_map_from_several_starts_finds_the_lower_basin(pull_sd, close):
    """From the prior median (-1/2) one search descends into the -2 basin; eight (the median
    and a Latin hypercube of the prior) find +2, the lower potential, and list both modes;
    a warning comes exactly when the two modes lie within 3 nats."""
    from functools import partial

    model = partial(two_basins, pull_sd=pull_sd)
    data = {"y": torch.tensor(4.0)}
    start = {"x": -0.5}  # the prior median, given (Pyro's init_to_median draws from the global RNG)
    one = fit(model, data, "laplace", num_samples=50, progress=False, init_values=start)
    assert float(one["posterior"]["x"].mean()) < -1.5
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        eight = fit(model, data, "laplace", num_samples=50, progress=False, map_starts=8, init_values=start)
    modes = json.loads(eight.attrs["map_modes"])
    assert float(eight["posterior"]["x"].mean()) > 1.5
    assert [round(m["values"]["x"]) for m in modes] == [2, -2]
    table = modes_table(eight)  # the same list for the user; no weights: one mode fitted
    assert table["x"].round().tolist() == [2, -2] and "weight" not in table
    gap = modes[1]["potential"] - modes[0]["potential"]
    assert abs(gap - (8 / pull_sd**2 - 0.5)) < 0.5  # the leading-order gap of the docstring
    assert any("multimodal" in str(w.message) for w in caught) == close
    with pytest.raises(ValueError, match="init='map'"):
        fit(model, data, "nuts", map_starts=8, progress=False)
