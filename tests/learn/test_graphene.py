"""The honeycomb sheet: three neighbours at a, exact strains of affine fields, the slit cuts bonds."""
import numpy as np

from bayespd.learn import graphene


def test_periodic_sheet_is_a_perfect_honeycomb():
    x, box = graphene.sheet(4, 3, 1.42)
    assert len(x) == 4 * 4 * 3 and ((x > 0) & (x < box)).all()
    pairs = graphene.bonds(x, 1.42, box)
    assert len(pairs) == 1.5 * len(x)
    np.testing.assert_array_equal(np.bincount(pairs.ravel(), minlength=len(x)), 3)
    np.testing.assert_allclose(graphene.bond_strain(x, np.zeros_like(x), pairs, box), 0.0, atol=1e-14)


def test_uniform_dilatation_stretches_every_bond_by_the_same_strain():
    x, box = graphene.sheet(3, 3, 1.42)
    pairs = graphene.bonds(x, 1.42)
    np.testing.assert_allclose(graphene.bond_strain(x, 0.01 * x, pairs), 0.01, rtol=1e-12)


def test_cells_and_slit():
    assert graphene.cells_for(100.0, 100.0, 1.42) == (41, 23)
    x, box = graphene.sheet(10, 6, 1.42)
    x = x - box / 2
    column = x[np.argmin(np.abs(x[:, 0])), 0]
    keep = graphene.edge_slit(x, column, x[:, 1].min() - 0.1, 10.0, 1.42)
    y = x[keep]
    pairs = graphene.bonds(y, 1.42)
    crossing = (np.sign(y[pairs[:, 0], 0] - column) != np.sign(y[pairs[:, 1], 0] - column)) & (y[pairs, 1].max(1) < y[:, 1].min() + 9.0)
    assert not crossing.any() and (~keep).sum() > 0
