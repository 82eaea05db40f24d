"""Floating pieces followed as bonds break (``bayespd.solvers.connectivity``): the same
particles as labelling the graph afresh at every change, with the relabelling skipped
whenever the lost bonds' ends keep a common neighbour."""
import numpy as np
import pytest
import scipy.sparse as sp
import torch
from scipy.sparse.csgraph import connected_components

import bayespd as bp
from bayespd import bond_loops
from bayespd.solvers import connectivity
from bayespd.solvers.connectivity import FloatingPieces
from bayespd.solvers.linear import floating_particles


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


@pytest.mark.parametrize("compiled", [True, False])
def test_components_number_the_pieces_as_scipy_does(monkeypatch, compiled):
    """``bond_loops.components`` (union-find, or scipy without numba) gives scipy's count and
    labels exactly, on 300 random graphs (self-loops, repeated edges, isolated vertices,
    edges left out by ``keep``; every other one sorted by first end, as bonds are) and on
    the 10k-particle plate's bonds cut along a line; the union-find runs when it should."""
    monkeypatch.setattr(bond_loops, "ENABLED", compiled)
    calls, union_find = [], bond_loops._components
    monkeypatch.setattr(bond_loops, "_components", lambda *a: calls.append(1) or union_find(*a))
    rng = np.random.default_rng(0)

    def scipy_components(n, i, j, keep):
        graph = sp.coo_matrix((np.ones(int(keep.sum())), (i[keep], j[keep])), shape=(n, n))
        return connected_components(graph, directed=False)

    for _ in range(300):
        n, m = int(rng.integers(1, 60)), int(rng.integers(0, 90))
        i, j, keep = rng.integers(0, n, m), rng.integers(0, n, m), rng.random(m) < 0.8
        if _ % 2:
            order = np.argsort(i, kind="stable")
            i, j = i[order], j[order]
        count, labels = bond_loops.components(n, i, j, keep)
        expected = scipy_components(n, i, j, keep)
        assert count == expected[0] and np.array_equal(labels, expected[1])
    p = bp.grid_2d(100.0, 100.0, 1.0)
    bonds = bp.find_bonds(p, 3.0)
    keep = ~((np.minimum(p.x[bonds.i, 1], p.x[bonds.j, 1]) < 50) & (np.maximum(p.x[bonds.i, 1], p.x[bonds.j, 1]) > 50))
    count, labels = bond_loops.components(p.n, bonds.i, bonds.j, keep)
    assert count == 2 and np.array_equal(labels, scipy_components(p.n, bonds.i, bonds.j, keep)[1])
    assert len(calls) == (301 if compiled and bond_loops.numba is not None else 0)
