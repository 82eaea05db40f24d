"""Energy-based surface correction (Madenci & Oterkus 2014, §4.2; Le & Bobaru 2018).

A particle near a free surface (a hole, a pre-crack) has a truncated family, so a uniform
strain stores less energy there than in the bulk: the body is too soft near its surfaces.
For each axis a, the uniaxial probe strain e_a e_a^T gives every particle a factor

    g_a,i = (W_classical - W_fixed,i) / W_bond,i,

where W_bond is the part of the PD energy density carried by the bonds (all of it for
bond-based; the deviatoric bond sum for LPS, whose dilatation part W_fixed is left as is).
A bond with unit direction n takes the mean of its ends' factors along each axis and
combines them on an ellipse (ellipsoid in 3D):

    G_b = (sum_a (n_a / gbar_a)^2)^(-1/2).

The factors depend on the moduli and params["delta"] and are differentiable in both.
"""
from __future__ import annotations

import torch


def bond_factors(material, moduli: dict, params: dict) -> torch.Tensor:
    """Correction factor G_b per bond (see the module docstring)."""
    x = torch.as_tensor(material.particles.x)
    i, j = material.i, material.j
    inverse_square = 0.0
    for a in range(material.dim):
        eps = torch.zeros(material.dim, material.dim)
        eps[a, a] = 1.0
        fixed, bond = material.energy_parts(moduli, params, x @ eps.T)
        g = (sum(material.bulk_energy_parts(moduli, params, a)) - fixed) / bond
        if not bool(torch.all(torch.isfinite(g) & (g > 0))):
            raise ValueError("surface correction failed: a particle's family stores no energy "
                             f"under uniaxial strain along axis {a} (an isolated particle or a "
                             "family in one line?); remove it or switch the correction off")
        inverse_square = inverse_square + (material.unit[:, a] / (0.5 * (g[i] + g[j]))) ** 2
    return inverse_square ** -0.5
