"""The MD crack on the coarse grid: which coarse PD bonds it cuts, frame by frame, and the crack
tip (paper 004 sec. 5.2's damage field of the coarse-grained MD, made comparable with PD's).

An atom bond is broken once its stretch has exceeded the potential's cut-off (``bayespd.learn.md``:
r > 2.0 A, no force left), irreversibly. Its crack face is the edge its two atoms' Voronoi cells
share in the reference honeycomb: through the bond's midpoint, normal to it, sqrt(3) a long (the
cells are triangles of side sqrt(3) a), so the faces of a row of broken bonds join into one line
(the bonds themselves leave gaps at the atoms). A coarse bond x_i -> x_j is cut when its segment
crosses a broken bond's face (reference positions); its MD intact fraction is then 0, else 1, and
the MD damage index is the PD one (``bayespd.damage.DamageIndex``, same weights) of those fractions:
both count the share of a node's family that the crack separates from it.
"""
from __future__ import annotations

import numpy as np

from bayespd.learn import graphene
from bayespd.learn.md import A0, CUTOFF

FACE = 1.01 * np.sqrt(3.0) * A0  # A: the length of a broken bond's crack face


def broken_atom_bonds(X, U, pairs=None) -> tuple[np.ndarray, np.ndarray]:
    """(pairs (m, 2), broken (F, m) bool): the nearest-neighbour bonds of ``X`` and, per frame of
    ``U`` (F, n, 2), whether their stretch has exceeded the cut-off at that frame or before."""
    pairs = graphene.bonds(X, A0) if pairs is None else pairs
    strain = np.stack([graphene.bond_strain(X, u, pairs) for u in np.asarray(U, float)])
    return pairs, np.maximum.accumulate(strain > CUTOFF / A0 - 1.0, axis=0)


def _crosses(p, q, a, b) -> np.ndarray:
    """(len(p), len(a)) bool: segment p -> q properly crosses segment a -> b."""
    def side(o, d, x):  # sign of the cross product (d - o) x (x - o), broadcast (k, 1) against (1, m)
        return np.sign((d[..., 0] - o[..., 0]) * (x[..., 1] - o[..., 1]) - (d[..., 1] - o[..., 1]) * (x[..., 0] - o[..., 0]))
    p, q, a, b = p[:, None], q[:, None], a[None], b[None]
    return (side(p, q, a) * side(p, q, b) < 0) & (side(a, b, p) * side(a, b, q) < 0)


def cut_coarse_bonds(x, bond_i, bond_j, X, pairs, broken) -> np.ndarray:
    """(F, bonds) MD intact fraction (0 or 1) of the coarse bonds (node positions ``x``, ends
    ``bond_i``, ``bond_j``) given atom positions ``X``, ``pairs`` and ``broken`` (F, m)."""
    x, X = np.asarray(x, float), np.asarray(X, float)
    ever = np.flatnonzero(broken.any(axis=0))
    intact = np.ones((len(broken), len(bond_i)))
    if ever.size:
        a, b = X[pairs[ever, 0]], X[pairs[ever, 1]]
        normal = (b - a)[:, ::-1] * np.array([1.0, -1.0]) / np.linalg.norm(b - a, axis=1)[:, None]
        half = FACE * normal / 2  # 1 % longer than the ideal face: the relaxed lattice is not ideal
        hit = _crosses(x[bond_i], x[bond_j], (a + b) / 2 - half, (a + b) / 2 + half)  # (bonds, ever)
        for f, row in enumerate(broken[:, ever]):
            intact[f, hit[:, row].any(axis=1)] = 0.0
    return intact


def tip_height(mid_y, broken) -> np.ndarray:
    """(F,) the largest of the bond midpoints' heights ``mid_y`` (m,) among the ``broken`` (F, m)
    bonds (NaN where none is): the crack tip of a crack running up, for atoms or PD bonds."""
    mid_y = np.asarray(mid_y, float)
    return np.array([mid_y[row].max() if row.any() else np.nan for row in np.asarray(broken, bool)])


def slit_centre(X, top: float, reach: float = 5.0) -> float:
    """The x of an edge slit's centre line in the reference atom positions ``X`` (n, 2): the middle
    of the widest gap between the atoms' x within ``reach`` A of x = 0 below the slit's ``top``
    (``bayespd.learn.graphene.edge_slit`` removes one atom column, so the gap is two lattice
    spacings wide and centred on it). A PD pre-crack drawn there puts each coarse node on the side
    of the slit its atoms are on."""
    X = np.asarray(X, float)
    x = np.unique(X[(X[:, 1] < top) & (np.abs(X[:, 0]) < reach), 0])
    if len(x) < 2:
        raise ValueError(f"no atoms within {reach} A of x = 0 below y = {top}: pass the slit's top and a wider reach")
    k = int(np.argmax(np.diff(x)))
    return float(0.5 * (x[k] + x[k + 1]))
