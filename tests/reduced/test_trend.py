"""bayespd/reduced/trend.py: the smooth trend reproduces quadratics in its features, its
leave-one-out errors are those of refits, it follows a strongly nonlinear error and stays twice
differentiable; the relative error of a loaded plate depends on the moduli through G / K only."""
import math

import pytest
import torch

import bayespd as bp
from bayespd.reduced.discrepancy import estimate_discrepancy
from tests.conftest import plate_scene
from tests.reduced.test_discrepancy import DIM, N, POINTS, cheap, draws_of


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


def test_elastic_features_without_delta_are_the_scale_free_ratio_alone():
    """With delta held (bp.Held) the features are (log(G / K),): unchanged when K, G scale."""
    f = bp.ElasticFeatures(with_delta=False)
    a, b = f({"K": 2.0, "G": 1.0}), f({"K": 2e4, "G": 1e4})
    assert a.shape == (1,) and torch.equal(a, b) and float(a) == pytest.approx(math.log(0.5), abs=1e-15)
    assert bp.ElasticFeatures()({"K": 2.0, "G": 1.0, "delta": 3.0}).tolist() == pytest.approx([math.log(0.5), 3.0])
