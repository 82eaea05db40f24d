"""Tikhonov inversion (Turner 2015 eq 12): recovery of constants and fields, one adjoint solve per
gradient, Hessian-vector products, and refused input (the choice of psi:
tests/inverse/test_psi_choice.py)."""
import numpy as np
import pytest

from bayespd.inverse.least_squares import ModelErrorWarning, Objective, tikhonov
from tests.conftest import plate_scene
from bayespd.scenes.tikhonov_square import DELTA, K0, MU0, graded_moduli, square_scene

TRUTH = {"K": K0, "G": MU0}


@pytest.mark.parametrize("material", ["lps", "bond"])
def test_recovers_moduli_noise_free(material):
    scene = plate_scene(nx=14, ny=8, material=material)
    truth = {"K": 3000.0, "G": 1400.0} if material == "lps" else {"K": 3000.0}
    y = scene.observe(scene.solve(dict(truth, delta=2.2))).detach()
    init = {k: 0.3 * v for k, v in truth.items()}
    res = tikhonov(scene, y, init, fixed={"delta": 2.2})
    for k, v in truth.items():
        assert abs(res.params[k] - v) / v < 1e-6, (k, res.params[k])
    assert res.evaluations < 100


def test_regularisation_pulls_towards_reference():
    scene = plate_scene(nx=14, ny=8)
    truth = {"K": 3000.0, "G": 1400.0}
    y = scene.observe(scene.solve(dict(truth, delta=2.2))).detach()
    ref = {"K": 2000.0, "G": 1000.0}
    free = tikhonov(scene, y, ref, fixed={"delta": 2.2}, sigma=1e-3)
    strong = tikhonov(scene, y, ref, fixed={"delta": 2.2}, sigma=1e-3, psi=1e12)
    assert abs(free.params["K"] - 3000.0) < 1e-3
    np.testing.assert_allclose([strong.params["K"], strong.params["G"]], [2000.0, 1000.0], rtol=1e-3)


@pytest.fixture(scope="module")
def square():
    """Turner 2015 §4.1: the 11 x 11 square and its manufactured data."""
    scene = square_scene()
    return scene, scene.observe(scene.solve(dict(TRUTH, delta=DELTA))).detach()


@pytest.mark.parametrize("method,hessian", [("L-BFGS-B", "exact"), ("Newton-CG", "gauss-newton"),
                                            ("Newton-CG", "exact")])
def test_recovers_constants_of_the_paper_square(square, method, hessian):
    """§4.1 from (100, 100): double precision on same-model data leaves ~1e-14 (the paper: 6e-7)."""
    scene, y = square
    res = tikhonov(scene, y, {"K": 100.0, "G": 100.0}, fixed={"delta": DELTA}, sigma=1e-3,
                   method=method, hessian=hessian)
    for k, v in TRUTH.items():
        assert abs(res.params[k] - v) / v < 1e-10, (k, res.params[k])
    assert res.converged and len(res.history) == res.iterations
    assert res.history[-1] < 1e-12 * res.history[0]


@pytest.fixture(scope="module")
def small_field():
    """mu(x) of eq 27 on the square at h = 200 (6 x 6 particles), k(x) of eq 26 known."""
    scene = square_scene(h=200.0, delta=600.0)
    truth = graded_moduli(scene.particles.x)
    y = scene.observe(scene.solve(dict(truth, delta=600.0))).detach()
    return scene, truth, y


def test_recovers_a_per_particle_field(small_field):
    scene, truth, y = small_field
    res = tikhonov(scene, y, {"G": np.full(scene.particles.n, MU0)}, fixed={"delta": 600.0, "K": truth["K"]},
                   sigma=1e-3, method="Newton-CG", hessian="gauss-newton")
    assert res.params["G"].shape == (scene.particles.n,)
    np.testing.assert_allclose(res.params["G"], truth["G"].numpy(), rtol=1e-8)


def count_solves(scene, monkeypatch):
    """Count factorisations of K_ff and solves with the factors."""
    counts = {"factorizations": 0, "solves": 0}
    pattern = scene.constraints.pattern
    factorize = pattern.factorize

    def counting(*args, **kw):
        counts["factorizations"] += 1
        factor = factorize(*args, **kw)
        solve = factor.solve

        def counted(b):
            counts["solves"] += 1
            return solve(b)
        factor.solve = counted
        return factor
    monkeypatch.setattr(pattern, "factorize", counting)
    return counts


@pytest.mark.parametrize("field", [False, True])
def test_one_adjoint_solve_per_gradient_whatever_the_unknowns(small_field, monkeypatch, field):
    """Each objective-and-gradient evaluation factorises once and solves twice (forward and
    adjoint, eqs 18-19), for 2 unknowns as for 36; the final residual costs one more of each."""
    scene, truth, y = small_field
    counts = count_solves(scene, monkeypatch)
    n = scene.particles.n
    init = {"K": np.full(n, K0), "G": np.full(n, MU0)} if field else {"K": K0, "G": MU0}
    res = tikhonov(scene, y, init, fixed={"delta": 600.0}, maxiter=3)
    assert res.evaluations >= 3
    assert counts == {"factorizations": res.evaluations + 1, "solves": 2 * res.evaluations + 1}


def test_hessian_vector_product_matches_the_gradient(small_field):
    """Taylor remainder |g(z + e v) - g(z) - e H v| = O(e^2): slope 2 in e, while dropping H v
    leaves slope 1. At noise-free data the residual vanishes at the truth, where the Gauss-Newton
    Hessian (with the penalty's, centred there) equals the exact one."""
    scene, truth, y = small_field
    n = scene.particles.n
    rng = np.random.default_rng(0)
    f = Objective(scene, y, {"G": np.full(n, 1.1 * MU0)}, fixed={"delta": 600.0, "K": truth["K"]},
                  sigma=1e-3, psi=0.3, L="gradient")
    z = f.z0 + 0.05 * rng.standard_normal(n)
    v = rng.standard_normal(n)
    g0, Hv = f(z)[1], f.hessp(z, v)
    eps = np.array([1e-2, 5e-3, 2.5e-3, 1.25e-3])
    second = [np.linalg.norm(f(z + e * v)[1] - g0 - e * Hv) for e in eps]
    first = [np.linalg.norm(f(z + e * v)[1] - g0) for e in eps]
    slope2, slope1 = np.polyfit(np.log(eps), np.log(second), 1)[0], np.polyfit(np.log(eps), np.log(first), 1)[0]
    assert 1.9 < slope2 < 2.1 and 0.9 < slope1 < 1.1, (slope2, slope1)
    kw = {"fixed": {"delta": 600.0, "K": truth["K"]}, "sigma": 1e-3, "psi": 0.3, "L": "gradient"}
    exact = Objective(scene, y, {"G": truth["G"]}, **kw)
    gn = Objective(scene, y, {"G": truth["G"]}, hessian="gauss-newton", **kw)
    np.testing.assert_allclose(gn.hessp(exact.z0, v), exact.hessp(exact.z0, v), rtol=1e-8,
                               atol=1e-10 * np.abs(exact.hessp(exact.z0, v)).max())


def test_bad_input_is_refused(small_field):
    scene, truth, y = small_field
    fixed = {"delta": 600.0, "K": truth["K"]}
    with pytest.raises(ValueError, match="psi for G must be finite and >= 0"):
        tikhonov(scene, y, {"G": MU0}, fixed=fixed, psi=-1.0)
    with pytest.raises(ValueError, match="one value per particle"):
        tikhonov(scene, y, {"G": np.full(5, MU0)}, fixed=fixed)
    with pytest.raises(ValueError, match="per-particle field"):
        tikhonov(scene, y, {"G": MU0}, fixed=fixed, L="gradient")
    with pytest.raises(ValueError, match="positive"):
        tikhonov(scene, y, {"G": -MU0}, fixed=fixed)
    with pytest.raises(ValueError, match="no bounds"):
        tikhonov(scene, y, {"G": MU0}, fixed=fixed, method="Newton-CG", bounds={"G": (1.0, 1e4)})
    bad = y.clone()
    bad[3, 1] = float("nan")
    with pytest.raises(ValueError, match="mask them out"):
        tikhonov(scene, bad, {"G": MU0}, fixed=fixed)


def test_nan_outside_the_mask_is_ignored(square):
    scene, y = square
    mask = np.ones(y.shape, dtype=bool)
    mask[60:70, 0] = False
    holey = y.clone()
    holey[60:70, 0] = float("nan")
    res = tikhonov(scene, holey, {"K": 300.0, "G": 200.0}, fixed={"delta": DELTA}, mask=mask, sigma=1e-3)
    for k, v in TRUTH.items():
        assert abs(res.params[k] - v) / v < 1e-10


@pytest.mark.slow
def test_recovers_the_graded_field_of_the_paper():
    """§4.2 in full: mu(x) of eq 27 at all 121 cells within 0.5 % (paper: 1.2 %)."""
    scene = square_scene()
    truth = graded_moduli(scene.particles.x)
    y = scene.observe(scene.solve(dict(truth, delta=DELTA))).detach()
    res = tikhonov(scene, y, {"G": np.full(scene.particles.n, MU0)}, fixed={"delta": DELTA, "K": truth["K"]},
                   sigma=1e-3, method="Newton-CG", hessian="gauss-newton")
    assert np.abs(res.params["G"] / truth["G"].numpy() - 1).max() < 5e-3


@pytest.mark.parametrize("method", ["L-BFGS-B", "trust-constr"])
def test_bounds_that_exclude_the_truth_are_active(square, method):
    """With G capped below its true value, G ends on the cap and K at its best value for that G
    (a one-parameter fit with G fixed at the cap); trust-constr is the paper's trust-region
    setting (§3.2) with bounds."""
    scene, y = square
    with pytest.warns(ModelErrorWarning, match="model does not fit"):  # the cap keeps the fit 70 sigma rms off
        res = tikhonov(scene, y, {"K": 300.0, "G": 200.0}, fixed={"delta": DELTA}, sigma=1e-3, method=method,
                       hessian="gauss-newton", bounds={"G": (10.0, 350.0)}, gtol=1e-10, maxiter=40)
        best_K = tikhonov(scene, y, {"K": 300.0}, fixed={"delta": DELTA, "G": 350.0}, sigma=1e-3).params["K"]
    assert res.params["G"] == pytest.approx(350.0, rel=1e-6)
    assert res.params["K"] == pytest.approx(best_K, rel=1e-6)


@pytest.fixture(scope="module")
def plate_data():
    """Same-model data on the small plate, and the same with seeded noise of 1e-3 mm."""
    import torch
    scene = plate_scene(nx=14, ny=8)
    y = scene.observe(scene.solve({"K": 3000.0, "G": 1400.0, "delta": 2.2})).detach()
    return scene, y, y + 1e-3 * torch.randn(y.shape, generator=torch.Generator().manual_seed(0))


@pytest.mark.parametrize("unit", [1.0, 1e-3, 1e-6])
def test_bounds_in_any_units_converge_to_the_answer(plate_data, unit):
    """Data in mm, m or km-scaled units with sigma = 1 (J ~ unit^2): the objective is scaled by
    its start, so no absolute threshold ends the run at the start (it used to stop after
    2 evaluations, converged=True, at unit 1e-3 with bounds); the projected gradient or the
    exact-fit test passes (which one depends on the CPU's round-off) and the moduli (scaled by
    1 / unit) are recovered to 1e-8."""
    scene, y, _ = plate_data
    res = tikhonov(scene, y * unit, {"K": 1500.0 / unit, "G": 2000.0 / unit}, fixed={"delta": 2.2},
                   bounds={"K": (300.0 / unit, 3e4 / unit), "G": (140.0 / unit, 1.4e4 / unit)})
    assert res.converged and res.reason.startswith(("projected gradient", "J fell to round-off"))
    assert res.params["K"] * unit == pytest.approx(3000.0, rel=1e-8)
    assert res.params["G"] * unit == pytest.approx(1400.0, rel=1e-8)


def test_noise_free_data_fitted_to_round_off_are_converged_whatever_gtol(plate_data):
    """With gtol = 1e-30 (no gradient test can pass) the same-model fit still ends converged,
    by the exact-fit test J <= eps J0, at the truth; noisy data under the same settings do not
    (their J has a positive minimum: the stall test below)."""
    scene, y, _ = plate_data
    res = tikhonov(scene, y, {"K": 1500.0, "G": 2000.0}, fixed={"delta": 2.2}, gtol=1e-30, ftol=1e-300)
    assert res.converged and res.reason.startswith("J fell to round-off")
    assert res.params["K"] == pytest.approx(3000.0, rel=1e-8) and res.params["G"] == pytest.approx(1400.0, rel=1e-8)


@pytest.mark.parametrize("method", ["L-BFGS-B", "Newton-CG"])
def test_a_stall_at_the_round_off_floor_is_not_converged(plate_data, method):
    """gtol and ftol below round-off cannot pass: the run stops at the (noisy-data) optimum,
    after `stall` evaluations without progress or (by the CPU's round-off) when the line search
    gets lost there (the project's monitor, or scipy's own round-off stops: an L-BFGS-B
    iteration that leaves J unchanged, a Newton-CG line search losing precision), and says so
    instead of claiming success."""
    scene, _, noisy = plate_data
    best = tikhonov(scene, noisy, {"K": 1500.0, "G": 2000.0}, fixed={"delta": 2.2})
    res = tikhonov(scene, noisy, {"K": 1500.0, "G": 2000.0}, fixed={"delta": 2.2}, gtol=1e-30,
                   ftol=1e-300, stall=10, method=method)
    assert best.converged and not res.converged
    assert res.reason.startswith(("stalled: 10 evaluations", "the optimiser proposed",
                                  "the optimiser stopped at J's round-off floor")) and "raise gtol or ftol" in res.reason
    assert res.params["K"] == pytest.approx(best.params["K"], rel=1e-6)


def test_maxfun_ends_the_run_unconverged(plate_data):
    scene, _, noisy = plate_data
    res = tikhonov(scene, noisy, {"K": 1500.0, "G": 2000.0}, fixed={"delta": 2.2}, maxfun=5)
    assert not res.converged and res.reason == "maxfun=5 evaluations spent: raise maxfun"
    assert res.evaluations <= 5


@pytest.mark.parametrize("kw,match", [({"gtol": 0.0}, "gtol must be positive"), ({"ftol": -1.0}, "ftol must be positive"),
                                      ({"maxfun": 1}, "maxfun must be an integer >= 2"),
                                      ({"stall": 1.5}, "stall must be an integer")])
def test_bad_stopping_controls_are_refused_by_name(plate_data, kw, match):
    scene, y, _ = plate_data
    with pytest.raises((ValueError, TypeError), match=match):
        tikhonov(scene, y, {"K": 1500.0, "G": 2000.0}, fixed={"delta": 2.2}, **kw)


def test_runs_on_a_held_reduced_scene():
    """Tikhonov on ``bp.Held(bp.ReducedScene(...), delta=...)`` (the objective calls the scene's
    ``predict``): same-model data from the full scene are recovered to the reduced basis's
    observation error, 1e-6 of max |u| by construction, i.e. ~1e-6 relative on K and G (1e-5
    allowed: the moduli are no better informed than the data's scale)."""
    import bayespd as bp
    scene = plate_scene(nx=14, ny=8)
    truth = {"K": 3000.0, "G": 1400.0}
    y = scene.observe(scene.solve(dict(truth, delta=2.2))).detach()
    rng = np.random.default_rng(0)
    draws = [{"K": 3000.0 * np.exp(rng.normal(0, 0.5)), "G": 1400.0 * np.exp(rng.normal(0, 0.5)), "delta": 2.2}
             for _ in range(16)]
    reduced = bp.Held(bp.ReducedScene(scene, draws, 1e-6 * float(y.abs().max()), delta_range=(2.2 * (1 - 1e-6), 2.2)),
                      delta=2.2)
    res = tikhonov(reduced, y, {"K": 2000.0, "G": 1000.0}, sigma=1e-3)
    for k, v in truth.items():
        assert abs(res.params[k] / v - 1) < 1e-5
