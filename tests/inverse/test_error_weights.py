"""``bayespd.inverse.error_weights`` and ``tikhonov(..., discrepancy=)``: the whitened residual is
the generalised least squares of the approximation-error term, and the weighted Tikhonov
removes a model error that biases the plain one (the FE-field case: test_tikhonov_fe_field.py)."""
import numpy as np
import pytest
import torch

import bayespd as bp
from bayespd.inverse.error_weights import ErrorWeights
from bayespd.inverse.least_squares import tikhonov
from tests.conftest import plate_scene


def test_whitened_residual_is_the_generalised_least_squares():
    """||C^-1/2 r||^2 = r^T C^-1 r with C = s0^2 (W W^T + diag d) + sigma^2 I on the observed
    entries and r = prediction + s mu - y (relative term): against the dense inverse, to round-off."""
    rng = np.random.default_rng(3)
    points, k, sigma = 30, 4, 0.3
    term = bp.Discrepancy(mean=torch.as_tensor(rng.normal(size=(points, 2))) * 0.01,
                          factor=torch.as_tensor(rng.normal(size=(2 * points, k))) * 0.05,
                          diag=torch.as_tensor(rng.uniform(1e-4, 1e-3, 2 * points)), rms=0.05, explained=0.9,
                          num_draws=20, relative=True)
    observed = torch.as_tensor(rng.uniform(size=(points, 2)) > 0.2)
    pred0, pred, y = (torch.as_tensor(rng.normal(size=(points, 2))) for _ in range(3))
    weights = ErrorWeights(term, observed, sigma, pred0, {})
    white = weights(pred, {}, y)
    s0, s = (float(p.square().mean().sqrt()) for p in (pred0, pred))
    keep = observed.reshape(-1).numpy()
    C = s0**2 * term.covariance().numpy()[np.ix_(keep, keep)] + sigma**2 * np.eye(keep.sum())
    r = (pred + s * term.mean - y).reshape(-1).numpy()[keep]
    assert float(white @ white) == pytest.approx(r @ np.linalg.solve(C, r), rel=1e-12)


@pytest.fixture(scope="module")
def model_error():
    """Data from the plate at delta = 2.9 calibrated at delta = 2.2 (a model error of 2 % rms),
    with the term of that error from 13 draws of G / K in [0.2, 0.8] (smooth trend)."""
    scene = plate_scene(nx=14, ny=8, delta_max=3.0)

    def observe(delta, params):
        with torch.no_grad():
            return scene.observe(scene.solve(dict(params, delta=delta)))

    ratios = np.linspace(0.2, 0.8, 13)
    draws = [{"K": 3000.0, "G": 3000.0 * r} for r in ratios]
    term = bp.estimate_discrepancy(lambda p: observe(2.9, p), lambda p: observe(2.2, p), draws, dependence="smooth",
                                   features=bp.ElasticFeatures(with_delta=False), relative=True, explained=0.9999,
                                   points=scene.observation.points)
    return scene, observe, term, ratios


@pytest.mark.parametrize("truth,tol", [({"K": 3000.0, "G": 1500.0}, 1e-7), ({"K": 2000.0, "G": 940.0}, 1e-5)])
def test_weighted_tikhonov_removes_the_model_error(model_error, truth, tol):
    """At a design point of the term (G / K = 0.5) the smooth trend reproduces the error exactly,
    so the weighted misfit is 0 at the truth: only the optimiser's stopping is left (1e-7). Between
    design points (G / K = 0.47, E 2000) the trend's interpolation error is left (measured 6e-10;
    1e-5 allowed). The plain misfit misses by 0.4-1.7 % (the test's power)."""
    scene, observe, term, _ = model_error
    y = observe(2.9, truth)
    init = {k: 0.7 * v for k, v in truth.items()}
    plain = tikhonov(scene, y, init, fixed={"delta": 2.2}, sigma=1e-3)
    weighted = tikhonov(scene, y, init, fixed={"delta": 2.2}, sigma=0.0, discrepancy=term)
    assert max(abs(plain.params[k] / v - 1) for k, v in truth.items()) > 4e-3
    for k, v in truth.items():
        assert abs(weighted.params[k] / v - 1) < tol


@pytest.mark.parametrize("hessian", ["gauss-newton", "exact"])
def test_weighted_newton_cg_reaches_the_truth_with_either_hessian(model_error, hessian):
    """The whitened residual (C^-1/2 r) keeps Gauss-Newton's J_r^T J_r the misfit's Hessian at a
    zero residual: Newton-CG with the Gauss-Newton or the exact Hessian-vector products reaches
    the truth at a design point of the term as L-BFGS-B does (1e-7), and says it converged: the
    covariance refresh does not rerun from an exact fit (J on its round-off floor, where the
    rerun's relative tests failed with a projected gradient of 1e12-1e13 before)."""
    scene, observe, term, _ = model_error
    truth = {"K": 3000.0, "G": 1500.0}
    init = {k: 0.7 * v for k, v in truth.items()}
    fit = tikhonov(scene, observe(2.9, truth), init, fixed={"delta": 2.2}, sigma=1e-3, discrepancy=term,
                   method="Newton-CG", hessian=hessian)
    assert fit.converged, fit.reason
    for k, v in truth.items():
        assert abs(fit.params[k] / v - 1) < 1e-7


def test_zero_sigma_needs_a_discrepancy(model_error):
    scene, observe, term, _ = model_error
    y = observe(2.9, {"K": 3000.0, "G": 1500.0})
    with pytest.raises(ValueError, match="0 only with a discrepancy"):
        tikhonov(scene, y, {"K": 2000.0, "G": 1000.0}, fixed={"delta": 2.2}, sigma=0.0)
