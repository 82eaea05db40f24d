"""bayespd/reduced/discrepancy.py: the approximation-error term recovers the mean, covariance
and linear dependence of a known Gaussian error within sampling error, and refuses bad input."""
import math

import pytest
import torch

import bayespd as bp
from bayespd.infer.datatree import build_tree
from bayespd.reduced.discrepancy import MIN_DOF, estimate_discrepancy, gaussian_draws, posterior_draws, prior_draws

POINTS, DIM, RANK = 6, 2, 2
N = POINTS * DIM


def known_error(seed=0):
    """mu0 (points, dim), W0 (n, 2), d0 (n,) of a synthetic error eps ~ N(mu0, W0 W0^T + diag d0)."""
    g = torch.Generator().manual_seed(seed)
    return (torch.randn(POINTS, DIM, generator=g), torch.randn(N, RANK, generator=g),
            0.05 * torch.ones(N))


def cheap(params):
    """A stand-in model: smooth in K and delta, (points, dim)."""
    t = torch.linspace(0, 1, N).reshape(POINTS, DIM)
    return torch.as_tensor(params["delta"]) * t / torch.as_tensor(params["K"])


def draws_of(num, seed=1):
    priors = {"K": torch.distributions.LogNormal(0.0, 0.3), "delta": torch.distributions.Uniform(2.0, 4.0)}
    return prior_draws(priors, num, seed)


def reference_with(eps):
    """reference = cheap + eps_i for the i-th call (estimate_discrepancy calls it once per draw, in order)."""
    rows = iter(eps)
    return lambda p: cheap(p) + next(rows).reshape(POINTS, DIM)


def gaussian_errors(num, mu0, W0, d0, seed=2):
    g = torch.Generator().manual_seed(seed)
    z = torch.randn(num, RANK, generator=g)
    return mu0.reshape(-1) + z @ W0.T + d0.sqrt() * torch.randn(num, N, generator=g)


def test_mean_and_covariance_recovered_within_sampling_error():
    """n = 4000 draws of eps ~ N(mu0, C), C = W0 W0^T + diag(d0): each mean entry within 4.5
    standard errors sqrt(C_ii / n), each covariance entry within 4.5 sqrt((C_ij^2 + C_ii C_jj) / (n - 1))
    (the sd of a sample covariance); rank 2 by explained variance 0.95 (the two components
    hold ~97.5 % of the variance, tr W0 W0^T ~ 24 against tr diag(d0) = 0.6)."""
    mu0, W0, d0 = known_error()
    n = 4000
    draws = draws_of(n)
    term = estimate_discrepancy(reference_with(gaussian_errors(n, mu0, W0, d0)), cheap, draws, explained=0.95)
    C = W0 @ W0.T + torch.diag(d0)
    assert term.rank == RANK and term.shape == (POINTS, DIM)
    assert term.slope is None and term.num_draws == n
    z_mean = (term.mean.reshape(-1) - mu0.reshape(-1)) / (C.diagonal() / n).sqrt()
    assert float(z_mean.abs().max()) < 4.5
    se = ((C.square() + C.diagonal()[:, None] * C.diagonal()[None, :]) / (n - 1)).sqrt()
    assert float(((term.covariance() - C) / se).abs().max()) < 4.5
    # the diagonal is the residual variance the components leave: d0 = 0.05 within its se
    assert float(((term.diag - d0) / (C.diagonal() * math.sqrt(2 / (n - 1)))).abs().max()) < 4.5
    rms = math.sqrt(float((mu0.square().mean() + C.diagonal().mean())))
    assert term.rms == pytest.approx(rms, rel=0.05)
    assert term.noise_ratio(0.5) == pytest.approx(2 * term.rms, rel=1e-12)


def test_linear_dependence_recovered():
    """eps = mu0 + b0 log K + noise: the linear term's shift at a new K is within 4.5 standard
    errors of the regression prediction sqrt(C_ii x^T (X^T X)^-1 x); the residual covariance
    is C again (each entry within 4.5 sds of a sample covariance), while a constant fit's
    holds var(log K) |b0|^2 more in its trace (10 %)."""
    mu0, W0, d0 = known_error()
    n = 2000
    draws = draws_of(n)
    b0 = 2.0 * torch.randn(N, generator=torch.Generator().manual_seed(5))
    logk = torch.tensor([math.log(float(p["K"])) for p in draws])
    eps = gaussian_errors(n, mu0, W0, d0) + logk[:, None] * b0
    # full rank: the covariance is the sample covariance of the residuals, no truncation
    linear = estimate_discrepancy(reference_with(eps), cheap, draws, rank=N, dependence="linear")
    constant = estimate_discrepancy(reference_with(eps), cheap, draws, rank=N)
    assert linear.names == ("K", "delta")
    at = {"K": torch.tensor(1.7), "delta": torch.tensor(3.3)}
    expected = mu0.reshape(-1) + math.log(1.7) * b0
    X = torch.stack([torch.ones(n), logk - logk.mean(),
                     torch.tensor([math.log(float(p["delta"])) for p in draws]) - linear.centre[1]], 1)
    x = torch.tensor([1.0, math.log(1.7) - float(linear.centre[0]), math.log(3.3) - float(linear.centre[1])])
    C = W0 @ W0.T + torch.diag(d0)
    se = (C.diagonal() * float(x @ torch.linalg.solve(X.T @ X, x))).sqrt()
    assert float(((linear.shift(at).reshape(-1) - expected) / se).abs().max()) < 4.5
    cov_se = ((C.square() + C.diagonal()[:, None] * C.diagonal()[None, :]) / (n - 3)).sqrt()
    assert float(((linear.covariance() - C) / cov_se).abs().max()) < 4.5
    extra = float(constant.covariance().trace() - linear.covariance().trace())
    assert extra == pytest.approx(float(logk.var() * b0.square().sum()), rel=0.1)
    with pytest.raises(ValueError, match="pass params"):
        linear.shift()


def test_prior_draws_are_reproducible_and_named():
    priors = {"K": torch.distributions.LogNormal(0.0, 0.3), "G": torch.distributions.LogNormal(0.0, 0.3)}
    a, b = prior_draws(priors, 5, seed=3, names=["K"]), prior_draws(priors, 5, seed=3, names=["K"])
    assert [list(p) for p in a] == [["K"]] * 5 and all(float(p["K"]) == float(q["K"]) for p, q in zip(a, b))
    with pytest.raises(ValueError, match="no prior for"):
        prior_draws(priors, 5, seed=3, names=["delta"])


def test_reference_of_another_shape_is_refused():
    """A reference observed at other points than the model: an error naming the fix."""
    draws = draws_of(20)
    with pytest.raises(ValueError, match="same .points, dim. entries"):
        estimate_discrepancy(lambda p: torch.zeros(POINTS + 1, DIM), cheap, draws)


def test_nan_and_too_few_draws_are_refused():
    draws = draws_of(MIN_DOF + 1)
    bad = lambda p: torch.full((POINTS, DIM), float("nan"))  # noqa: E731
    with pytest.raises(ValueError, match="reference returned NaN/inf at draw 0"):
        estimate_discrepancy(bad, cheap, draws)
    estimate_discrepancy(cheap, cheap, draws)  # 11 draws: enough for a constant mean
    with pytest.raises(ValueError, match="use at least 13 draws"):
        estimate_discrepancy(cheap, cheap, draws, dependence="linear")
    with pytest.raises(ValueError, match="rank must lie"):
        estimate_discrepancy(cheap, cheap, draws, rank=100)


def test_points_and_shapes_are_checked():
    """A term estimated at some points refuses a scene observed elsewhere or at more points."""
    points = torch.rand(POINTS, 2, generator=torch.Generator().manual_seed(0))
    draws = draws_of(20)
    term = estimate_discrepancy(cheap, cheap, draws, points=points)
    assert term.rms == 0.0 and bool((term.diag == 0).all())
    term.check_points(points)
    with pytest.raises(ValueError, match="other observation points"):
        term.check_points(points + 0.1)
    with pytest.raises(ValueError, match=r"has shape \(7, 2\) but the discrepancy was estimated at 6 points"):
        term.check_points(torch.rand(POINTS + 1, 2))
    with pytest.raises(ValueError, match="model's prediction"):
        term.gaussian(torch.zeros(POINTS, 3))


def test_relative_error_of_a_scaled_model():
    """reference = 1.1 model, model = (delta / K) t: the relative error 0.1 t / rms(t) is the same at
    every draw, so the relative term has that mean and no variance;
    the absolute term's variance is 0.01 var(delta / K) t^2. ``gaussian`` scales the relative
    moments by s = rms(prediction): loc = 1.1 prediction."""
    draws = draws_of(40)
    reference = lambda p: 1.1 * cheap(p)  # noqa: E731
    t = torch.linspace(0, 1, N).reshape(POINTS, DIM)
    relative = estimate_discrepancy(reference, cheap, draws, relative=True)
    assert torch.allclose(relative.mean, 0.1 * t / t.square().mean().sqrt(), rtol=0, atol=1e-12)
    assert float(relative.covariance().abs().max()) < 1e-24
    prediction = cheap(draws[0])
    loc, factor, diag = relative.gaussian(prediction)
    assert torch.allclose(loc, 1.1 * prediction, rtol=1e-12, atol=0)
    absolute = estimate_discrepancy(reference, cheap, draws)
    ratio = torch.tensor([float(p["delta"] / p["K"]) for p in draws])
    # rank 1 holds it all: d is the floor, 1e-6 x the mean variance (~4e-9)
    assert torch.allclose(absolute.covariance().diagonal(), 0.01 * ratio.var() * t.reshape(-1).square(),
                          rtol=1e-9, atol=1e-8)


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


def test_public_names():
    assert {"Discrepancy", "estimate_discrepancy", "prior_draws", "posterior_draws", "gaussian_draws"} <= set(bp.__all__)
