"""The pieces of a body that hold no fixed particle: the one check that the static Scene (which
refuses them), the linear force (which reports them) and the quasi-static and fracture
solvers (which drop their dofs) share.

``floating_particles`` labels the components of the intact-bond graph afresh (a pass over
every bond). Between two calls of a fracture run a few bonds break, and breaking a bond
(i, j) cannot split a component when i and j still share an intact neighbour k (the path
i-k-j stands in for it); when that holds for every bond lost since the last call, the
graph's components, and so the floating particles, are unchanged. ``FloatingPieces``
checks that first and relabels only when it fails (a bond whose ends lost every common
neighbour: the crack faces far behind its tip, or a piece coming loose).
"""
from __future__ import annotations

import numpy as np
import torch

from bayespd.bond_loops import components

CONNECTED = 1e-6  # bonds with a smaller intact fraction no longer hold a piece in place
MAX_CHECKED = 64  # more bonds lost at once than this: relabel instead of checking each


def floating_particles(bonds, intact, fixed: np.ndarray) -> np.ndarray:
    """Indices of the particles in pieces of the graph of bonds with intact fraction above
    CONNECTED (all bonds when ``intact`` is None) that hold no ``fixed`` particle."""
    n = len(fixed)
    keep = np.ones(bonds.n, dtype=bool) if intact is None else np.asarray(torch.as_tensor(intact) > CONNECTED)
    count, label = components(n, bonds.i, bonds.j, keep)
    anchored = np.zeros(count, dtype=bool)
    anchored[label[fixed]] = True
    return np.flatnonzero(~anchored[label])


class FloatingPieces:
    """``floating(intact)``: indices of the particles in pieces of the graph of bonds with
    intact fraction above CONNECTED that hold no ``fixed`` particle (as
    ``floating_particles``), reusing the previous answer when the change cannot split a piece."""

    def __init__(self, bonds, fixed: np.ndarray):
        self.bonds, self.fixed = bonds, fixed
        self._indptr, self._bond, self._other = _by_particle(bonds, len(fixed))
        self._keep, self._floating = None, None

    def __call__(self, intact) -> np.ndarray:
        keep = np.asarray(torch.as_tensor(intact) > CONNECTED)
        if self._keep is None or not self._unsplit(keep):
            self._floating = floating_particles(self.bonds, intact, self.fixed)
        self._keep = keep
        return self._floating

    def _unsplit(self, keep: np.ndarray) -> bool:
        """True when ``keep`` only drops bonds of the last graph, each of whose ends still
        share an intact neighbour."""
        lost = np.flatnonzero(keep != self._keep)
        if keep[lost].any():
            return False  # a bond was restored: pieces may have joined
        if len(lost) > MAX_CHECKED:
            return False
        return all(np.intersect1d(self._neighbours(i, keep), self._neighbours(j, keep), assume_unique=True).size
                   for i, j in zip(self.bonds.i[lost], self.bonds.j[lost]))

    def _neighbours(self, p: int, keep: np.ndarray) -> np.ndarray:
        span = slice(self._indptr[p], self._indptr[p + 1])
        return self._other[span][keep[self._bond[span]]]


_BY_PARTICLE: list = []  # [(bonds, n, arrays)]: the latest two (the bonds held, so their id stays theirs)


def _by_particle(bonds, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(indptr, bond, other): the bonds of particle p are bond[indptr[p]:indptr[p + 1]] and
    their other ends other[...]; read-only, shared by the trackers of the same bonds (the
    runs of an ensemble's worker: 5 MB each at 10k particles)."""
    for held, size, arrays in _BY_PARTICLE:
        if held is bonds and size == n:
            return arrays
    ends = np.concatenate([bonds.i, bonds.j])
    order = np.argsort(ends, kind="stable")
    arrays = (np.concatenate([[0], np.cumsum(np.bincount(ends, minlength=n))]), order % bonds.n,
              np.concatenate([bonds.j, bonds.i])[order])
    for a in arrays:
        a.setflags(write=False)
    _BY_PARTICLE[:] = [(bonds, n, arrays)] + _BY_PARTICLE[:1]
    return arrays
