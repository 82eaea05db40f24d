"""bayespd/reduced/discrepancy.py: the approximation-error term recovers the mean, covariance
and linear dependence of a known Gaussian error within sampling error, and refuses bad input."""
import math

import pytest
import torch

import bayespd as bp
from bayespd.reduced.discrepancy import MIN_DOF, estimate_discrepancy
from bayespd.reduced.draws import prior_draws

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


def test_public_names():
    assert {"Discrepancy", "estimate_discrepancy", "prior_draws", "posterior_draws", "gaussian_draws", "LogFeatures",
            "ElasticFeatures"} <= set(bp.__all__)


def test_with_errors_adds_their_second_moment():
    """Rows E (m, n) add (1/m) E^T E to the covariance (low rank), and with ``spread`` also their
    mean square to every diagonal entry; the mean and trend are untouched; bad rows are refused."""
    draws = draws_of(20)
    term = estimate_discrepancy(lambda p: 1.1 * cheap(p), cheap, draws, relative=True)
    errors = torch.randn(3, N, generator=torch.Generator().manual_seed(4), dtype=torch.float64)
    second = errors.T @ errors / 3
    wider = term.with_errors(errors)
    assert wider.rank == term.rank + 3 and torch.equal(wider.mean, term.mean)
    assert torch.allclose(wider.covariance(), term.covariance() + second, rtol=0, atol=1e-12)
    spread = term.with_errors(errors, spread=True)
    assert torch.allclose(spread.covariance(), term.covariance() + second + errors.square().mean() * torch.eye(N),
                          rtol=0, atol=1e-12)
    with pytest.raises(ValueError, match=r"errors must be \(m >= 1, 12\)"):
        term.with_errors(errors[:, :5])
    with pytest.raises(ValueError, match="put 0 where an entry has no error"):
        term.with_errors(torch.full((1, N), float("nan")))
