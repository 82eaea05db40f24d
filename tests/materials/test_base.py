"""The ``Material`` / ``Force`` contract of ``bayespd.materials.base``: the parameter names, the
refusal of incomplete params naming the fix, the Gram terms at mu = 1, the bilinear form and
energy against the assembled matrix, the intact fractions' shape, the abstract methods.
(The law-by-law checks, patch tests and energies, are in ``tests/materials/test_laws.py``.)"""
import numpy as np
import pytest
import torch

import bayespd as bp
from bayespd.influence import Bernstein
from bayespd.materials import Force, Material
from bayespd.nonlinear import NonlinearBonds

LAWS = [pytest.param(bp.LPS, id="lps"), pytest.param(bp.BondBased, id="pmb"),
        pytest.param(bp.ConicalBondBased, id="conical")]


@pytest.fixture(scope="module")
def lattice():
    p = bp.grid_2d(7.0, 6.0, 1.0)
    return p, bp.find_bonds(p, 2.5)


def heterogeneous(n):
    return {"K": torch.linspace(2.0, 3.0, n), "G": torch.linspace(1.5, 1.0, n), "delta": 2.2}


def params_for(mat, n):
    """The params of ``mat``: only its own moduli (a bond-based law has no G)."""
    return {k: v for k, v in heterogeneous(n).items() if k in mat.param_names}


def random_u(n, seed):
    return torch.randn(n, 2, generator=torch.Generator().manual_seed(seed))


@pytest.mark.parametrize("law", LAWS)
def test_param_names_are_moduli_then_influence_then_delta(lattice, law):
    p, bonds = lattice
    assert law(p, bonds).param_names == (*law.moduli_names, "delta")
    learnable = law(p, bonds, influence=Bernstein(2))
    assert learnable.param_names == (*law.moduli_names, "D", "delta")


@pytest.mark.parametrize("law", LAWS)
def test_params_missing_a_modulus_or_the_horizon_are_refused_naming_them(lattice, law):
    p, bonds = lattice
    mat = law(p, bonds)
    full = params_for(mat, p.n)
    for name in mat.param_names:
        partial = {k: v for k, v in full.items() if k != name}
        with pytest.raises(ValueError, match=rf"needs params \['{name}'\]") as err:
            mat.stiffness(partial)
        assert ("pass params['delta']" in str(err.value)) == (name == "delta")


def test_influence_parameters_are_required_like_moduli(lattice):
    p, bonds = lattice
    mat = bp.LPS(p, bonds, influence=Bernstein(2))
    with pytest.raises(ValueError, match=r"needs params \['D'\]"):
        mat.stiffness(heterogeneous(p.n))


def test_unknown_plane_is_refused(lattice):
    with pytest.raises(ValueError, match="'stress' or 'strain'"):
        bp.LPS(*lattice, plane="axisymmetric")


@pytest.mark.parametrize("law", LAWS)
def test_terms_with_every_bond_intact_equal_the_undamaged_terms(lattice, law):
    """terms(params, ones) and terms(params) are the same Gram terms (operators, data and
    weights equal to rounding: mu = 1 multiplies the bond weights by one)."""
    p, bonds = lattice
    mat = law(p, bonds)
    params = params_for(mat, p.n)
    plain, ones = mat.terms(params), mat.terms(params, np.ones(bonds.n))
    assert len(plain) == len(ones) >= 1
    for (g0, d0, w0), (g1, d1, w1) in zip(plain, ones):
        assert g0 is g1
        torch.testing.assert_close(d1, d0, rtol=0, atol=0)
        torch.testing.assert_close(w1, w0, rtol=1e-15, atol=0)


@pytest.mark.parametrize("law", LAWS)
def test_numeric_stiffness_equals_the_differentiable_stiffness(lattice, law):
    p, bonds = lattice
    mat = law(p, bonds)
    params = params_for(mat, p.n)
    values = mat.stiffness(params).detach()
    numeric = mat.numeric_stiffness(params)
    assert not numeric.requires_grad
    assert float((numeric - values).abs().max()) <= 1e-13 * float(values.abs().max())


@pytest.mark.parametrize("law", LAWS)
def test_copies_are_one_body_whose_stiffness_is_the_bodys_k_times_over(lattice, law):
    """``copies(3)``: the stiffness is block diagonal, each block the body's own (the same bits: the
    copies' bonds and weights are the body's), and no bond joins two copies."""
    p, bonds = lattice
    mat = law(p, bonds, influence=Bernstein(2))
    params = {**params_for(mat, p.n), "D": torch.tensor([1.0, 0.5, 2.0], dtype=torch.float64)}
    params = {k: v for k, v in params.items() if k in mat.param_names}
    many = mat.copies(3)
    tiled = {k: v.repeat(3) if torch.is_tensor(v) and v.shape == (p.n,) else v for k, v in params.items()}
    K = mat.pattern.matrix(mat.numeric_stiffness(params)).toarray()
    K3 = many.pattern.matrix(many.numeric_stiffness(tiled)).toarray()
    assert many.particles.n == 3 * p.n and len(many.i) == 3 * len(mat.i)
    assert np.array_equal(K3, np.kron(np.eye(3), K))
    assert np.all(many.bonds.i // p.n == many.bonds.j // p.n)


def test_points_about_the_copies_map_back_into_the_body(lattice):
    """``in_body``: each copy's particles, and points up to just short of halfway to the next copy,
    land where they are in the body; the copies lie whole grid steps apart (one lattice)."""
    p, bonds = lattice
    mat = bp.LPS(p, bonds)
    many, shift = mat.copies(3), mat.copy_shift
    assert shift / p.h == round(shift / p.h) and shift >= np.ptp(p.x[:, 0]) + p.h + 2 * bonds.delta_max
    np.testing.assert_allclose(mat.in_body(many.particles.x), np.tile(p.x, (3, 1)), atol=1e-12 * shift)
    half = (shift - np.ptp(p.x[:, 0])) / 2
    edges = np.array([[p.x[:, 0].min() - 0.99 * half, 0.0], [p.x[:, 0].max() + 0.99 * half, 0.0]])
    for c in range(3):
        np.testing.assert_allclose(mat.in_body(edges + [c * shift, 0.0]), edges, atol=1e-12 * shift)


@pytest.mark.parametrize("law", LAWS)
def test_stiffness_in_chosen_rows_is_those_rows_of_the_stiffness_with_their_gradient(lattice, law):
    """K's entries in a few rows (unsorted, repeated, a node's two dofs and one more) from the
    products of those rows alone: the full stiffness's entries there, in the pattern's order, to
    rounding, and so is their gradient in every modulus field."""
    p, bonds = lattice
    mat = law(p, bonds)
    params = {k: v.clone().requires_grad_() if torch.is_tensor(v) else v for k, v in params_for(mat, p.n).items()}
    rows = (21, 8, 9, 21)
    at = mat.pattern.in_rows(rows)
    assert set(mat.pattern.rows[at]) == {8, 9, 21} and np.all(np.diff(at) > 0)
    full, some = mat.stiffness(params)[torch.as_tensor(at)], mat.stiffness(params, rows)
    torch.testing.assert_close(some, full, rtol=1e-14, atol=1e-14 * float(full.detach().abs().max()))
    weights = torch.linspace(-1.0, 2.0, len(at), dtype=torch.float64)
    moduli = [v for v in params.values() if torch.is_tensor(v)]
    torch.testing.assert_close(torch.autograd.grad((weights * some).sum(), moduli),
                               torch.autograd.grad((weights * full).sum(), moduli))


@pytest.mark.parametrize("law", LAWS)
def test_form_is_v_K_u_and_energy_is_half_u_K_u(lattice, law):
    """The matrix-free v^T K u and u^T K u / 2 equal the products with the assembled K, for
    v != u, to 1e-12 of |v| |K| |u| (sums of O(bonds) products)."""
    p, bonds = lattice
    mat = law(p, bonds)
    params = params_for(mat, p.n)
    A = mat.pattern.matrix(mat.numeric_stiffness(params)).toarray()
    u, v = random_u(p.n, 0), random_u(p.n, 1)
    un, vn = u.reshape(-1).numpy(), v.reshape(-1).numpy()
    scale = np.abs(A).max() * np.abs(un).sum() * np.abs(vn).sum()
    assert abs(float(mat.form(params, v, u)) - vn @ A @ un) <= 1e-13 * scale
    assert abs(float(mat.form(params, v, u)) - float(mat.form(params, u, v))) <= 1e-13 * scale
    assert abs(float(mat.energy(params, u)) - 0.5 * un @ A @ un) <= 1e-13 * scale


def test_form_differentiates_to_the_stiffness_derivative(lattice):
    """d/dK_k (v^T K u) by autograd equals v^T (dK/dK_k) u from the assembled derivative: in
    plane strain (kappa = K + G/3) the stiffness is linear in K, so one unit perturbation gives
    the derivative exactly (up to rounding)."""
    p, bonds = lattice
    mat = bp.LPS(p, bonds, plane="strain")
    params = heterogeneous(p.n)
    Kmod = params["K"].clone().requires_grad_(True)
    u, v = random_u(p.n, 2), random_u(p.n, 3)
    (grad,) = torch.autograd.grad(mat.form(dict(params, K=Kmod), v, u), Kmod)
    k = 17
    e = torch.zeros(p.n)
    e[k] = 1.0
    dK = (mat.numeric_stiffness(dict(params, K=params["K"] + e)) - mat.numeric_stiffness(params))
    dA = mat.pattern.matrix(dK).toarray()
    expect = v.reshape(-1).numpy() @ dA @ u.reshape(-1).numpy()
    assert abs(float(grad[k]) - expect) <= 1e-10 * abs(expect)


def test_extension_is_the_projected_relative_displacement(lattice):
    p, bonds = lattice
    mat = bp.BondBased(p, bonds)
    u = random_u(p.n, 4)
    n = bonds.xi / bonds.length[:, None]
    expect = np.einsum("ba,ba->b", n, (u[bonds.j] - u[bonds.i]).numpy())
    np.testing.assert_allclose(mat.extension(u).numpy(), expect, rtol=0, atol=1e-14)


def test_intact_fractions_need_one_value_per_bond(lattice):
    p, bonds = lattice
    mat = bp.LPS(p, bonds)
    for wrong in (np.ones(bonds.n - 1), np.ones((bonds.n, 1)), np.ones(0)):
        with pytest.raises(ValueError, match=f"one value per bond \\({bonds.n}\\)"):
            mat.check_intact(wrong)
    mu = mat.check_intact(np.linspace(0, 1, bonds.n, dtype=np.float32))
    assert mu.dtype == torch.float64 and mu.shape == (bonds.n,)


def test_a_particle_without_family_is_refused_by_the_bond_weight():
    """A lone particle farther than delta_max + h/2 from the rest has no bond: the bond weight
    refuses it, naming the particle and the fix."""
    x = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [1.0, 1.0], [9.0, 9.0]])
    p = bp.from_points(x, volume=np.ones(5), h=1.0)
    mat = bp.BondBased(p, bp.find_bonds(p, 1.5))
    with pytest.raises(ValueError, match=r"particle 4 at \[9.0, 9.0\] has an empty family.*increase delta"):
        mat.bond_weight({"K": 1.0, "delta": 1.5})


def test_a_law_missing_an_abstract_method_cannot_be_instantiated(lattice):
    class NoNonlinear(Material):
        moduli_names = ("K",)

        def stiffness_terms(self, moduli, params, factor=1.0, intact=None):
            return []

        def term_coefficients(self, moduli):
            return []

        def energy_parts(self, moduli, params, u, factor=1.0):
            return 0.0, 0.0

        def bulk_energy_parts(self, moduli, params, axis):
            return 0.0, 0.0

    with pytest.raises(TypeError, match="nonlinear"):
        NoNonlinear(*lattice)

    class NoEnergy(Force):
        def force(self, u, intact=None, components=None):
            return u

    with pytest.raises(TypeError, match="strain_energy"):
        NoEnergy(None, {})


@pytest.mark.parametrize("law", LAWS)
def test_force_energy_adds_load_and_confinement(lattice, law):
    """Force.energy = strain energy - p . u + (eps/2) u . u (Dodwell 2019 eq 3)."""
    p, bonds = lattice
    mat = law(p, bonds)
    force = NonlinearBonds(mat).at(params_for(mat, p.n))
    u, load = 0.01 * random_u(p.n, 5), random_u(p.n, 6)
    mu = torch.linspace(0.2, 1.0, bonds.n)
    expect = force.strain_energy(u, mu) - (load * u).sum() + 0.5 * 0.3 * (u * u).sum()
    assert abs(float(force.energy(u, mu, load, 0.3) - expect)) <= 1e-14 * abs(float(expect))
    assert float(force.energy(u, mu)) == float(force.strain_energy(u, mu))


def test_force_refuses_a_displacement_of_another_dtype(lattice):
    mat = bp.BondBased(*lattice)
    force = NonlinearBonds(mat).at({"K": 1.0, "delta": 2.2})
    with pytest.raises(ValueError, match=r"NonlinearBonds.at\(params, dtype=torch.float32\)"):
        force.force(random_u(mat.particles.n, 7).float())
