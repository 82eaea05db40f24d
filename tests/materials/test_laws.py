"""The checks every material law passes (LPS, bond-based PMB, conical bond-based): patch test,
energy of an isotropic expansion, symmetric stiffness with the rigid modes in its null space,
damaged terms at mu = 1 equal to the intact ones, and the damaged linearised stiffness as the
Hessian at u = 0 of the nonlinear energy whose gradient is minus the nonlinear force."""
import math

import numpy as np
import pytest
import torch

import bayespd as bp
from bayespd.nonlinear import NonlinearBonds

E, NU = 4000.0, 0.3
K0, G0 = (float(v) for v in bp.moduli_from_young(E, NU))


def lps_bulk(mat, K, plane):
    return float(mat.kappa(torch.tensor(K), torch.tensor(G0)))


def bond_based_bulk(mat, K, plane):
    """In-plane bulk modulus of a bond-based law: nu = 1/3 (plane stress), 1/4 (plane strain)."""
    return 0.75 * K if plane == "stress" else 1.2 * K


# (law, in-plane bulk modulus, relative error of the isotropic expansion at m = 3, h = 1)
LAWS = [pytest.param(bp.LPS, lps_bulk, 1e-8, id="lps"),
        pytest.param(bp.BondBased, bond_based_bulk, 0.03, id="pmb"),
        pytest.param(bp.ConicalBondBased, bond_based_bulk, 0.07, id="conical")]



def random_u(n, scale, seed=0):
    return scale * torch.randn(n, 2, generator=torch.Generator().manual_seed(seed))


@pytest.fixture(scope="module", params=["linear", "smooth"])
def lattice(request):
    p = bp.grid_2d(24.0, 24.0, 1.0)
    return p, bp.find_bonds(p, 3.0, rule=request.param)


@pytest.fixture(scope="module")
def plate():
    p = bp.grid_2d(10.0, 8.0, 1.0)
    bonds = bp.find_bonds(p, 3.0)
    mu = torch.rand(bonds.n, generator=torch.Generator().manual_seed(1))
    mu[torch.as_tensor((bonds.i == 0) | (bonds.j == 0))] = 0.0  # particle 0 fully broken
    return p, bonds, mu


@pytest.mark.parametrize("plane", ["stress", "strain"])
@pytest.mark.parametrize("law,bulk,tol", LAWS)
def test_patch_test_zero_interior_force(lattice, law, bulk, tol, plane):
    """A linear displacement field leaves the particles whose own and neighbours' families are
    complete without force."""
    p, bonds = lattice
    mat = law(p, bonds, plane=plane)
    eps = torch.tensor([[1e-3, 4e-4], [4e-4, -2e-3]])
    values = mat.stiffness({"K": K0, "G": G0, "delta": 2.7})
    f = mat.pattern.matvec(values, (torch.as_tensor(p.x) @ eps.T).reshape(-1)).reshape(-1, 2)
    inner = p.interior(2 * (2.7 + 0.5) + 1e-9)
    assert inner.sum() > 20
    assert f[inner].abs().max() <= 1e-10 * f[~inner].abs().max()


@pytest.mark.parametrize("plane", ["stress", "strain"])
@pytest.mark.parametrize("law,bulk,tol", LAWS)
def test_isotropic_expansion_stores_the_classical_energy(lattice, law, bulk, tol, plane):
    """W = kappa/2 tr(eps)^2 at interior particles: exact on the lattice for LPS (m absorbs the
    quadrature), within the partial-volume quadrature error of the continuum calibration for
    the bond-based laws (measured 2.0 % PMB, 5.8 % conical at m = 3)."""
    p, bonds = lattice
    mat = law(p, bonds, plane=plane)
    strain = 1e-3
    W = mat.energy_density({"K": K0, "G": G0, "delta": 3.0}, strain * torch.as_tensor(p.x))
    inner = p.interior(3.0 + 0.5 + 1e-9)
    classical = 0.5 * bulk(mat, K0, plane) * (2 * strain) ** 2
    np.testing.assert_allclose(W[inner].numpy(), classical, rtol=tol)


@pytest.mark.parametrize("law,bulk,tol", LAWS)
def test_stiffness_symmetric_and_consistent(lattice, law, bulk, tol):
    """K is symmetric for heterogeneous moduli, the scipy assembly equals the torch one,
    2 E(u) = u^T K u, and the three rigid-body modes are its null space."""
    p, bonds = lattice
    mat = law(p, bonds, plane="stress")
    n = p.n
    params = {"K": torch.linspace(2000.0, 4000.0, n), "G": torch.linspace(1500.0, 900.0, n), "delta": 2.7}
    values = mat.stiffness(params)
    A = mat.pattern.matrix(values)
    assert abs(A - A.T).max() <= 1e-12 * abs(A).max()
    np.testing.assert_allclose(mat.numeric_stiffness(params), values, rtol=0, atol=1e-12 * abs(A).max())
    u = torch.randn(n, 2, generator=torch.Generator().manual_seed(0))
    quad = float(u.reshape(-1) @ torch.as_tensor(A @ u.reshape(-1).numpy()))
    np.testing.assert_allclose(float(2 * mat.energy(params, u)), quad, rtol=1e-12)
    ev = np.linalg.eigvalsh(A.toarray())
    assert np.sum(np.abs(ev) < 1e-9 * ev.max()) == 3 and ev[3] > 1e-6 * ev.max()


@pytest.mark.parametrize("surface", [False, True])
@pytest.mark.parametrize("law,bulk,tol", LAWS)
def test_damaged_terms_with_all_bonds_intact_are_the_intact_terms(plate, law, bulk, tol, surface):
    p, bonds, _ = plate
    mat = law(p, bonds, surface_correction=surface)
    params = {"K": K0, "G": G0, "delta": 2.7}
    assert torch.equal(mat.numeric_stiffness(params, torch.ones(bonds.n)), mat.numeric_stiffness(params))
    with pytest.raises(ValueError, match="one value per bond"):
        mat.terms(params, torch.ones(bonds.n + 1))


@pytest.mark.parametrize("damaged", [False, True])
@pytest.mark.parametrize("law,bulk,tol", LAWS)
def test_nonlinear_force_is_minus_damaged_stiffness_times_small_u(plate, law, bulk, tol, damaged):
    """|f(s u; mu) + K(mu) s u| = O(s^2): slope 2 as u is scaled (the damaged linearised
    stiffness is the Hessian at u = 0 of the nonlinear energy at the same mu)."""
    p, bonds, mu = plate
    mat = law(p, bonds)
    params = {"K": torch.linspace(2000.0, 3000.0, p.n), "G": G0, "delta": 2.7}
    mu = mu if damaged else None
    K = mat.numeric_stiffness(params, mu)
    force = NonlinearBonds(mat).at(params)
    u, scales, rem = random_u(p.n, 1.0), [1e-2, 5e-3, 2.5e-3], []
    for s in scales:
        lin = -mat.pattern.matvec(K, (s * u).reshape(-1)).reshape(-1, 2)
        rem.append(float((force.force(s * u, mu) - lin).norm()))
        assert rem[-1] < 0.05 * float(lin.norm())
    np.testing.assert_allclose(np.diff(np.log(rem)) / np.diff(np.log(scales)), 2.0, atol=0.05)


@pytest.mark.parametrize("law,bulk,tol", LAWS)
def test_nonlinear_energy_and_force_are_consistent(plate, law, bulk, tol):
    """V(u + t v) - V(u) + t f(u) . v = O(t^2) at a finite, damaged deformation (slope 2)."""
    p, bonds, mu = plate
    mat = law(p, bonds)
    force = NonlinearBonds(mat).at({"K": K0, "G": G0, "delta": 2.7})
    u, v = random_u(p.n, 0.05), random_u(p.n, 0.05, seed=1)
    f_v = float((force.force(u, mu) * v).sum())
    ts = [1e-1, 5e-2, 2.5e-2]
    rem = [abs(float(force.energy(u + t * v, mu) - force.energy(u, mu)) + t * f_v) for t in ts]
    np.testing.assert_allclose(np.diff(np.log(rem)) / np.diff(np.log(ts)), 2.0, atol=0.1)


@pytest.mark.parametrize("law,bulk,tol", LAWS)
def test_the_horizon_is_an_ordinary_parameter(plate, law, bulk, tol):
    """delta is one of ``param_names``; params without it are refused, naming the fix, by the
    linear, damaged and nonlinear forms alike."""
    p, bonds, mu = plate
    mat = law(p, bonds)
    assert mat.param_names[-1] == "delta"
    for evaluate in (mat.stiffness, lambda q: mat.terms(q, mu), NonlinearBonds(mat).at):
        with pytest.raises(ValueError, match=r"pass params\['delta'\]"):
            evaluate({"K": K0, "G": G0})


@pytest.mark.parametrize("law,coefs", [(bp.BondBased, (9, 72 / 5, 18)), (bp.ConicalBondBased, (36, 288 / 5, 90))],
                         ids=["pmb", "conical"])
def test_bond_based_micromodulus_closed_forms(law, coefs):
    """omega = 1: c t = a K/(pi delta^3) in plane stress and plane strain, c = a K/(pi delta^4)
    in 3D, with a = 9, 72/5, 18 (PMB) and 36, 288/5, 90 (conical: c0 = M_2 / C_2 = 4 times
    PMB's) -- the constants of the laws' module docstrings."""
    p2, p3 = bp.grid_2d(6.0, 6.0, 1.0), bp.grid_3d(4.0, 4.0, 4.0, 1.0)
    K, d = torch.tensor(1e3), 2.5
    for (p, plane, power), a in zip([(p2, "stress", 3), (p2, "strain", 3), (p3, "stress", 4)], coefs):
        mat = law(p, bp.find_bonds(p, d), plane=plane)
        c = mat.micromodulus(K, {"delta": d}) * p.thickness
        assert abs(float(c / (a * K / (math.pi * d**power))) - 1) < 1e-14


@pytest.mark.parametrize("plane", ["stress", "strain"])
@pytest.mark.parametrize("law,bulk,tol", LAWS)
def test_terms_are_affine_in_their_coefficients(lattice, law, bulk, tol, plane):
    """K(moduli, delta) = sum_t Theta_t(moduli) A_t(delta): each term's weights at other
    homogeneous moduli are those at the reference times Theta_t / Theta_t(reference)."""
    p, bonds = lattice
    mat = law(p, bonds, plane=plane)
    names = mat.moduli_names
    ref = {"K": K0, "G": G0}
    other = {"K": 1.7 * K0, "G": 0.6 * G0}
    at = lambda moduli: {**{k: torch.tensor(moduli[k]) for k in names}, "delta": 2.4}  # noqa: E731
    scale = [float(a / b) for a, b in zip(mat.term_coefficients(at(other)), mat.term_coefficients(at(ref)))]
    assert len(scale) == len(mat.terms(at(ref)))
    for s, (_, _, w_ref), (_, _, w) in zip(scale, mat.terms(at(ref)), mat.terms(at(other))):
        torch.testing.assert_close(w, s * w_ref, rtol=1e-13, atol=0)
