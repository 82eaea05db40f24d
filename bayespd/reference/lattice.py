"""Effective elasticity tensor of an LPS lattice at fixed m = delta / h.

On a square (cubic) grid the one-point quadrature of the LPS energy (Delorme 2018 eq 40 with the
partial-volume rule, §2.2.4) is exact for dilatation but not for the deviatoric part: an
interior particle stores W = 1/2 eps : C_m : eps with a tensor C_m of cubic symmetry that
differs from the isotropic one by a few percent at m = 2-3 and tends to it as m grows. So at
fixed m the PD solution converges, as delta -> 0, to the local problem with C_m, not to the
isotropic one: the error against an isotropic FE peer has a floor set by |C_m - C|. An FE
peer built with C_m isolates the part of the error that does vanish with delta.
"""
from __future__ import annotations

import math

import numpy as np
import torch

import bayespd as bp
from bayespd.reference.fem import VOIGT


def lattice_stiffness(m: float, K: float, G: float, dim: int = 2, plane: str = "stress",
                      rule: str = "linear") -> np.ndarray:
    """Voigt tensor C_m (``fem.VOIGT`` order) stored by an interior particle of the grid.

    Computed from the energy density of the central particle of a grid with h = 1 and
    delta = m under the unit Voigt strains and their pairwise sums (W is quadratic in eps);
    ``rule``: the partial-volume ramp (``bayespd.bonds.partial_volume``).
    """
    n = 2 * math.ceil(m) + 5  # the central particle's family is complete
    p = bp.grid_2d(n, n, 1.0) if dim == 2 else bp.grid_3d(n, n, n, 1.0)
    material = bp.LPS(p, bp.find_bonds(p, m, rule), plane=plane)
    centre = int(np.argmin(np.linalg.norm(p.x - n / 2, axis=1)))
    x = torch.as_tensor(p.x)
    params = {"K": K, "G": G, "delta": m}
    modes = VOIGT[dim]

    def unit(k):
        eps = np.zeros((dim, dim))
        a, b = modes[k]
        eps[a, b] = eps[b, a] = 1.0 if a == b else 0.5  # engineering shear strain 1
        return eps

    def W(eps):
        u = x @ torch.as_tensor(eps).T
        with torch.no_grad():
            return float(material.energy_density(params, u)[centre])

    k = len(modes)
    C = np.zeros((k, k))
    for a in range(k):
        C[a, a] = 2 * W(unit(a))
    for a in range(k):
        for b in range(a + 1, k):
            C[a, b] = C[b, a] = W(unit(a) + unit(b)) - 0.5 * (C[a, a] + C[b, b])
    C[np.abs(C) < 1e-9 * np.abs(C).max()] = 0.0  # round-off where cubic symmetry gives zeros
    return C
