"""Patch tests, symmetry and energy consistency of the linearised materials."""
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


def interior(p, depth):
    lo, hi = p.lower() + depth, p.upper() - depth
    return np.all((p.x > lo) & (p.x < hi), axis=1)


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
    params = {"K": K, "G": G}
    eps = torch.tensor([[1e-3, 4e-4], [4e-4, -2e-3]])
    u = torch.as_tensor(p.x) @ eps.T
    values = mat.stiffness(params, delta)
    f = mat.pattern.matvec(values, u.reshape(-1)).reshape(-1, 2)
    inner = interior(p, 2 * (delta + 0.5) + 1e-9)  # own and neighbours' families complete
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
    params = {"K": K, "G": G}
    inner = interior(p, delta + 0.5 + 1e-9)
    x = torch.as_tensor(p.x)

    def W(eps):
        return mat.energy_density(params, delta, x @ torch.as_tensor(eps).T)[inner]

    iso = 1e-3 * np.eye(2)
    np.testing.assert_allclose(W(iso), classical_energy_density(iso, plane), rtol=1e-8)
    eps = np.array([[1e-3, 4e-4], [4e-4, -2e-3]])
    c, s = np.cos(np.pi / 4), np.sin(np.pi / 4)
    R = np.array([[c, -s], [s, c]])
    pair = W(eps) + W(R @ eps @ R.T)
    np.testing.assert_allclose(pair, 2 * classical_energy_density(eps, plane), rtol=1e-8)
    # single deviatoric mode: lattice anisotropy of a few percent at m = 3
    np.testing.assert_allclose(W(eps), classical_energy_density(eps, plane), rtol=0.05)


def test_bond_based_isotropic_expansion_converges_with_m():
    """PMB is calibrated on the continuum family; with partial volumes the discrete energy
    density of an isotropic expansion approaches the classical one as m = delta/h grows."""
    K = 1.0e3  # plane-stress PMB: nu = 1/3, E = K, 2D bulk modulus 3E/4
    strain = 1e-3
    classical = 0.5 * (2 * strain) ** 2 * (0.75 * K)
    errors = []
    for m in (3, 6):
        p = bp.grid_2d(8.0 * m, 8.0 * m, 1.0)
        bonds = bp.find_bonds(p, float(m))
        mat = bp.BondBased(p, bonds)
        u = strain * torch.as_tensor(p.x)
        k_b = mat._terms({"K": K}, float(m))[0][2]
        w_b = 0.25 * k_b * mat.extension(u) ** 2  # half of each bond's energy to each end
        i, j = torch.as_tensor(bonds.i), torch.as_tensor(bonds.j)
        per_node = torch.zeros(p.n).index_add(0, i, w_b).index_add(0, j, w_b)
        inner = interior(p, m + 0.5 + 1e-9)
        W = per_node[torch.as_tensor(inner)] / torch.as_tensor(p.volume[inner])
        errors.append(abs(float(W.mean()) - classical) / classical)
    assert errors[1] < errors[0] < 0.1


@pytest.mark.parametrize("cls", [bp.LPS, bp.BondBased])
def test_stiffness_symmetric_and_consistent(lattice, cls):
    p, bonds = lattice
    mat = cls(p, bonds, plane="stress")
    n = p.n
    K = torch.linspace(2000.0, 4000.0, n)  # heterogeneous field: K stays symmetric
    G = torch.linspace(1500.0, 900.0, n)
    params = {"K": K, "G": G}
    values = mat.stiffness(params, 2.7)
    A = mat.pattern.matrix(values)
    asym = abs(A - A.T).max()
    assert asym <= 1e-12 * abs(A).max()
    np.testing.assert_allclose(mat.numeric_stiffness(params, 2.7), values, rtol=0, atol=1e-12 * abs(A).max())
    u = torch.randn(n, 2, generator=torch.Generator().manual_seed(0))
    quad = float(u.reshape(-1) @ torch.as_tensor(A @ u.reshape(-1).numpy()))
    np.testing.assert_allclose(float(2 * mat.energy(params, 2.7, u)), quad, rtol=1e-12)
    # rigid-body modes are in the null space: exactly 3 zero eigenvalues in 2D
    ev = np.linalg.eigvalsh(A.toarray())
    assert np.sum(np.abs(ev) < 1e-9 * ev.max()) == 3 and ev[3] > 1e-6 * ev.max()
