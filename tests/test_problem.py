"""The differentiable solve: gradcheck, Taylor remainders, second derivatives, backends."""
import numpy as np
import pytest
import torch

import bayespd as bp
from bayespd import linalg
from bayespd.linalg import adjoint, sparse
from bayespd.linalg.amg import VCycle
from bayespd.materials.checks import NonFiniteParameterError
from bayespd.problem import SCENE_RTOL
from tests.conftest import plate_scene

# delta = 2.2 h keeps every bond away from a kink of the partial-volume weights (|xi| = delta +- h/2)
BASE = {"K": 3000.0, "G": 1500.0, "delta": 2.2, "load": 1.0}
NAMES = list(BASE)


def observed(scene, *theta):
    return scene.observe(scene.solve(dict(zip(NAMES, theta)))).reshape(-1)


def leaves(values=BASE):
    return [torch.tensor(values[k], requires_grad=True) for k in NAMES]


def test_scene_gradcheck_and_gradgradcheck(small_scene):
    fn = lambda *t: observed(small_scene, *t)  # noqa: E731
    assert torch.autograd.gradcheck(fn, leaves(), eps=1e-6, atol=1e-9, rtol=1e-6)
    assert torch.autograd.gradgradcheck(fn, leaves(), eps=1e-6, atol=1e-8, rtol=1e-5)


def test_values_solve_gradcheck_through_stiffness(small_scene):
    """The spec'd primitive: solve(pattern, values, rhs) with values from the material."""
    sc = small_scene
    c = sc.constraints

    def fn(K, G, delta, load):
        values = c.free_values(sc.material.stiffness({"K": K, "G": G, "delta": delta}))
        return adjoint.solve(c.pattern, values, c.free(sc.force) * load)

    assert torch.autograd.gradcheck(fn, leaves(), eps=1e-6, atol=1e-9, rtol=1e-6)
    assert torch.autograd.gradgradcheck(fn, leaves(), eps=1e-6, atol=1e-8, rtol=1e-5)


def taylor_slopes(J, x0, direction, grad):
    ts = 1e-2 * 0.5 ** np.arange(5)
    J0 = J(x0)
    r0 = [abs(J(x0 + t * direction) - J0) for t in ts]
    r1 = [abs(J(x0 + t * direction) - J0 - t * float((grad * direction).sum())) for t in ts]
    return np.diff(np.log(r0)) / np.diff(np.log(ts)), np.diff(np.log(r1)) / np.diff(np.log(ts))


def amg_scene():
    """A plate solved by PCG with the AMG V-cycle at the scene's default rtol, large enough
    (672 dofs > pyamg's coarsest 300) for a V-cycle that is not the exact coarse solve."""
    with linalg.settings(static_solver="amg"):
        scene = plate_scene(nx=24, ny=14)
    assert scene.solver == "amg"
    assert len(scene.factor({k: BASE[k] for k in NAMES}).precondition.levels) >= 1
    return scene


@pytest.mark.parametrize("solver", ["direct", "amg"])
@pytest.mark.parametrize("name", NAMES)
def test_taylor_remainder_slope_two(small_scene, name, solver):
    """|J(p + t dp) - J(p) - t dJ.dp| = O(t^2) per parameter, with a random data misfit J;
    with AMG-PCG too, at the scene's default rtol (SCENE_RTOL = 1e-8): the adjoint's error
    (~ kappa rtol, relative) stays below the t^2 term down to the smallest step, 6.25e-4 x
    the scale below (delta: 3e-4 = h / 3200). At rtol = 1e-6 delta's slopes fall to 1.9, 1.7
    and 1.3 (the error term, linear in t, takes over): this test fails there."""
    if solver == "amg":
        small_scene = amg_scene()
        assert small_scene.rtol == SCENE_RTOL
    gen = torch.Generator().manual_seed(7)
    y = observed(small_scene, *leaves()).detach() * (1 + 0.05 * torch.randn(1, generator=gen))
    y = y + 1e-3 * torch.randn(y.shape, generator=gen)
    scale = {"K": 300.0, "G": 150.0, "delta": 0.5, "load": 0.1}[name]

    def J(x):
        theta = dict(BASE, **{name: x})
        return float(0.5 * ((observed(small_scene, *theta.values()) - y) ** 2).sum())

    x0 = torch.tensor(BASE[name], requires_grad=True)
    theta = [x0 if k == name else torch.tensor(BASE[k]) for k in NAMES]
    obj = 0.5 * ((observed(small_scene, *theta) - y) ** 2).sum()
    (grad,) = torch.autograd.grad(obj, x0)
    direction = torch.tensor(scale * float(torch.randn(1, generator=gen).sign()))
    s0, s1 = taylor_slopes(lambda v: J(float(v)), x0.detach(), direction, grad)
    assert np.all(np.abs(s0 - 1.0) < 0.1)
    assert np.all(np.abs(s1 - 2.0) < 0.1), s1


@pytest.mark.parametrize("solver", ["direct", "amg"])
def test_hessian_vector_product_matches_finite_difference(small_scene, solver):
    """Second derivatives through the adjoint (its backward is one more solve) against central
    differences of the gradient; AMG-PCG as the direct factor (the same symmetric operator)."""
    if solver == "amg":
        small_scene = amg_scene()
    theta = leaves()
    y = observed(small_scene, *theta).detach() * 1.1

    def grad_at(values):
        t = leaves(values)
        obj = 0.5 * ((observed(small_scene, *t) - y) ** 2).sum()
        return torch.stack(torch.autograd.grad(obj, t))

    obj = 0.5 * ((observed(small_scene, *theta) - y) ** 2).sum()
    g = torch.stack(torch.autograd.grad(obj, theta, create_graph=True))
    v = torch.tensor([100.0, -50.0, 0.02, 0.05])
    hv = torch.stack(torch.autograd.grad(g @ v, theta))
    h = 1e-4
    plus = {k: BASE[k] + h * float(v[i]) for i, k in enumerate(NAMES)}
    minus = {k: BASE[k] - h * float(v[i]) for i, k in enumerate(NAMES)}
    fd = (grad_at(plus) - grad_at(minus)) / (2 * h)
    np.testing.assert_allclose(hv, fd, rtol=1e-5, atol=1e-9 * float(fd.abs().max()))


def test_auto_solver_is_amg_above_the_crossover_and_direct_below():
    """Scene(solver="auto"): direct for the small plate under the default crossover; AMG-PCG
    (a ``PCGFactor`` preconditioned by the V-cycle, never a silent SuperLU fallback) when the
    plate is above it, agreeing with the direct displacement to 1e-8 relative."""
    small = plate_scene(nx=24, ny=14)
    assert small.solver == "direct"
    with linalg.settings(direct_max_dofs=small.particles.n * 2 - 1):
        large = plate_scene(nx=24, ny=14)
    assert large.solver == "amg"
    factor = large.factor({k: BASE[k] for k in NAMES})
    assert isinstance(factor, sparse.PCGFactor) and isinstance(factor.precondition, VCycle)
    params = {k: torch.tensor(BASE[k]) for k in NAMES}
    u, u_direct = large.solve(params), small.solve(params)
    factor.solve(np.ones(len(large.constraints.free_dofs)))
    assert factor.iterations > 1  # a V-cycle, not an exact coarse solve
    with pytest.raises(ValueError, match="solver='direct'"):
        large.stiffness_values(params)
    assert float((u - u_direct).norm()) <= 1e-8 * float(u_direct.norm())


def test_superlu_fill_is_refused_naming_the_fix(monkeypatch):
    """A direct SuperLU solve past ``SPLU_MAX_NNZ`` entries raises ``SuperLUFillError`` that
    names solver='auto'/'amg' and CHOLMOD's extra (the limit lowered to this plate's K_ff)."""
    from bayespd.linalg import config

    monkeypatch.setattr(sparse, "default_backend", lambda: "splu")
    monkeypatch.setattr("bayespd.problem.default_backend", lambda: "splu")
    scene = plate_scene()
    monkeypatch.setattr(config, "SPLU_MAX_NNZ", scene.constraints.pattern.nnz - 1)
    with pytest.raises(linalg.SuperLUFillError, match="solver='auto' or 'amg'.*make fast"):
        scene.solve({k: torch.tensor(BASE[k]) for k in NAMES})


@pytest.mark.skipif(sparse.cholmod is None, reason="CHOLMOD (scikit-sparse) not installed")
def test_backends_agree():
    sc = plate_scene(nx=16, ny=8)
    c = sc.constraints
    values = c.free_values(sc.material.numeric_stiffness(BASE))
    rhs = c.free(sc.force).numpy()
    u_chol = c.pattern.factorize(values, "cholmod").solve(rhs)
    u_lu = c.pattern.factorize(values, "splu").solve(rhs)
    np.testing.assert_allclose(u_chol, u_lu, rtol=1e-10, atol=1e-14)


@pytest.mark.parametrize("backend", ["splu", "cholmod"])
def test_not_positive_definite_is_reported(backend):
    if backend == "cholmod" and sparse.cholmod is None:
        pytest.skip("CHOLMOD not installed")
    p = bp.grid_2d(6.0, 4.0, 1.0)
    mat = bp.LPS(p, bp.find_bonds(p, 2.0))
    values = mat.numeric_stiffness({"K": 1.0, "G": 1.0, "delta": 2.0})
    with pytest.raises(bp.NotPositiveDefiniteError):  # no constraints: rigid-body modes
        mat.pattern.factorize(values, backend).solve(np.ones(mat.pattern.n))
    with pytest.raises(bp.NotPositiveDefiniteError):
        mat.pattern.factorize(-values - 1e-3 * torch.eye(1)[0, 0], backend)


def test_per_particle_field_gradient_costs_one_solve(monkeypatch):
    """The gradient with respect to a per-particle shear field (one unknown per particle)
    takes one adjoint solve, and its Taylor remainder falls with slope 2."""
    scene = plate_scene(nx=14, ny=8)
    n = scene.particles.n
    G = torch.linspace(1200.0, 1800.0, n, requires_grad=True)
    solves = []
    factorize = sparse.Pattern.factorize

    def counting(self, values, backend=None):
        f = factorize(self, values, backend)
        inner = f.solve
        f.solve = lambda b: solves.append(1) or inner(b)
        return f

    monkeypatch.setattr(sparse.Pattern, "factorize", counting)

    def J(g):
        return float((scene.solve({"K": 3000.0, "G": g, "delta": 2.2}) ** 2).sum())

    u = scene.solve({"K": 3000.0, "G": G, "delta": 2.2})
    (u**2).sum().backward()
    assert len(solves) == 2  # forward + one adjoint, for n = 112 unknowns
    direction = torch.randn(n, generator=torch.Generator().manual_seed(7)) * 100
    _, s1 = taylor_slopes(J, G.detach(), direction, G.grad)
    assert abs(s1[-1] - 2.0) < 0.1


def test_prescribed_displacement_load_is_differentiable_only_when_asked():
    """f_f - K_fc u_c: with grad enabled its derivative in K matches a central difference
    (error O((dK/K)^2) ~ 1e-5 relative: plane-stress kappa is not linear in K); under no_grad
    it carries no graph."""
    p = bp.grid_2d(8.0, 4.0, h=1.0, thickness=1.0)
    material = bp.LPS(p, bp.find_bonds(p, 2.5), plane="stress")
    scene = bp.Scene(material, [bp.Dirichlet.layer(p, "left", 2.5),
                                bp.Dirichlet(p.layer("right", 1.0), (0.01, None))],
                     [bp.Load(p.layer("top", 1.0), (0.0, 1.0))])
    K = torch.tensor(3000.0, dtype=torch.float64, requires_grad=True)
    rhs = scene.free_load({"K": K, "G": 1400.0, "delta": 2.2})
    w = torch.linspace(-1, 1, rhs.numel(), dtype=torch.float64)
    (dK,) = torch.autograd.grad((w * rhs).sum(), K)
    with torch.no_grad():
        f = [(w * scene.free_load({"K": k, "G": 1400.0, "delta": 2.2})).sum() for k in (2990.0, 3010.0)]
        assert not scene.free_load({"K": K, "G": 1400.0, "delta": 2.2}).requires_grad
    assert float(dK) != 0 and abs(float(dK) - float(f[1] - f[0]) / 20.0) < 1e-4 * abs(float(dK))


def small_plate():
    p = bp.grid_2d(6.0, 3.0, 1.0)
    return p, bp.LPS(p, bp.find_bonds(p, 2.0))


@pytest.mark.parametrize("load", [float("nan"), float("inf"), torch.tensor(float("nan"), requires_grad=True)])
def test_non_finite_load_factor_is_refused(load):
    p, material = small_plate()
    scene = bp.Scene(material, [bp.Dirichlet.layer(p, "left", 2.0)], [bp.Load(p.layer("right", 1.0), (1.0, 0.0))])
    with pytest.raises(NonFiniteParameterError, match=r"load factor params\['load'\] contains NaN or inf.*finite"):
        scene.solve({"K": 1.0, "G": 0.5, "delta": 2.0, "load": load})


def test_extreme_load_factor_scales_the_displacement_linearly():
    p, material = small_plate()
    scene = bp.Scene(material, [bp.Dirichlet.layer(p, "left", 2.0)], [bp.Load(p.layer("right", 1.0), (1.0, 0.0))])
    params = {"K": 1.0, "G": 0.5, "delta": 2.0}
    u1, big = scene.solve({**params, "load": 1.0}), scene.solve({**params, "load": 1e200})
    assert torch.isfinite(big).all()
    torch.testing.assert_close(big / 1e200, u1, rtol=0.0, atol=1e-12 * float(u1.abs().max()))


def test_load_on_the_clamped_layer_is_refused_and_a_partial_one_warned():
    p, material = small_plate()
    clamp = [bp.Dirichlet.layer(p, "left", 2.0)]
    with pytest.raises(ValueError, match="load 0 acts only on Dirichlet-constrained dofs.*apply it to free"):
        bp.Scene(material, clamp, [bp.Load(p.layer("left", 1.0), (1.0, 0.0))])
    roller = [bp.Dirichlet.layer(p, "left", 2.0, (0.0, None))]  # y stays free: a y load there acts
    u = bp.Scene(material, roller + [bp.Dirichlet(p.layer("right", 1.0), (None, 0.0))],
                 [bp.Load(p.layer("left", 1.0), (0.0, 1.0))]).solve({"K": 1.0, "G": 0.5, "delta": 2.0})
    assert torch.isfinite(u).all() and float(u[p.layer("left", 1.0), 1].min()) > 0
    with pytest.warns(UserWarning, match=r"50% of load 0's component 0 acts on Dirichlet-constrained dofs"):
        bp.Scene(material, clamp, [bp.Load(p.box((0.0, 0.0), (4.0, 1.0)), (1.0, 0.0))])
