"""bayespd/reduced/discrepancy.py, draws.py, trend.py: the approximation-error term recovers the mean,
covariance and linear dependence of a known Gaussian error within sampling error, its smooth trend
reproduces quadratics and leaves honest leave-one-out errors, and it refuses bad input."""
import math

import pytest
import torch

import bayespd as bp
from bayespd.infer.datatree import build_tree
from bayespd.reduced.discrepancy import MIN_DOF, estimate_discrepancy
from bayespd.reduced.draws import gaussian_draws, posterior_draws, prior_draws
from tests.conftest import plate_scene

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
    assert term.trend is None and term.num_draws == n
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
    assert linear.trend.features == bp.LogFeatures(("K", "delta"))
    at = {"K": torch.tensor(1.7), "delta": torch.tensor(3.3)}
    expected = mu0.reshape(-1) + math.log(1.7) * b0
    X = torch.stack([torch.ones(n), logk - logk.mean(),
                     torch.tensor([math.log(float(p["delta"])) for p in draws]) - linear.trend.centre[1]], 1)
    x = torch.tensor([1.0, math.log(1.7) - float(linear.trend.centre[0]), math.log(3.3) - float(linear.trend.centre[1])])
    C = W0 @ W0.T + torch.diag(d0)
    se = (C.diagonal() * float(x @ torch.linalg.solve(X.T @ X, x))).sqrt()
    assert float(((linear.shift(at).reshape(-1) - expected) / se).abs().max()) < 4.5
    cov_se = ((C.square() + C.diagonal()[:, None] * C.diagonal()[None, :]) / (n - 3)).sqrt()
    assert float(((linear.covariance() - C) / cov_se).abs().max()) < 4.5
    extra = float(constant.covariance().trace() - linear.covariance().trace())
    assert extra == pytest.approx(float(logk.var() * b0.square().sum()), rel=0.1)
    with pytest.raises(ValueError, match="pass params"):
        linear.shift()


def smooth_error(params):
    """A strongly nonlinear error: eps(K, delta) = sin(3 delta) a + (log K)^2 b + 0.1."""
    t = torch.linspace(-1, 1, N)
    return (torch.sin(3 * torch.as_tensor(params["delta"])) * t + torch.log(torch.as_tensor(params["K"])) ** 2
            * t.cos() + 0.1).reshape(POINTS, DIM)


def test_smooth_trend_reproduces_quadratics_and_its_leave_one_out_errors_are_refits():
    """The polyharmonic interpolant with its quadratic block reproduces a quadratic in the
    features (log K, log delta) exactly (a new point to 1e-8; every leave-one-out error ~0), and Rippa's
    leave-one-out errors a_i / (A^-1)_ii equal those of refitting without draw i (1e-8)."""
    draws = draws_of(30)
    quadratic = lambda p: cheap(p) + (math.log(float(p["K"])) * math.log(float(p["delta"]))) * torch.ones(POINTS, DIM)  # noqa: E731
    exact = estimate_discrepancy(quadratic, cheap, draws, dependence="smooth", rank=0)
    at = {"K": torch.tensor(1.3), "delta": torch.tensor(2.5)}
    assert float((exact.shift(at) - math.log(1.3) * math.log(2.5)).abs().max()) < 1e-8
    assert float(exact.diag.max()) < 1e-12
    from bayespd.reduced.trend import _kernel, _monomials, fit_smooth
    E = torch.stack([(smooth_error(p)).reshape(-1) for p in draws])
    trend, loo, dof = fit_smooth(bp.LogFeatures(("K", "delta")), draws, E)
    assert dof == len(draws)
    x = trend.nodes  # the standardised features; the refit keeps their metric
    for i in (0, 7, 29):
        keep = torch.arange(len(draws)) != i
        P = _monomials(x[keep])
        m = P.shape[1]
        A = torch.cat([torch.cat([_kernel(x[keep], x[keep]), P], 1), torch.cat([P.T, torch.zeros(m, m)], 1)])
        a = torch.linalg.solve(A, torch.cat([E[keep], torch.zeros(m, N)]))
        refit = _kernel(x[i], x[keep]) @ a[:-m] + _monomials(x[i]) @ a[-m:]
        torch.testing.assert_close(E[i] - refit, loo[i], rtol=0, atol=1e-8)


def test_smooth_trend_follows_a_nonlinear_error_and_stays_twice_differentiable():
    """eps = sin(3 delta) a + (log K)^2 b + 0.1, no noise, 120 draws: at 200 new draws the smooth
    trend's error is below 10 % of eps's rms and within a factor 2 of its leave-one-out rms (an
    estimate of the same out-of-sample error), while the linear trend leaves > 50 %; the
    likelihood's Hessian in delta is finite at a node (r^5: C^4) and matches central
    differences of its gradient to 1e-5."""
    draws, new = draws_of(120, seed=4), draws_of(200, seed=9)
    reference = lambda p: cheap(p) + smooth_error(p)  # noqa: E731
    smooth = estimate_discrepancy(reference, cheap, draws, dependence="smooth", rank=N)
    linear = estimate_discrepancy(reference, cheap, draws, dependence="linear", rank=N)
    truth = torch.stack([smooth_error(p) for p in new])
    rms = float(truth.square().mean().sqrt())
    held_out = lambda term: float((torch.stack([term.shift(p) for p in new]) - truth).square().mean().sqrt())  # noqa: E731
    loo_rms = math.sqrt(float(smooth.covariance().trace()) / N)
    assert held_out(smooth) < 0.1 * rms and 0.5 < held_out(smooth) / loo_rms < 2.0  # measured 4.6 %, 0.68
    assert held_out(linear) > 0.5 * rms  # measured 77 %

    def shift_at(delta):
        return smooth.shift({"K": draws[0]["K"], "delta": delta}).square().sum()

    delta = torch.as_tensor(float(draws[0]["delta"]), dtype=torch.float64)
    hessian = torch.autograd.functional.hessian(shift_at, delta)
    step = 1e-5
    grad = lambda d: torch.autograd.grad(shift_at(d.requires_grad_()), d)[0]  # noqa: E731
    fd = (grad(delta + step) - grad(delta - step)) / (2 * step)
    assert bool(torch.isfinite(hessian)) and float(abs(hessian - fd)) < 1e-5 * max(1.0, float(abs(fd)))


def test_smooth_trend_refuses_a_constant_feature_and_too_few_draws():
    draws = [{"K": torch.tensor(1.0), "delta": p["delta"]} for p in draws_of(20)]
    with pytest.raises(ValueError, match="takes one value over every draw"):
        estimate_discrepancy(cheap, cheap, draws, dependence="smooth")
    with pytest.raises(ValueError, match="features are used by dependence='linear' or 'smooth' only"):
        estimate_discrepancy(cheap, cheap, draws, features=bp.LogFeatures(("K",)))
    with pytest.raises(ValueError, match="every value must be positive"):
        bp.LogFeatures(("K",))({"K": torch.tensor(-1.0)})


def test_relative_error_of_a_loaded_plate_depends_on_the_moduli_through_their_ratio():
    """Plates under prescribed loads: u(c K, c G) = u(K, G) / c in both models, so the relative
    error eps / rms(model) is the same at (K, G) and (3 K, 3 G) (1e-10), and so are its
    ElasticFeatures (log(G / K), delta): the two features a smooth trend needs."""
    coarse, fine = plate_scene(nx=10, ny=6, h=1.0), plate_scene(nx=20, ny=12, h=0.5)
    fine = bp.Scene(fine.material, fine.dirichlet, fine.loads, bp.Observation(fine.particles, coarse.observation.points))

    def relative_error(params):
        with torch.no_grad():
            m = coarse.predict(params)
            return (fine.predict(params) - m) / m.square().mean().sqrt()

    at = {"K": torch.tensor(2.0e3), "G": torch.tensor(0.9e3), "delta": torch.tensor(2.2)}
    scaled = {**at, "K": 3 * at["K"], "G": 3 * at["G"]}
    torch.testing.assert_close(relative_error(scaled), relative_error(at), rtol=1e-10, atol=1e-12)
    assert float(relative_error(at).abs().max()) > 1e-3  # a real discretisation error
    torch.testing.assert_close(bp.ElasticFeatures()(scaled), bp.ElasticFeatures()(at))


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
    assert {"Discrepancy", "estimate_discrepancy", "prior_draws", "posterior_draws", "gaussian_draws", "LogFeatures",
            "ElasticFeatures"} <= set(bp.__all__)
