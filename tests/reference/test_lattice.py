"""bayespd/reference/lattice.py: the effective tensor C_m of an LPS grid at fixed m."""
import numpy as np
import pytest

import bayespd as bp
from bayespd.reference.fem import isotropic_stiffness
from bayespd.reference.lattice import lattice_stiffness


def test_lattice_stiffness_exact_on_average():
    """Dilatation is exact on the grid and the rotational average of the deviatoric energy is
    exact, so C_m is isotropic 'on average'; its cubic anisotropy (1.9e-2 at m = 3) fades as m
    grows (2.6e-5 at m = 16)."""
    K, G = (float(v) for v in bp.moduli_from_young(4000.0, 0.3))
    kappa = 9 * K * G / (3 * K + 4 * G)  # plane-stress in-plane bulk modulus
    C = lattice_stiffness(3, K, G, dim=2)
    np.testing.assert_allclose(C[0, 0] + C[0, 1], 2 * kappa, rtol=1e-10)
    np.testing.assert_allclose((C[0, 0] - C[0, 1]) / 2 + C[2, 2], 2 * G, rtol=1e-10)
    assert C[0, 2] == 0 and C[1, 2] == 0
    C3 = lattice_stiffness(2, K, G, dim=3)
    np.testing.assert_allclose(C3[0, 0] + 2 * C3[0, 1], 3 * K, rtol=1e-10)
    np.testing.assert_allclose((C3[0, 0] - C3[0, 1] + 3 * C3[3, 3]) / 5, G, rtol=1e-10)
    iso = isotropic_stiffness(4000.0, 0.3, 2)
    a3, a16 = (np.linalg.norm(lattice_stiffness(m, K, G) - iso) / np.linalg.norm(iso) for m in (3, 16))
    assert 0.01 < a3 < 0.03 and a16 < a3 / 100

@pytest.mark.parametrize("rule", ["linear", "smooth"])
@pytest.mark.parametrize("m", [2.5, 3.0])
def test_lattice_tensor_is_symmetric_cubic_and_exact_on_average(m, rule):
    """For either partial-volume ramp and non-integer m: C_m is symmetric positive definite
    with cubic symmetry (C11 = C22, no normal-shear coupling), its in-plane bulk modulus is
    exact, C11 + C12 = 2 kappa, and so is its rotational average of the shear modulus,
    (C11 - C12) / 2 + C66 = 2 G (to rounding, 1e-10)."""
    K, G = (float(v) for v in bp.moduli_from_young(4000.0, 0.3))
    kappa = 9 * K * G / (3 * K + 4 * G)
    C = lattice_stiffness(m, K, G, rule=rule)
    np.testing.assert_array_equal(C, C.T)
    assert np.linalg.eigvalsh(C).min() > 0
    assert C[0, 0] == pytest.approx(C[1, 1], rel=1e-12)
    assert C[0, 2] == C[1, 2] == 0.0
    np.testing.assert_allclose(C[0, 0] + C[0, 1], 2 * kappa, rtol=1e-10)
    np.testing.assert_allclose((C[0, 0] - C[0, 1]) / 2 + C[2, 2], 2 * G, rtol=1e-10)
    assert abs(C[2, 2] / G - 1) > 1e-4  # cubic, not isotropic: the quadrature error is real


def test_lattice_tensor_is_linear_in_the_moduli():
    """In plane strain (and 3D) W is linear in (K, G): C_m(2 K1 + 3 K2, 2 G1 + 3 G2) =
    2 C_m(K1, G1) + 3 C_m(K2, G2); in plane stress the in-plane bulk modulus 9KG / (3K + 4G)
    is not linear, only homogeneous of degree 1: C_m(a K, a G) = a C_m(K, G)."""
    C1, C2 = (lattice_stiffness(3, K, G, plane="strain") for K, G in ((2.0, 1.0), (1.0, 3.0)))
    np.testing.assert_allclose(lattice_stiffness(3, 2 * 2.0 + 3 * 1.0, 2 * 1.0 + 3 * 3.0, plane="strain"),
                               2 * C1 + 3 * C2, rtol=1e-12, atol=1e-12 * np.abs(C2).max())
    np.testing.assert_allclose(lattice_stiffness(3, 7.0, 5.0), 2.5 * lattice_stiffness(3, 2.8, 2.0),
                               rtol=1e-12, atol=1e-12)
