"""Bond-based PMB: the continuum calibration of the micromodulus."""
import math

import numpy as np
import torch

import bayespd as bp


def interior(p, depth):
    lo, hi = p.lower() + depth, p.upper() - depth
    return np.all((p.x > lo) & (p.x < hi), axis=1)


def test_micromodulus_closed_forms():
    """omega = 1: c t = 9K/(pi delta^3) (plane stress), 72K/(5 pi delta^3) (plane strain),
    c = 18K/(pi delta^4) (3D) -- the constants of the module docstring."""
    p2, p3 = bp.grid_2d(6.0, 6.0, 1.0), bp.grid_3d(4.0, 4.0, 4.0, 1.0)
    K, d = torch.tensor(1e3), 2.5
    for p, plane, expected in [(p2, "stress", 9 * K / (math.pi * d**3)),
                               (p2, "strain", 72 * K / (5 * math.pi * d**3)),
                               (p3, "stress", 18 * K / (math.pi * d**4))]:
        mat = bp.BondBased(p, bp.find_bonds(p, d), plane=plane)
        c = mat.micromodulus(K, {"delta": d}) * p.thickness
        assert abs(float(c / expected) - 1) < 1e-14


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
        k_b = mat.terms({"K": K, "delta": float(m)})[0][2]
        w_b = 0.25 * k_b * mat.extension(u) ** 2  # half of each bond's energy to each end
        i, j = torch.as_tensor(bonds.i), torch.as_tensor(bonds.j)
        per_node = torch.zeros(p.n).index_add(0, i, w_b).index_add(0, j, w_b)
        inner = interior(p, m + 0.5 + 1e-9)
        W = per_node[torch.as_tensor(inner)] / torch.as_tensor(p.volume[inner])
        errors.append(abs(float(W.mean()) - classical) / classical)
    assert errors[1] < errors[0] < 0.1


