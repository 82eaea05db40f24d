"""Property-based tests (hypothesis) of the public API under bad and extreme input (issue 27):
NaN, +-inf, 0, negatives, huge and tiny finite values for Dirichlet values, loads, load
factors, moduli, delta, h, particle coordinates, observation points and fit settings. Each
property holds one of two outcomes: the value is refused by a ``ValueError`` / ``TypeError``
(or a bayespd error class) raised in bayespd code whose message names the parameter, or the
result is finite and passes a physical check (linearity in the load and the prescribed
displacement, 1/K scaling and positive energy, exact interpolation of an affine field).
Never NaN out, never a raw exception from a dependency. Scenes are built once per module."""
import math
import traceback
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings, strategies as st

import bayespd as bp
from bayespd.infer import HMC, NUTS, SVI, Laplace

from tests.conftest import plate_scene

PACKAGE = Path(bp.__file__).resolve().parent
SETTINGS = settings(max_examples=20, deadline=None, derandomize=True,
                    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
EXTREMES = [math.nan, math.inf, -math.inf, 0.0, -0.0, -1.0, 1e-300, -1e-300, 5e-324, 1e300, -1e300,
            1.7976931348623157e308, 1e-8, 1e8]
TINY = 1e-290  # below it, results are subnormal and carry few significant digits: compared absolutely
# every float, NaN and +-inf included, plus the extremes above (drawn often)
numbers = st.one_of(st.sampled_from(EXTREMES), st.floats(allow_nan=True, allow_infinity=True))


def refused(call, *names, errors=(ValueError, TypeError)):
    """``call()``'s result, or None when it raised one of ``errors`` from a bayespd frame with a
    message naming one of ``names`` (case-insensitive); anything else fails the test."""
    try:
        return call()
    except errors as error:
        frames = traceback.extract_tb(error.__traceback__)
        assert any(Path(f.filename).resolve().is_relative_to(PACKAGE) for f in frames[-1:]), \
            f"{type(error).__name__} raised outside bayespd: {error}\n{''.join(traceback.format_tb(error.__traceback__))}"
        message = str(error).lower()
        assert any(n.lower() in message for n in names), f"the message does not name {names}: {error}"
        return None


@pytest.fixture(scope="module")
def plate():
    """The conftest plate (10 x 6, LPS, clamped left, pulled right), its parts and the solve
    at the nominal params."""
    scene = plate_scene()
    p, mat = scene.particles, scene.material
    params = {"K": 1000.0, "G": 600.0, "delta": 2.0}
    return p, mat, scene, params, scene.solve(params)


def assert_linear(u, u1, factor):
    """u == factor * u1 to rounding (where factor * u1 is representable)."""
    assert torch.isfinite(u).all()
    scale = float(u1.abs().max()) * abs(factor)
    torch.testing.assert_close(u, factor * u1, rtol=1e-9, atol=max(1e-12 * scale, TINY))


@SETTINGS
@given(factor=numbers)
def test_load_factor_scales_the_displacement(plate, factor):
    p, mat, scene, params, u1 = plate
    u = refused(lambda: scene.solve(dict(params, load=factor)), "load factor", "load")
    if u is not None:
        assert_linear(u, u1, factor)


@SETTINGS
@given(fx=numbers, fy=numbers)
def test_a_load_is_refused_or_moves_the_plate_linearly(plate, fx, fy):
    p, mat, scene, params, _ = plate
    load = refused(lambda: bp.Load(p.layer("right", 1.0), (fx, fy)), "load")
    if load is None:
        return
    s = refused(lambda: bp.Scene(mat, scene.dirichlet, [load]), "load", "nothing loads")
    if s is None:
        assert fx == 0 and fy == 0
        return
    u = refused(lambda: s.solve(params), "load", "K contains", "displacement")
    if u is not None:
        unit = bp.Scene(mat, scene.dirichlet, [bp.Load(p.layer("right", 1.0), (1.0, 0.0))]).solve(params)
        other = bp.Scene(mat, scene.dirichlet, [bp.Load(p.layer("right", 1.0), (0.0, 1.0))]).solve(params)
        expected = fx * unit + fy * other
        assert torch.isfinite(u).all()
        torch.testing.assert_close(u, expected, rtol=1e-8, atol=max(1e-10 * float(expected.abs().max()), TINY))
        work = float(((u / u.abs().max()) * (s.force / s.force.abs().max())).sum())  # f.u = u^T K u >= 0
        assert work >= 0


@SETTINGS
@given(value=numbers)
def test_a_dirichlet_value_is_refused_or_prescribes_a_linear_solution(plate, value):
    """Displacement control: the right layer pulled by ``value``, the left clamped."""
    p, mat, scene, params, _ = plate
    bc = refused(lambda: bp.Dirichlet.layer(p, "right", 2.5, (value, 0.0)), "dirichlet value")
    if bc is None:
        return
    build = lambda v: bp.Scene(mat, [scene.dirichlet[0], bp.Dirichlet.layer(p, "right", 2.5, (v, 0.0))])
    s = refused(lambda: build(value), "nothing loads", "dirichlet")
    if s is None:
        assert value == 0
        return
    u = refused(lambda: s.solve(params), "dirichlet", "displacement")
    if u is not None:
        assert_linear(u, build(1.0).solve(params), value)


@SETTINGS
@given(K=numbers, ratio=st.sampled_from([0.6, 1e-6, 1.0, 1e3]))
def test_moduli_are_refused_or_scale_the_displacement_as_one_over_K(plate, K, ratio):
    """u(K, ratio K) = u(1, ratio) / K; the work f.u = u^T K u > 0."""
    p, mat, scene, params, _ = plate
    u = refused(lambda: scene.solve({"K": K, "G": ratio * K, "delta": 2.0}), "K ", "G ", "K contains", "G contains",
                "moduli", "stiffness")
    if u is not None:
        unit = scene.solve({"K": 1.0, "G": ratio, "delta": 2.0})
        assert torch.isfinite(u).all() and float((u * scene.force).sum()) > 0
        torch.testing.assert_close(u * K, unit, rtol=1e-7, atol=max(1e-12 * float(unit.abs().max()), TINY * K))


@SETTINGS
@given(delta=numbers)
def test_delta_is_refused_or_in_the_bond_range(plate, delta):
    p, mat, scene, params, _ = plate
    u = refused(lambda: scene.solve(dict(params, delta=delta)), "delta")
    if u is not None:
        assert 1.0 <= delta <= 2.5 and torch.isfinite(u).all() and float((u * scene.force).sum()) > 0


@SETTINGS
@given(h=numbers, thickness=st.sampled_from([1.0, 0.0, -1.0, math.nan, math.inf, 1e-300]))
def test_grid_spacing_is_refused_or_gives_positive_volumes(h, thickness):
    p = refused(lambda: bp.grid_2d(4 * h, 2 * h, h, thickness=thickness), "h", "thickness", "spacing",
                "extent", "volume")
    if p is not None:
        assert p.n == 8 and np.isfinite(p.x).all() and np.all(p.volume > 0) and p.h == h
        np.testing.assert_allclose(p.volume.sum(), 8 * h * h * thickness, rtol=1e-12)


@SETTINGS
@given(k=st.integers(0, 23), c=st.integers(0, 1), value=numbers)
def test_particle_coordinates_are_refused_or_kept(k, c, value):
    """One coordinate of a 6 x 4 grid replaced: NaN/inf, a duplicate or a far point is refused
    or the particles keep every coordinate as given."""
    x = bp.grid_2d(6.0, 4.0, 1.0).x.copy()
    x[k, c] = value
    p = refused(lambda: bp.from_points(x, np.ones(24), h=1.0), "position", "coordinates", "closer than",
                "NaN", "x ")
    if p is not None:
        assert np.array_equal(p.x, x) and np.isfinite(p.x).all()


@SETTINGS
@given(px=numbers, py=numbers)
def test_an_observation_point_is_refused_or_interpolates_affine_fields_exactly(plate, px, py):
    p = plate[0]
    obs = refused(lambda: bp.Observation(p, [[px, py]]), "point", "outside the body", "NaN")
    if obs is not None:
        A = torch.tensor([[1e-3, 2e-3], [-3e-3, 4e-3]])
        u = torch.as_tensor(p.x) @ A.T
        expected = torch.tensor([[px, py]]) @ A.T
        torch.testing.assert_close(obs(u), expected, rtol=1e-10, atol=1e-14)


counts = st.one_of(st.integers(-3, 3), st.sampled_from([10**9, True, 2.5, "10", None, math.nan]))
fractions = st.one_of(numbers, st.floats(0, 1))


@SETTINGS
@given(num_samples=counts, num_warmup=counts, num_chains=counts, target_accept=fractions,
       max_tree_depth=counts, checkpoint_every=counts)
def test_nuts_settings_are_refused_by_name_or_kept(num_samples, num_warmup, num_chains, target_accept,
                                                   max_tree_depth, checkpoint_every):
    kw = dict(num_samples=num_samples, num_warmup=num_warmup, num_chains=num_chains, target_accept=target_accept,
              max_tree_depth=max_tree_depth, checkpoint_every=checkpoint_every)
    s = refused(lambda: NUTS(**kw), *kw)
    if s is not None:
        assert s.num_samples >= 1 and s.num_warmup >= 0 and s.num_chains >= 1 and s.max_tree_depth >= 1
        assert 0 < s.target_accept < 1 and s.checkpoint_every >= 1


@SETTINGS
@given(trajectory_length=st.one_of(numbers, st.none()), step_size=numbers)
def test_hmc_trajectory_length_is_refused_by_name_or_positive(trajectory_length, step_size):
    s = refused(lambda: HMC(trajectory_length=trajectory_length), "trajectory_length")
    if s is not None:
        assert trajectory_length is None or 0 < trajectory_length < math.inf


@SETTINGS
@given(svi_lr=numbers, svi_steps=counts, svi_particles=counts, svi_rank=st.one_of(st.none(), counts))
def test_svi_settings_are_refused_by_name_or_kept(svi_lr, svi_steps, svi_particles, svi_rank):
    kw = dict(svi_lr=svi_lr, svi_steps=svi_steps, svi_particles=svi_particles, svi_rank=svi_rank)
    s = refused(lambda: SVI(**kw), *kw)
    if s is not None:
        assert 0 < s.svi_lr < math.inf and s.svi_steps >= 1 and s.svi_particles >= 1


@SETTINGS
@given(seed=counts, map_starts=counts, hessian=st.sampled_from(["exact", "gauss-newton", "bfgs", "", None]))
def test_shared_and_laplace_settings_are_refused_by_name_or_kept(seed, map_starts, hessian):
    kw = dict(seed=seed, map_starts=map_starts, hessian=hessian, init="map")
    s = refused(lambda: Laplace(**kw), *kw)
    if s is not None:
        assert s.seed >= 0 and s.map_starts >= 1


@pytest.fixture(scope="module")
def normal_model():
    import pyro
    import pyro.distributions as dist

    y = 1.0 + torch.randn(10, generator=torch.Generator().manual_seed(0))

    def model(y):
        mu = pyro.sample("mu", dist.Normal(0.0, 3.0))
        with pyro.plate("obs", 10):
            pyro.sample("y", dist.Normal(mu, 1.0), obs=y)
    return model, y


@settings(SETTINGS, max_examples=12)
@given(svi_lr=st.sampled_from([1e-300, 1e-12, 0.02, 1.0, 1e3, 1e12, 1e300]))
def test_an_svi_fit_at_any_valid_learning_rate_is_finite_or_refused_as_divergence(normal_model, svi_lr):
    """mu ~ N(0, 3), y ~ N(mu, 1): 30 steps end with finite draws, or a ValueError naming svi_lr."""
    from bayespd.infer import fit

    model, y = normal_model
    tree = refused(lambda: fit(model, {"y": y}, "svi", svi_lr=svi_lr, svi_steps=30, num_samples=20,
                               progress=False), "svi_lr")
    if tree is not None:
        assert np.isfinite(tree["posterior"]["mu"].values).all()


@settings(SETTINGS, max_examples=15)
@given(entry=numbers, shape=st.sampled_from([(10,), (9,), (10, 1), (1, 10), ()]),
       kind=st.sampled_from(["tensor", "numpy", "list"]))
def test_data_are_refused_by_name_or_fitted(normal_model, entry, shape, kind):
    """``y`` with one entry replaced, of a wrong shape or type: refused naming ``y``, or a fit
    with a finite posterior."""
    from bayespd.infer import fit

    model, y = normal_model
    data = y.clone()
    data[3] = entry
    data = data.reshape(shape) if math.prod(shape) == 10 else data[: math.prod(shape)].reshape(shape)
    data = {"tensor": data, "numpy": data.numpy(), "list": data.tolist()}[kind]
    tree = refused(lambda: fit(model, {"y": data}, "laplace", num_samples=20, progress=False), "y", "data")
    if tree is not None:
        assert np.isfinite(tree["posterior"]["mu"].values).all()
