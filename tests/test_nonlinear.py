"""Nonlinear bond force: f = -grad V, linear limit -K u + O(|u|^2), parameter gradients."""
from functools import partial

import numpy as np
import pytest
import torch

import bayespd as bp
from bayespd.nonlinear import NonlinearBonds

DELTA = 2.7
LAWS = [bp.BondBased, bp.LPS, bp.ConicalBondBased]


@pytest.fixture(scope="module")
def plate():
    p = bp.grid_2d(10.0, 8.0, 1.0)
    return p, bp.find_bonds(p, 3.0)


def setup(plate, cls, surface=False):
    p, bonds = plate
    mat = cls(p, bonds, plane="stress", surface_correction=surface)
    params = {"K": torch.linspace(2000.0, 3000.0, p.n), "G": torch.linspace(1500.0, 900.0, p.n), "delta": DELTA}
    return mat, params, NonlinearBonds(mat)


def random_u(n, scale, seed=0, dim=2):
    return scale * torch.randn(n, dim, generator=torch.Generator().manual_seed(seed))


def damage_state(bonds, p, seed=1):
    """Random intact fractions in [0, 1], and particle 0 (a corner) fully broken."""
    mu = torch.rand(bonds.n, generator=torch.Generator().manual_seed(seed))
    mu[torch.as_tensor((bonds.i == 0) | (bonds.j == 0))] = 0.0
    return mu


@pytest.mark.parametrize("cls", LAWS)
@pytest.mark.parametrize("damaged", [False, True])
def test_force_is_minus_energy_gradient(plate, cls, damaged):
    p, bonds = plate
    mat, params, nl = setup(plate, cls, surface=not damaged)
    mu = damage_state(bonds, p) if damaged else None
    u = random_u(p.n, 0.05).requires_grad_()  # finite (5 % of h) deformation
    load = torch.randn(p.n, 2, generator=torch.Generator().manual_seed(3))
    eps = 0.7
    V = nl.energy(u, params, mu, load=load, eps=eps)
    (grad,) = torch.autograd.grad(V, u)
    f = nl.force(u.detach(), params, mu)
    expected = -grad  # = f + p - eps u
    got = f + load - eps * u.detach()
    assert torch.isfinite(got).all()
    assert float((got - expected).norm() / expected.norm()) < 1e-10
    if damaged:  # the fully broken particle feels only load and confinement
        assert float(f[0].abs().max()) == 0.0


@pytest.mark.parametrize("cls", LAWS)
def test_small_displacement_matches_linear_stiffness(plate, cls):
    """|f(s u) + K s u| = O(s^2): the remainder falls with slope 2 as u is scaled."""
    p, _ = plate
    mat, params, nl = setup(plate, cls)
    K = mat.numeric_stiffness(params)
    u = random_u(p.n, 1.0)
    scales = [1e-2, 5e-3, 2.5e-3, 1.25e-3]
    rem = []
    for s in scales:
        lin = -mat.pattern.matvec(K, (s * u).reshape(-1)).reshape(-1, 2)
        f = nl.force(s * u, params)
        rem.append(float((f - lin).norm()))
        assert rem[-1] < 0.05 * float(lin.norm())
    slopes = np.diff(np.log(rem)) / np.diff(np.log(scales))
    np.testing.assert_allclose(slopes, 2.0, atol=0.05)


@pytest.mark.parametrize("cls", LAWS)
def test_rigid_rotation_is_force_free(plate, cls):
    """A finite rigid rotation stretches no bond (the linearised force would not vanish)."""
    p, _ = plate
    mat, params, nl = setup(plate, cls)
    c, s = np.cos(0.4), np.sin(0.4)
    x = torch.as_tensor(p.x)
    u = x @ torch.tensor([[c - 1, -s], [s, c - 1]]).T
    assert float(nl.stretch(u).abs().max()) < 1e-14
    f = nl.force(u, params)
    assert float(f.abs().max()) < 1e-12 * 3000.0


@pytest.mark.parametrize("cls", LAWS)
def test_force_is_twice_differentiable_in_u(cls):
    """The force through the two sparse products (scipy on the CPU): gradcheck and
    gradgradcheck in u on a tiny plate."""
    p = bp.grid_2d(4.0, 3.0, 1.0)
    nl = NonlinearBonds(cls(p, bp.find_bonds(p, 2.1)))
    u = random_u(p.n, 0.1).requires_grad_(True)
    f = partial(nl.force, params={"K": 2.0, "G": 1.0, "delta": 2.1})
    assert torch.autograd.gradcheck(f, (u,))
    assert torch.autograd.gradgradcheck(f, (u,))


@pytest.mark.parametrize("cls", LAWS)
def test_force_gradient_in_parameters(cls):
    """Per-particle moduli, delta and mu: torch.autograd.gradcheck on a tiny plate."""
    p = bp.grid_2d(5.0, 4.0, 1.0)
    bonds = bp.find_bonds(p, 2.5)
    nl = NonlinearBonds(cls(p, bonds))
    u = random_u(p.n, 0.1)
    K0 = torch.linspace(2.0, 3.0, p.n, requires_grad=True)
    G0 = torch.linspace(1.5, 1.0, p.n, requires_grad=True)
    delta = torch.tensor(2.3, requires_grad=True)
    mu = torch.linspace(0.2, 1.0, bonds.n, requires_grad=True)

    def f(K, G, delta, mu):
        return nl.force(u, {"K": K, "G": G, "delta": delta}, mu)

    assert torch.autograd.gradcheck(f, (K0, G0, delta, mu))


@pytest.mark.parametrize("cls", LAWS)
def test_three_d_gradient_and_linear_limit(cls):
    p = bp.grid_3d(4.0, 4.0, 3.0, 1.0)
    mat = cls(p, bp.find_bonds(p, 2.0))
    params = {"K": torch.linspace(2.0, 3.0, p.n), "G": 1.2, "delta": 1.8}
    nl = NonlinearBonds(mat)
    u = random_u(p.n, 0.05, dim=3).requires_grad_()
    (grad,) = torch.autograd.grad(nl.energy(u, params), u)
    f = nl.force(u.detach(), params)
    assert float((f + grad).norm() / grad.norm()) < 1e-10
    K = mat.numeric_stiffness(params)
    rem = [float((nl.force(s * u.detach(), params)
                  + mat.pattern.matvec(K, s * u.detach().reshape(-1)).reshape(-1, 3)).norm())
           for s in (1e-2, 5e-3)]
    assert np.log2(rem[0] / rem[1]) == pytest.approx(2.0, abs=0.05)


@pytest.mark.parametrize("cls", LAWS)
def test_shared_components_give_the_same_force_and_stretch(plate, cls, monkeypatch):
    """One gather for both: force and stretch from ``components(u)`` are bit for bit those
    torch computes from u."""
    from bayespd import bond_loops

    monkeypatch.setattr(bond_loops, "ENABLED", False)
    mat, params, nl = setup(plate, cls)
    u, mu = random_u(mat.particles.n, 0.01), damage_state(mat.bonds, mat.particles)
    parts = nl.components(u)
    f = nl.at(params)
    assert torch.equal(f.force(u, mu, parts), f.force(u, mu))
    assert torch.equal(nl.stretch(u, parts), nl.stretch(u))


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("dim", [2, 3])
def test_compiled_loops_match_the_torch_path(plate, dim, dtype, monkeypatch):
    """``bond_loops`` does torch's operations in torch's order, with a correctly rounded |y|
    where torch's is off by an ulp now and then: the stretch and the PMB force agree with
    torch's to a few ulp of the dtype; a broken bond's end feels exactly nothing."""
    pytest.importorskip("numba")
    from bayespd import bond_loops

    if dim == 2:
        mat, params, nl = setup(plate, bp.BondBased)
    else:
        p = bp.grid_3d(4.0, 4.0, 3.0, 1.0)
        mat = bp.BondBased(p, bp.find_bonds(p, 2.0))
        params = {"K": torch.linspace(2.0, 3.0, p.n), "G": 1.2, "delta": 1.8}
        nl = NonlinearBonds(mat)
    u = random_u(mat.particles.n, 0.05, dim=dim).to(dtype)
    mu = damage_state(mat.bonds, mat.particles).to(dtype)
    assert bond_loops.usable(u, None) and not bond_loops.usable(u.clone().requires_grad_())
    assert not bond_loops.usable(u, u.double() if dtype == torch.float32 else u.float())
    assert nl.shared_components(u) is None
    forces, results = nl.at(params, dtype), {}
    for enabled in (True, False):
        monkeypatch.setattr(bond_loops, "ENABLED", enabled)
        results[enabled] = nl.stretch(u), forces.force(u, mu), forces.force(u)
    (s, f, f_intact), (s0, f0, f0_intact) = results[True], results[False]
    assert s.dtype == f.dtype == dtype
    ulp = torch.finfo(dtype).eps
    assert float((s - s0).abs().max() / s0.abs().max()) <= 8 * ulp
    for got, expected in ((f, f0), (f_intact, f0_intact)):
        assert float((got - expected).abs().max() / expected.abs().max()) <= 64 * ulp
    assert float(f[0].abs().max()) == 0.0 and float(f_intact[0].abs().max()) > 0
