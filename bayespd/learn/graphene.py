"""A single-layer graphene sheet: honeycomb positions, nearest-neighbour bonds, bond strains.

The sheet is built zigzag along x: a rectangular cell of width sqrt(3) a and height 3 a holds
four atoms, so a periodic box of ``nx`` by ``ny`` cells is commensurate with the lattice
(``a`` is the C-C distance: 1.46 A in paper 004 with Tersoff, about 1.42 A with REBO-II).
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from bayespd.validate import count, in_range, positive

CELL_FRACTIONS = np.array([[0.0, 0.0], [0.5, 0.5 / 3.0], [0.5, 0.5], [0.0, 2.0 / 3.0]])  # of (sqrt3 a, 3a)


def cell_size(a: float) -> np.ndarray:
    """(width, height) of the four-atom rectangular cell for C-C distance ``a``."""
    positive("a", a, "pass the C-C bond length in angstrom (about 1.42)")
    return np.array([np.sqrt(3.0) * a, 3.0 * a])


def cells_for(width: float, height: float, a: float) -> tuple[int, int]:
    """The numbers of cells whose box is closest to ``width`` x ``height`` (at least 2 each)."""
    positive("width", width, "pass the sheet width in angstrom")
    positive("height", height, "pass the sheet height in angstrom")
    w, h = cell_size(a)
    return max(2, round(width / w)), max(2, round(height / h))


def sheet(nx: int, ny: int, a: float) -> tuple[np.ndarray, np.ndarray]:
    """Positions (n, 2) of ``nx`` x ``ny`` cells with the box's lower-left corner at the origin,
    and the box size (2,). Atom order: cell by cell, row-major in (y, x)."""
    count("nx", nx, 2, "pass at least 2 cells")
    count("ny", ny, 2, "pass at least 2 cells")
    size = cell_size(a)
    j, i = np.meshgrid(np.arange(ny), np.arange(nx), indexing="ij")
    corners = np.stack([i.ravel(), j.ravel()], axis=1)[:, None, :]
    offset = np.array([0.25, 0.25 / 3.0])  # keeps every atom strictly inside the box
    x = (corners + CELL_FRACTIONS[None] + offset) * size
    return x.reshape(-1, 2), np.array([nx, ny]) * size


def bonds(x: np.ndarray, a: float, box: np.ndarray | None = None) -> np.ndarray:
    """Nearest-neighbour pairs (m, 2), i < j, of positions ``x``: those closer than 1.2 ``a``
    (the second neighbours sit at sqrt(3) a). ``box`` makes x and y periodic with that size."""
    x = np.asarray(x, float)
    if box is not None:
        x = np.mod(x, box)
    tree = cKDTree(x, boxsize=None if box is None else np.asarray(box, float))
    return np.array(sorted(tree.query_pairs(1.2 * a)), dtype=np.int64).reshape(-1, 2)


def bond_strain(x: np.ndarray, u: np.ndarray, pairs: np.ndarray, box: np.ndarray | None = None) -> np.ndarray:
    """Stretch |xi + eta| / |xi| - 1 of each pair (paper 004 eq 3.11), xi by the minimum image
    when ``box`` is given."""
    xi = x[pairs[:, 1]] - x[pairs[:, 0]]
    if box is not None:
        xi -= np.round(xi / box) * box
    eta = u[pairs[:, 1]] - u[pairs[:, 0]]
    return np.linalg.norm(xi + eta, axis=1) / np.linalg.norm(xi, axis=1) - 1.0


def edge_slit(x: np.ndarray, centre_x: float, bottom: float, length: float, a: float) -> np.ndarray:
    """Mask of the atoms kept after cutting a vertical slit of ``length`` up from ``bottom`` at
    ``centre_x``: the atoms within 0.6 ``a`` of the line are removed, which breaks every bond
    crossing it (a zigzag-x sheet has bonds with |xi_x| <= sqrt(3)/2 a)."""
    positive("length", length, "pass the slit length in angstrom")
    in_range("a", a, 0.5, 3.0, "pass the C-C bond length in angstrom")
    return ~((np.abs(x[:, 0] - centre_x) < 0.6 * a) & (x[:, 1] < bottom + length))
