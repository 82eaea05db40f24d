"""Where a damage error comes from (paper 004 sec. 5.2-5.4, eq 5.4 fields on a coarse grid): the
field operations that separate a PD-MD damage mismatch into crack timing, crack position and
crack path, each compared by the same relative error (``bayespd.learn.discrepancy``).

* ``lagged``: a field history delayed (lag > 0) or advanced by whole frames: the error left once
  the PD crack's initiation and speed are aligned with the data's.
* ``shifted``: a field moved by a lattice vector on a regular grid: the error left once the PD
  crack's line is moved onto the data's.
* ``cone_average``: the cone-weighted nodal average of radius R, 1 - r / R (eq 2.2's weight), the
  same operator on both fields: the error at the resolution R, where paths closer than R agree.
* ``straight_crack_intact``: the 0/1 intact fractions of the coarse bonds for a straight crack up
  a line to a given tip height per frame: with the data's own tip history it has the data's
  timing and length exactly, so its error against the data is the part due to the path alone.
"""
from __future__ import annotations

import numpy as np
import scipy.sparse
from scipy.spatial import cKDTree

from bayespd.learn.md_damage import _crosses
from bayespd.validate import positive


def lagged(field, lag: int) -> np.ndarray:
    """``field`` (F, ...) with frame f holding frame f - lag (lag > 0: later; the first frames hold
    frame 0; lag < 0: earlier, the last frames hold the last one)."""
    field = np.asarray(field, float)
    return field[np.clip(np.arange(len(field)) - int(lag), 0, len(field) - 1)]


def shifted(field, x, shift) -> np.ndarray:
    """``field`` (..., N) on the nodes ``x`` (N, 2) moved by ``shift`` (2,): node k takes the value
    of the node at x_k - shift, 0 where there is none (within 1e-6 of the smallest spacing)."""
    x = np.asarray(x, float)
    tree = cKDTree(x)
    spacing = float(tree.query(x, k=2)[0][:, 1].min())
    dist, src = tree.query(x - np.asarray(shift, float), distance_upper_bound=1e-6 * spacing)
    found = np.isfinite(dist)
    out = np.zeros(np.shape(field))
    out[..., found] = np.asarray(field, float)[..., src[found]]
    return out


def cone_average(field, x, radius: float) -> np.ndarray:
    """sum_j w_ij a_j / sum_j w_ij with w_ij = max(1 - |x_i - x_j| / R, 0) for ``field`` (..., N)."""
    x = np.asarray(x, float)
    positive("radius", radius, "pass the averaging radius in the grid's units")
    tree = cKDTree(x)
    pairs = tree.query_pairs(radius, output_type="ndarray")  # i < j, each pair once
    r = np.linalg.norm(x[pairs[:, 0]] - x[pairs[:, 1]], axis=1)
    n = len(x)
    w = scipy.sparse.coo_matrix((np.tile(1.0 - r / radius, 2), (np.r_[pairs[:, 0], pairs[:, 1]],
                                 np.r_[pairs[:, 1], pairs[:, 0]])), shape=(n, n)) + scipy.sparse.eye(n)
    w = scipy.sparse.diags(1.0 / np.asarray(w.sum(axis=1)).ravel()) @ w.tocsr()
    flat = np.asarray(field, float).reshape(-1, n)
    return (w @ flat.T).T.reshape(np.shape(field))


def straight_crack_intact(x, bond_i, bond_j, line_x: float, base_y: float, tips) -> np.ndarray:
    """(F, bonds) 0/1 intact fractions of the bonds ``bond_i`` -> ``bond_j`` between the nodes ``x``
    for a straight crack along x = ``line_x`` from ``base_y`` up to ``tips`` (F,) (NaN: no crack
    yet); a bond is cut when it properly crosses that segment."""
    x = np.asarray(x, float)
    tips = np.asarray(tips, float)
    p, q = x[np.asarray(bond_i)], x[np.asarray(bond_j)]
    intact = np.ones((len(tips), len(p)))
    for f, top in enumerate(tips):
        if np.isfinite(top) and top > base_y:
            intact[f, _crosses(p, q, np.array([[line_x, base_y]]), np.array([[line_x, top]]))[:, 0]] = 0.0
    return intact
