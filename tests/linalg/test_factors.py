"""Factors of scipy SPD matrices (``bayespd.linalg.factors``): residuals, the operator's own
shifted factor, and the CHOLMOD ordering from the settings or the call."""
import numpy as np
import pytest
import scipy.sparse as sp

from bayespd import linalg
from bayespd.linalg import sparse
from bayespd.linalg.factors import shifted_factor, spd_factor
from tests.linalg.linalg_systems import grid_spd

needs_cholmod = pytest.mark.skipif(sparse.cholmod is None, reason="orderings are CHOLMOD's")


def test_spd_factor_of_an_unsorted_matrix_with_duplicates():
    """A COO matrix given twice over (duplicates, unsorted): the factor solves 2 M x = b with
    relative residual <= 1e-12."""
    spd = grid_spd()
    coo = spd.tocoo()
    order = np.random.default_rng(0).permutation(coo.nnz)
    r, c, v = coo.row[order], coo.col[order], coo.data[order]
    r, c, v = (np.concatenate([a, a]) for a in (r, c, v))
    twice = sp.coo_matrix((v, (r, c)), shape=spd.shape)
    b = np.random.default_rng(1).standard_normal((spd.shape[0], 2))
    x = spd_factor(twice).solve(b)
    assert np.linalg.norm(2 * (spd @ x) - b) <= 1e-12 * np.linalg.norm(b)


def test_shifted_factor_asks_the_operator_when_it_knows_how():
    spd = grid_spd()
    s, b = np.linspace(1.0, 2.0, spd.shape[0]), 0.5
    rhs = np.random.default_rng(2).standard_normal(spd.shape[0])
    x = shifted_factor(spd, s, b).solve(rhs)
    assert np.linalg.norm(s * x + b * (spd @ x) - rhs) <= 1e-12 * np.linalg.norm(rhs)

    class Own:
        def shifted_factor(self, s_, b_):
            return ("own", b_)

    assert shifted_factor(Own(), s, b) == ("own", b)


@needs_cholmod
def test_ordering_comes_from_the_settings_unless_given():
    """Under ``cholmod_ordering="natural"`` the factor keeps the rows in order; an ordering
    named in the call wins; both solve to 1e-12."""
    spd = grid_spd()
    n = spd.shape[0]
    rhs = np.random.default_rng(3).standard_normal(n)
    with linalg.settings(cholmod_ordering="natural"):
        natural = spd_factor(spd)
        amd = spd_factor(spd, ordering="amd")
    assert np.array_equal(natural.cholmod.P(), np.arange(n))
    assert not np.array_equal(amd.cholmod.P(), np.arange(n))
    for f in (natural, amd):
        assert np.linalg.norm(spd @ f.solve(rhs) - rhs) <= 1e-12 * np.linalg.norm(rhs)
