"""Factors with chosen rows last (``bayespd.linalg.trailing``): the half solves compose to
the full solve, the trailing block's inverse, and the factor shared per operator."""
import numpy as np
import pytest
import scipy.linalg as sla
import scipy.sparse as sp

from bayespd.linalg import trailing
from bayespd.linalg.sparse import NotPositiveDefiniteError
from tests.linalg.linalg_systems import grid_spd

pytestmark = pytest.mark.skipif(not trailing.available(), reason="the trailing factor needs CHOLMOD")


def middle_band(M, side=12, half_width=1.5):
    """The dofs of the grid nodes whose row is within ``half_width`` of the middle."""
    node_row = np.arange(M.shape[0]) // 2 // side
    return np.flatnonzero(np.abs(node_row - (side - 1) / 2) < half_width)


def test_trailing_factor_half_solves_and_inverse():
    """Rows last (``TrailingFactor``): forward then backward half solves equal the direct
    solve to 1e-12, and L_S^-1 is the inverse of the factor's trailing block (its columns are
    L^-1 e_r for rows r of the region, checked against the forward solve of e_r)."""
    M = grid_spd()
    region = middle_band(M)
    f = trailing.TrailingFactor(M, region)
    rhs = np.random.default_rng(1).standard_normal((M.shape[0], 2))
    exact = sla.solve(M.toarray(), rhs)
    assert np.abs(f.solve(rhs) - exact).max() <= 1e-12 * np.abs(exact).max()
    assert np.abs(f.backward(f.forward(rhs[:, 0])) - exact[:, 0]).max() <= 1e-12 * np.abs(exact).max()
    r = region[[0, 7]]
    E = np.zeros((M.shape[0], 2))
    E[r, [0, 1]] = 1.0
    z = f.forward(E)
    assert np.abs(z[: f.n_first]).max() == 0.0
    assert np.abs(z[f.n_first:] - f.trailing_inverse[:, f.position[r]]).max() <= 1e-12 * np.abs(z).max()
    with pytest.raises(ValueError, match="non-empty"):
        trailing.TrailingFactor(M, [])
    with pytest.raises(NotPositiveDefiniteError, match="not positive definite"):
        trailing.TrailingFactor(M - 3.0 * sp.eye(M.shape[0]), region)


def test_shared_trailing_factor_is_one_per_operator():
    """``trailing.shared`` hands the same read-only factor to every caller whose operator and
    rows are equal bit for bit, and a new one when either changes in any entry."""
    M = grid_spd().tocsr()
    region = middle_band(M)
    f = trailing.shared(M, region)
    assert trailing.shared(M.copy(), region.copy()) is f
    nudged = M.copy()
    nudged.data[0] *= 1 + 1e-15
    assert trailing.shared(nudged, region) is not f
    assert trailing.shared(M, region[1:]) is not f
    with pytest.raises(ValueError, match="read-only"):
        f.trailing_inverse[0, 0] = 0.0
