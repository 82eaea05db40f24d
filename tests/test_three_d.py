"""3D LPS and bond-based (PMB, conical): patch test, classical energy, symmetry and rigid-body modes."""
import numpy as np
import pytest
import torch

import bayespd as bp

K3, G3 = bp.moduli_from_young(4000.0, 0.3)


def classical_energy_density(K, G, eps):
    """K/2 tr(eps)^2 + G dev(eps):dev(eps) in 3D."""
    tr = torch.trace(eps)
    dev = eps - tr / 3 * torch.eye(3)
    return 0.5 * K * tr**2 + G * (dev * dev).sum()


def inside(p, depth):
    return np.all((p.x > p.lower() + depth) & (p.x < p.upper() - depth), axis=1)


@pytest.fixture(scope="module")
def cube():
    p = bp.grid_3d(14.0, 14.0, 14.0, 1.0)
    return p, bp.find_bonds(p, 2.5)


@pytest.mark.parametrize("cls", [bp.LPS, bp.BondBased, bp.ConicalBondBased])
def test_patch_test_3d(cube, cls):
    p, bonds = cube
    mat = cls(p, bonds)
    params = {"K": K3, "G": G3} if cls is bp.LPS else {"K": K3}
    eps = torch.tensor([[1e-3, 4e-4, 1e-4], [4e-4, -2e-3, 2e-4], [1e-4, 2e-4, 5e-4]])
    f = mat.pattern.matvec(mat.numeric_stiffness(dict(params, delta=2.5)), (torch.as_tensor(p.x) @ eps.T).reshape(-1)).reshape(-1, 3)
    inner = inside(p, 2 * 3.0 + 1e-9)
    assert inner.sum() >= 8
    assert f[inner].abs().max() <= 1e-10 * f[~inner].abs().max()


def test_lps_3d_energy_density(cube):
    """A dilatation is exact (1e-10); a deviatoric strain is within the cubic lattice's
    anisotropy of a few percent at m = 2.5."""
    p, bonds = cube
    mat = bp.LPS(p, bonds)
    x = torch.as_tensor(p.x)
    near = inside(p, 3.0 + 1e-9)
    for eps, rtol in [(1e-3 * torch.eye(3), 1e-10),
                      (torch.tensor([[1e-3, 4e-4, 0.0], [4e-4, -2e-3, 2e-4], [0.0, 2e-4, 5e-4]]), 0.08)]:
        W = mat.energy_density({"K": K3, "G": G3, "delta": 2.5}, x @ eps.T)[near]
        np.testing.assert_allclose(W, float(classical_energy_density(K3, G3, eps)), rtol=rtol)


@pytest.mark.parametrize("cls", [bp.LPS, bp.BondBased, bp.ConicalBondBased])
def test_3d_symmetric_with_six_rigid_modes(cls):
    p = bp.grid_3d(5.0, 4.0, 4.0, 1.0)
    mat = cls(p, bp.find_bonds(p, 2.0))
    n = p.n
    params = {"K": torch.linspace(2000.0, 4000.0, n), "G": torch.linspace(1500.0, 900.0, n)}
    if cls is bp.BondBased:
        params.pop("G")
    A = mat.pattern.matrix(mat.stiffness(dict(params, delta=2.0))).toarray()
    assert abs(A - A.T).max() <= 1e-12 * abs(A).max()
    ev = np.linalg.eigvalsh(A)
    assert np.sum(np.abs(ev) < 1e-9 * ev.max()) == 6 and ev[6] > 1e-6 * ev.max()
