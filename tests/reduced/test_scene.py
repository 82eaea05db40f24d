"""The reduced scene: observations within the tolerance at draws it was not built from,
derivatives that pass the finite-difference check (Taylor remainder of second order), the
prescribed-displacement part of the load, and the refusals that name their fix."""
import numpy as np
import pytest
import torch

import bayespd as bp
from bayespd.reduced import ReducedScene, ToleranceMissed

K0, G0 = 3000.0, 1400.0


def plate(h=1.0, delta_max=3.0, rule="smooth", material=bp.LPS, pulled=False, solver="direct", **options):
    """A 20 x 10 plate clamped on the left, loaded (or, ``pulled``, displaced) on the right."""
    p = bp.grid_2d(20.0, 10.0, h)
    mat = material(p, bp.find_bonds(p, delta_max, rule), plane="stress", **options)
    clamp = [bp.Dirichlet.layer(p, "left", delta_max)]
    if pulled:
        clamp.append(bp.Dirichlet.layer(p, "right", delta_max, (0.02, None)))
    loads = [] if pulled else [bp.Load(p.layer("right", h), (40.0, 15.0))]
    obs = bp.Observation(p, p.x[(p.x[:, 0] > delta_max) & (p.x[:, 0] < 20.0 - delta_max)])
    return bp.Scene(mat, clamp, loads, obs, solver=solver)


def draws(scene, n, seed):
    """Prior-like draws: moduli log-normal about (K0, G0), delta uniform in [h, delta_max]."""
    g = torch.Generator().manual_seed(seed)
    h, top = scene.particles.h, scene.material.bonds.delta_max
    out = []
    for _ in range(n):
        z = torch.randn(2, generator=g, dtype=torch.float64)
        d = h + (top - h) * float(torch.rand(1, generator=g, dtype=torch.float64))
        params = {"K": K0 * float(torch.exp(0.3 * z[0])), "delta": d}
        if "G" in scene.param_names:
            params["G"] = G0 * float(torch.exp(0.3 * z[1]))
        out.append(params)
    return out


def observation_scale(scene):
    with torch.no_grad():
        return float(scene.predict({k: v for k, v in {"K": K0, "G": G0, "delta": 2.0}.items()
                                    if k in scene.param_names}).abs().max())


@pytest.fixture(scope="module")
def built():
    scene = plate()
    tolerance = 5e-4 * observation_scale(scene)
    return scene, ReducedScene(scene, draws(scene, 32, seed=0), tolerance), tolerance


def test_observations_within_tolerance_at_new_draws(built):
    """Draws the basis never saw: the error stays within twice the tolerance the held-out
    draws certified (the rank is chosen on 4 of them, so allow that sampling slack)."""
    scene, rom, tolerance = built
    assert rom.report["validation_error_max"] <= tolerance
    for params in draws(scene, 6, seed=7):
        with torch.no_grad():
            error = float((rom.predict(params) - scene.predict(params)).abs().max())
        assert error <= 2 * tolerance, (params, error / tolerance)


def test_full_field_matches_observations(built):
    scene, rom, _ = built
    params = draws(scene, 1, seed=3)[0]
    with torch.no_grad():
        torch.testing.assert_close(rom.observe(rom.solve(params)), rom.predict(params), rtol=1e-12, atol=1e-14)


def test_derivatives_pass_gradcheck_twice(built):
    """First and second derivatives in K, G and delta against central differences."""
    _, rom, _ = built
    weights = torch.randn(rom.observation.n, 2, generator=torch.Generator().manual_seed(2), dtype=torch.float64)

    def functional(K, G, delta):
        return (weights * rom.predict({"K": 1e3 * K, "G": 1e3 * G, "delta": delta})).sum()

    x = tuple(torch.tensor(v, requires_grad=True) for v in (3.1, 1.3, 2.05))
    assert torch.autograd.gradcheck(functional, x, eps=1e-6, atol=1e-8, rtol=1e-5)
    assert torch.autograd.gradgradcheck(functional, x, eps=1e-6, atol=1e-7, rtol=1e-4)


def test_prescribed_displacement_and_load_factor():
    """Displacement control: the load vector -K_fc u_c is split like K; a load factor scales
    the (here absent) loads only."""
    scene = plate(pulled=True)
    tolerance = 5e-4 * observation_scale(scene)
    rom = ReducedScene(scene, draws(scene, 36, seed=1), tolerance)
    for params in draws(scene, 3, seed=8):
        with torch.no_grad():
            error = float((rom.predict({**params, "load": 2.0}) - scene.predict(params)).abs().max())
        assert error <= 2 * tolerance


def test_a_pcg_scene_reduces_to_the_same_model(built):
    """Snapshots by PCG (large systems), its preconditioner in the estimator: the same
    observations as the direct scene's reduced model, and an estimate within a factor 2."""
    scene, rom, tolerance = built
    pcg = ReducedScene(plate(solver="pcg"), draws(scene, 32, seed=0), tolerance)
    assert pcg.rank == rom.rank
    for params in draws(scene, 3, seed=7):
        with torch.no_grad():
            torch.testing.assert_close(pcg.predict(params), rom.predict(params), rtol=0, atol=1e-3 * tolerance)
            error = float((pcg.predict(params) - scene.predict(params)).abs().max())
        assert 0.5 < pcg.error_estimate(params) / error < 2.0


def test_bond_based_law_has_one_term():
    scene = plate(material=bp.BondBased)
    tolerance = 5e-4 * observation_scale(scene)
    rom = ReducedScene(scene, draws(scene, 24, seed=4), tolerance)
    params = draws(scene, 1, seed=9)[0]
    with torch.no_grad():
        assert float((rom.predict(params) - scene.predict(params)).abs().max()) <= 2 * tolerance


@pytest.mark.filterwarnings("ignore:the reduced model's estimated observation error")
def test_draws_outside_the_snapshots_moduli_are_counted(built):
    scene, rom, _ = built
    inside, outside = {"K": K0, "G": G0, "delta": 2.0}, {"K": K0, "G": 20 * G0, "delta": 2.0}
    arrays = {k: np.array([[inside[k], outside[k], outside[k]]]) for k in inside}
    with pytest.warns(UserWarning, match="2 of 3 draws have moduli whose ratios leave.*rebuild it"):
        rom.diagnostics(arrays)


def test_refusals_name_the_fix(built):
    scene, rom, tolerance = built
    with pytest.raises(ValueError, match="outside the range.*rebuild"):
        rom.predict({"K": K0, "G": G0, "delta": 3.5})
    with pytest.raises(ValueError, match="homogeneous K.*full model"):
        rom.predict({"K": torch.full((scene.particles.n,), K0), "G": G0, "delta": 2.0})
    with pytest.raises(ValueError, match="give more draws"):
        ReducedScene(scene, draws(scene, 8, seed=0), tolerance)  # 4 snapshots: too few
    with pytest.raises(ValueError, match="held out"):
        ReducedScene(scene, draws(scene, 6, seed=0), tolerance)
    with pytest.raises(ValueError, match="surface_correction=False"):
        ReducedScene(plate(surface_correction=True), draws(scene, 24, seed=0), tolerance)


def test_from_sampler_grows_the_draws_until_the_basis_meets_the_tolerance(built):
    """8 draws (4 snapshots) miss the fixture's tolerance, 32 meet it: ``from_sampler`` asks for
    8, then 32, and builds the fixture's model; with 8 alone the miss is raised."""
    scene, rom, tolerance = built
    asked = []

    def sample(n):
        asked.append(n)
        return draws(scene, n, seed=0)

    grown = ReducedScene.from_sampler(scene, sample, tolerance, counts=(8, 32))
    assert asked == [8, 32] and grown.rank == rom.rank
    assert grown.report["validation_error_max"] == rom.report["validation_error_max"]
    with pytest.raises(ToleranceMissed, match="give more draws"):
        ReducedScene.from_sampler(scene, sample, tolerance, counts=(8,))
    with pytest.raises(ValueError, match="counts is empty"):
        ReducedScene.from_sampler(scene, sample, tolerance, counts=())


def test_a_fit_reports_the_error_estimate_per_draw(built):
    """A Pyro model on the reduced scene: ``fit`` stores the estimate in ``sample_stats`` at
    ``estimates`` evenly spaced draws, and it agrees with the true error there."""
    from bayespd.infer import fit
    from bayespd.models.elastic_plate import elastic_plate

    scene, rom, tolerance = built
    truth = {"K": K0, "G": G0, "delta": 2.2}
    with torch.no_grad():
        clean = scene.predict(truth)
    sigma = 0.01 * float(clean.abs().max())
    y = clean + sigma * torch.randn(clean.shape, generator=torch.Generator().manual_seed(5), dtype=torch.float64)
    rom.estimates, saved = 5, rom.estimates
    try:
        tree = fit(elastic_plate(rom, {"K": K0, "G": G0}, 5 * sigma), {"y": y}, "laplace", num_samples=20,
                   seed=0, progress=False)
    finally:
        rom.estimates = saved
    estimate = tree["sample_stats"]["reduced_error_estimate"].values
    assert estimate.shape == (1, 20) and int(np.isfinite(estimate).sum()) == 5
    post = tree["posterior"]
    for i in np.flatnonzero(np.isfinite(estimate[0])):
        params = {k: float(post[k].values[0, i]) for k in ("K", "G", "delta")}
        with torch.no_grad():
            error = float((rom.predict(params) - scene.predict(params)).abs().max())
        assert 0.5 < estimate[0, i] / error < 2.0
