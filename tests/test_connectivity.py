"""Floating pieces followed as bonds break (``bayespd.connectivity``): the same
particles as labelling the graph afresh at every change, with the relabelling skipped
whenever the lost bonds' ends keep a common neighbour."""
import numpy as np
import torch

import bayespd as bp
from bayespd import connectivity
from bayespd.connectivity import FloatingPieces
from bayespd.connectivity import floating_particles


def test_floating_pieces_match_a_fresh_labelling(monkeypatch):
    """A 10 x 10 plate (delta 1.5 h: 8 neighbours), fixed along its bottom row: bonds cut one
    at a time, first crossing a horizontal line (the top half comes loose when the last one
    goes), then all bonds of one particle at the right edge (it comes loose alone), then one
    of them restored. At every step the
    answer equals ``floating_particles``; the first cuts (whose ends keep a common
    neighbour) do not relabel."""
    p = bp.grid_2d(10.0, 10.0, 1.0)
    bonds = bp.find_bonds(p, 1.5)
    fixed = p.x[:, 1] < 1  # a mask, as LoadedBody passes it
    labelled = []
    monkeypatch.setattr(connectivity, "floating_particles",
                        lambda *a: labelled.append(1) or floating_particles(*a))
    pieces = FloatingPieces(bonds, fixed)
    yi, yj = p.x[bonds.i, 1], p.x[bonds.j, 1]
    across = np.flatnonzero((np.minimum(yi, yj) < 5) & (np.maximum(yi, yj) > 5))
    across = across[np.argsort(p.x[bonds.i[across], 0] + p.x[bonds.j[across], 0], kind="stable")]
    lone = int(np.argmin(np.abs(p.x - [9.5, 2.5]).sum(1)))
    own = np.flatnonzero((bonds.i == lone) | (bonds.j == lone))
    intact = torch.ones(bonds.n)
    steps = [[b] for b in across] + [[b] for b in own] + [[-1]]
    for n, cut in enumerate(steps):
        if cut == [-1]:
            intact[own[0]] = 1.0  # restored: pieces may join again
        else:
            intact[cut] = 0.0
        assert np.array_equal(pieces(intact), floating_particles(bonds, intact, fixed)), n
        if n == 1:
            assert len(labelled) == 1  # the first call labels, the first cut reuses it
        if n == len(steps) - 2:
            assert lone in pieces(intact)
    assert np.array_equal(pieces(intact), np.flatnonzero(p.x[:, 1] > 5))  # the top half, the lone particle back
    assert len(labelled) < len(steps) / 2
