"""Bond-based PMB: the continuum calibration of the micromodulus."""
import torch

import bayespd as bp


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
        inner = p.interior(m + 0.5 + 1e-9)
        W = per_node[torch.as_tensor(inner)] / torch.as_tensor(p.volume[inner])
        errors.append(abs(float(W.mean()) - classical) / classical)
    assert errors[1] < errors[0] < 0.1


