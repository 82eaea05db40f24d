"""The MD crack on the coarse grid (bayespd.learn.md_damage) on a synthetic graphene sheet."""
import numpy as np
import pytest

from bayespd.learn import graphene
from bayespd.learn.md import A0
from bayespd.learn.md_damage import broken_atom_bonds, cut_coarse_bonds, slit_centre, tip_height


def opened_sheet():
    """A graphene sheet whose lower right part (x > 20, y < 10) moves right by 1 A at frame 1 and
    2 A at frame 2 (a crack up to y = 10 opening): the bonds across x = 20 there exceed 2.0 A."""
    nx, ny = graphene.cells_for(40.0, 30.0, A0)
    X, _ = graphene.sheet(nx, ny, A0)
    U = np.zeros((3, len(X), 2))
    right, low = X[:, 0] > 20.0, X[:, 1] < 10.0
    for f in (1, 2):
        U[f, right & low, 0] = 1.0 * f
    return X, U


def test_broken_bonds_are_those_stretched_past_the_cut_off_and_stay_broken():
    X, U = opened_sheet()
    U = np.concatenate([U, np.zeros((1,) + U.shape[1:])])  # frame 3: the sheet closed again
    pairs, broken = broken_atom_bonds(X, U)
    assert not broken[0].any() and broken[1].any()
    np.testing.assert_array_equal(broken[3], broken[2])  # irreversible although the sheet closed
    mid = 0.5 * (X[pairs[:, 0]] + X[pairs[:, 1]])
    assert np.all(mid[broken[1], 1] < 10.0 + A0) and np.all(np.abs(mid[broken[1], 0] - 20.0) < A0)


def test_coarse_bonds_cut_are_those_crossing_the_crack_and_tip_is_its_top():
    X, U = opened_sheet()
    pairs, broken = broken_atom_bonds(X, U)
    nodes = np.array([[17.0, 5.0], [23.0, 5.0], [17.0, 20.0], [23.0, 20.0], [17.0, 7.0]])
    i, j = np.array([0, 2, 0, 0, 4]), np.array([1, 3, 2, 3, 1])
    intact = cut_coarse_bonds(nodes, i, j, X, pairs, broken)
    np.testing.assert_array_equal(intact[0], 1.0)
    # across the crack below y = 10: cut; above it: kept; along one side: kept; diagonal 5 -> 20
    # crosses x = 20 at y = 12.5, above the crack: kept
    np.testing.assert_array_equal(intact[1], [0.0, 1.0, 1.0, 1.0, 0.0])
    tip = tip_height(0.5 * (X[pairs[:, 0], 1] + X[pairs[:, 1], 1]), broken)
    assert np.isnan(tip[0]) and 8.0 < tip[1] < 10.0 + A0


def test_slit_centre_is_the_removed_column():
    """edge_slit removes the atoms within 0.6 a of a column; the neighbouring columns are sqrt(3)/2 a
    = 1.23 A away on either side (zigzag-x sheet), so the gap's middle is the column to rounding;
    an atom-scale jitter of the kept atoms (0.1 A, as after relaxation) moves it by at most that."""
    nx, ny = graphene.cells_for(30.0, 30.0, A0)
    X, box = graphene.sheet(nx, ny, A0)
    X = X - box / 2.0
    column = X[np.argmin(np.abs(X[:, 0] - 0.5)), 0]
    kept = X[graphene.edge_slit(X, column, X[:, 1].min() - 0.1, 10.0, A0)]
    top = X[:, 1].min() + 9.0
    assert abs(slit_centre(kept, top) - column) < 1e-12
    jitter = np.random.default_rng(0).uniform(-0.1, 0.1, kept.shape)
    assert abs(slit_centre(kept + jitter, top) - column) <= 0.1
    with pytest.raises(ValueError, match="wider reach"):
        slit_centre(kept, X[:, 1].min() - 1.0)
