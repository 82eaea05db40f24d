"""LPS: the patch test at any horizon and plane, and the exact lattice energy of a dilatation
and of a deviatoric pair (the laws' shared checks are in test_laws.py)."""
import numpy as np
import pytest
import torch

import bayespd as bp

E, NU = 4000.0, 0.3


def classical_energy_density(eps, plane):
    """1/2 eps : C : eps for isotropic 2D elasticity written with E and nu."""
    if plane == "stress":
        C = E / (1 - NU**2) * np.array([[1, NU, 0], [NU, 1, 0], [0, 0, (1 - NU) / 2]])
    else:
        f = E / ((1 + NU) * (1 - 2 * NU))
        C = f * np.array([[1 - NU, NU, 0], [NU, 1 - NU, 0], [0, 0, (1 - 2 * NU) / 2]])
    v = np.array([eps[0, 0], eps[1, 1], 2 * eps[0, 1]])
    return 0.5 * v @ C @ v



@pytest.fixture(scope="module", params=["linear", "smooth"])
def lattice(request):
    p = bp.grid_2d(24.0, 24.0, 1.0)
    return p, bp.find_bonds(p, 3.0, rule=request.param)


@pytest.mark.parametrize("plane", ["stress", "strain"])
@pytest.mark.parametrize("delta", [2.0, 2.7, 3.0])
def test_lps_patch_test_zero_interior_force(lattice, plane, delta):
    p, bonds = lattice
    mat = bp.LPS(p, bonds, plane=plane)
    K, G = bp.moduli_from_young(E, NU)
    params = {"K": K, "G": G, "delta": delta}
    eps = torch.tensor([[1e-3, 4e-4], [4e-4, -2e-3]])
    u = torch.as_tensor(p.x) @ eps.T
    values = mat.stiffness(params)
    f = mat.pattern.matvec(values, u.reshape(-1)).reshape(-1, 2)
    inner = p.interior(2 * (delta + 0.5) + 1e-9)  # own and neighbours' families complete
    scale = f[~inner].abs().max()
    assert inner.sum() > 20
    assert f[inner].abs().max() <= 1e-10 * scale


@pytest.mark.parametrize("plane", ["stress", "strain"])
def test_lps_energy_density_matches_classical(lattice, plane):
    """Dilatation is exact on the lattice; the two deviatoric modes of a square lattice
    differ (cubic anisotropy), but a strain and its 45-degree rotation together are exact."""
    p, bonds = lattice
    delta = 3.0
    mat = bp.LPS(p, bonds, plane=plane)
    K, G = bp.moduli_from_young(E, NU)
    params = {"K": K, "G": G, "delta": delta}
    inner = p.interior(delta + 0.5 + 1e-9)
    x = torch.as_tensor(p.x)

    def W(eps):
        return mat.energy_density(params, x @ torch.as_tensor(eps).T)[inner]

    iso = 1e-3 * np.eye(2)
    np.testing.assert_allclose(W(iso), classical_energy_density(iso, plane), rtol=1e-8)
    eps = np.array([[1e-3, 4e-4], [4e-4, -2e-3]])
    c, s = np.cos(np.pi / 4), np.sin(np.pi / 4)
    R = np.array([[c, -s], [s, c]])
    pair = W(eps) + W(R @ eps @ R.T)
    np.testing.assert_allclose(pair, 2 * classical_energy_density(eps, plane), rtol=1e-8)
    # single deviatoric mode: lattice anisotropy of a few percent at m = 3
    np.testing.assert_allclose(W(eps), classical_energy_density(eps, plane), rtol=0.05)


def test_the_kept_family_gives_the_fresh_terms_and_gradients():
    """w, m and the dilatation vectors are kept per horizon while it needs no gradient: a second
    ``terms`` at the same horizon reuses them (the same tensors) and gives the K, G gradients
    of a fresh material to the last bit; a horizon that needs a gradient is never served from
    the cache (its gradient equals a fresh material's), and a new horizon recomputes them."""
    p = bp.grid_2d(12.0, 8.0, 1.0)
    bonds = bp.find_bonds(p, 3.0)
    kept, fresh = bp.LPS(p, bonds), bp.LPS(p, bonds)
    u = torch.as_tensor(np.random.default_rng(3).standard_normal((p.n, 2)))

    def grads(mat, delta_grad):
        q = {"K": torch.tensor(3000.0, requires_grad=True), "G": torch.tensor(1500.0, requires_grad=True),
             "delta": torch.tensor(2.6, requires_grad=delta_grad)}
        leaves = [q[k] for k in ("K", "G", "delta") if q[k].requires_grad]
        return torch.autograd.grad(mat.form(q, u, u), leaves)

    with torch.no_grad():
        first = kept.terms({"K": 3000.0, "G": 1500.0, "delta": 2.6})
    assert kept.terms({"K": 4000.0, "G": 1000.0, "delta": torch.tensor(2.6)})[1][1].data_ptr() == first[1][1].data_ptr()
    for got, want in zip(grads(kept, False), grads(fresh, False)):
        assert torch.equal(got, want)
    for got, want in zip(grads(kept, True), grads(fresh, True)):
        assert torch.equal(got, want)
    assert kept.terms({"K": 3000.0, "G": 1500.0, "delta": 2.3})[1][1].data_ptr() != first[1][1].data_ptr()


@pytest.mark.parametrize("dim, options", [(2, {"plane": "stress"}),
                                          (2, {"plane": "strain", "surface_correction": True}),
                                          (3, {})])
def test_form_from_bond_extensions_is_the_gram_form(dim, options):
    """LPS.form (dilatations from the bond extensions, eq 10) is v^T K u of the Gram terms
    (Material.form): value, gradient in (K, G, delta) and a Hessian-vector product agree to
    1e-13 relative (the same sums in another order; measured <= 2e-15)."""
    from bayespd.materials.base import Material

    torch.manual_seed(0)
    p = bp.grid_2d(14.0, 9.0, 1.0) if dim == 2 else bp.grid_3d(6.0, 5.0, 4.0, 1.0)
    mat = bp.LPS(p, bp.find_bonds(p, 3.0), **options)
    v, u = torch.randn(p.n * dim, dtype=torch.float64), torch.randn(p.n * dim, dtype=torch.float64)
    results = []
    for form in (Material.form, bp.LPS.form):
        q = {"K": torch.linspace(3000.0, 3600.0, p.n, dtype=torch.float64).requires_grad_(),
             "G": torch.tensor(1500.0, dtype=torch.float64, requires_grad=True),
             "delta": torch.tensor(2.6, dtype=torch.float64, requires_grad=True)}
        value = form(mat, q, v, u)
        grads = torch.autograd.grad(value, list(q.values()), create_graph=True)
        hvp = torch.autograd.grad(sum(g.sum() for g in grads), list(q.values()))
        results.append([value, *grads, *hvp])
    for a, b in zip(*results):
        assert (a - b).abs().max() <= 1e-13 * b.abs().max()
