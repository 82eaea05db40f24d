"""Systems for the linear-algebra tests: a generic SPD matrix and an LPS plate's Gram terms."""
import numpy as np
import scipy.sparse as sp
import torch

import bayespd as bp
from bayespd.linalg.sparse import Pattern


def lps_terms(nx=14, ny=8, m=2.6, delta=2.4, plane="stress"):
    """(particles, bonds, material, terms): the Gram terms of an LPS plate, an operator made
    of 2 x 2 node blocks."""
    p = bp.grid_2d(float(nx), float(ny), 1.0)
    bonds = bp.find_bonds(p, m)
    mat = bp.LPS(p, bonds, plane=plane)
    terms = mat.terms({"K": torch.tensor(3000.0), "G": torch.tensor(1500.0), "delta": torch.tensor(delta)})
    return p, bonds, mat, terms


def grid_spd(side: int = 12, shift: float = 2.0, scale: float = 1e-3) -> sp.csc_matrix:
    """shift I + scale (L kron C): L the 5-point Laplacian of a side x side grid (Dirichlet),
    C = [[2, 1], [1, 2]] coupling each node's two dofs; SPD, sorted CSC."""
    d = sp.diags([-1.0, 2.0, -1.0], [-1, 0, 1], shape=(side, side))
    L = sp.kron(d, sp.identity(side)) + sp.kron(sp.identity(side), d)
    M = sp.identity(2 * side * side) * shift + scale * sp.kron(L, np.array([[2.0, 1.0], [1.0, 2.0]]))
    M = M.tocsc()
    M.sort_indices()
    return M


def csc_pattern(M):
    """(Pattern, values) of a scipy CSC matrix."""
    cols = np.repeat(np.arange(M.shape[0]), np.diff(M.indptr))
    return Pattern(M.indices, cols, M.shape[0]), torch.as_tensor(M.data)
