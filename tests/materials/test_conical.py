"""Conical bond-based law: the calibration constants of its docstring, its bond stiffness
(the PMB one times the profile), and the continuum calibration converging with m."""

import numpy as np
import pytest
import torch

import bayespd as bp



def test_bond_stiffness_is_pmb_times_the_profile():
    """k_b = (c0 / c) (1 - |xi|/delta)_+ k_b(PMB), with c0 / c = M_2 / C_2 = 4 for omega = 1 in
    2D; bonds at or beyond the horizon carry nothing."""
    p = bp.grid_2d(10.0, 10.0, 1.0)
    bonds = bp.find_bonds(p, 3.0)
    params = {"K": 1e3, "delta": 2.6}
    cone = bp.ConicalBondBased(p, bonds)
    k, k_pmb = (m.bond_stiffness(m.moduli(params), params) for m in (cone, bp.BondBased(p, bonds)))
    profile = torch.clamp(1 - cone.length / 2.6, min=0)
    np.testing.assert_allclose(k, 4 * profile * k_pmb, rtol=1e-13, atol=0)
    assert float(k[cone.length >= 2.6].abs().max()) == 0.0 and bool(torch.any(k_pmb[cone.length >= 2.6] > 0))


@pytest.mark.parametrize("plane", ["stress", "strain"])
def test_isotropic_expansion_converges_with_m(plane):
    """The continuum calibration: the interior energy of an isotropic expansion tends to the
    classical kappa/2 tr(eps)^2 (kappa = 3K/4, 6K/5) as m grows (measured 5.8 % -> 1.0 %)."""
    K, strain = 1.0e3, 1e-3
    classical = 0.5 * (2 * strain) ** 2 * (0.75 if plane == "stress" else 1.2) * K
    errors = []
    for m in (3, 6):
        p = bp.grid_2d(8.0 * m, 8.0 * m, 1.0)
        mat = bp.ConicalBondBased(p, bp.find_bonds(p, float(m)), plane=plane)
        W = mat.energy_density({"K": K, "delta": float(m)}, strain * torch.as_tensor(p.x))
        errors.append(abs(float(W[p.interior(m + 0.5 + 1e-9)].mean()) / classical - 1))
    assert errors[1] < 0.25 * errors[0] and errors[0] < 0.07, errors


def test_three_d_isotropic_expansion():
    """3D (K the bulk modulus): within the quadrature error at m = 2 (measured 6.5 %)."""
    K, strain = 1.0e3, 1e-3
    p = bp.grid_3d(12.0, 12.0, 12.0, 1.0)
    mat = bp.ConicalBondBased(p, bp.find_bonds(p, 2.0))
    W = mat.energy_density({"K": K, "delta": 2.0}, strain * torch.as_tensor(p.x))
    inner = p.interior(2.5 + 1e-9)
    assert inner.sum() >= 100
    np.testing.assert_allclose(W[inner].numpy(), 0.5 * K * (3 * strain) ** 2, rtol=0.08)
