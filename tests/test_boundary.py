"""bayespd/boundary.py: distributed loads (conservation and volume weighting), Dirichlet
layers, and the split into free and prescribed dofs (K_ff, embed / expand round trips)."""
import numpy as np
import pytest
import scipy.sparse as sp
import torch

import bayespd as bp
from bayespd.boundary import Constraints
from bayespd.linalg.sparse import Pattern


@pytest.fixture(scope="module")
def plate():
    return (bp.grid_2d(10.0, 6.0, 1.0),)


def test_load_is_conserved_and_spread_in_proportion_to_volume():
    """sum_i f_i = F to rounding; f_i = F V_i / sum V over the region, zero outside it, on
    particles of unequal volumes."""
    rng = np.random.default_rng(0)
    g = bp.grid_2d(6.0, 4.0, 1.0)
    V = rng.uniform(0.5, 1.5, g.n)
    p = bp.from_points(g.x, V)
    mask = p.layer("right", 2.0)
    F = torch.tensor([3.0, -7.0])
    f = bp.Load(mask, F).nodal(p)
    torch.testing.assert_close(f.sum(0), F, rtol=0, atol=1e-14)
    expected = np.where(mask, V, 0.0)[:, None] / V[mask].sum() * F.numpy()
    np.testing.assert_allclose(f.numpy(), expected, rtol=1e-14, atol=0)
    assert torch.all(f[~torch.as_tensor(mask)] == 0)
    cube = bp.grid_3d(2.0, 2.0, 2.0, 1.0)
    half = cube.x[:, 0] > 1
    f3 = bp.Load(half, (0.0, 0.0, 1.0)).nodal(cube)
    assert torch.equal(f3[:, 2], torch.as_tensor(0.25 * half)) and torch.all(f3[:, :2] == 0)
    with pytest.raises(ValueError, match="force must have 3 components"):
        bp.Load(np.ones(8, bool), (1.0, 0.0)).nodal(bp.grid_3d(2.0, 2.0, 2.0, 1.0))


def test_dirichlet_layer_records_mask_value_and_depth(plate):
    p = plate[0]
    bc = bp.Dirichlet.layer(p, "left", 2.0, (None, 0.5))
    np.testing.assert_array_equal(bc.mask, p.layer("left", 2.0))
    assert bc.value == (None, 0.5) and bc.depth == 2.0
    assert bp.Dirichlet(p.layer("top", 1.0)).depth is None


def random_pattern(n, rng, density=0.3):
    """A symmetric pattern with a full diagonal, entries sorted by (col, row), and values of
    an SPD matrix on it."""
    B = sp.random(n, n, density=density, random_state=rng) + sp.identity(n)
    S = ((B + B.T) != 0).astype(float).tocsc()
    S.sort_indices()
    cols = np.repeat(np.arange(n), np.diff(S.indptr))
    A = sp.csc_matrix((rng.standard_normal(S.nnz), S.indices, S.indptr), (n, n))
    A = (A + A.T + 2 * n * sp.identity(n)).tocsc()
    A.sort_indices()
    assert np.array_equal(A.indices, S.indices)
    return Pattern(S.indices, cols, n), A


def test_constraints_split_free_and_prescribed_dofs():
    """Components fixed by two overlapping regions combine (a roller u_y = 0 and u_x = 0.3 on
    the same particle fix both); free dofs are the others in flat order 2 i + a;
    free(embed(v)) = v, embed is zero on fixed dofs, and expand adds the prescribed values."""
    p = bp.grid_2d(4.0, 3.0, 1.0)
    left, corner = p.layer("left", 1.0), p.box((0.0, 0.0), (1.0, 1.0))
    c = Constraints(p, None, [bp.Dirichlet(left, (None, 0.0)), bp.Dirichlet(corner, (0.3, None))])
    fixed = np.zeros((p.n, 2), bool)
    fixed[left, 1] = True
    fixed[corner, 0] = True
    np.testing.assert_array_equal(c.free_dofs, np.flatnonzero(~fixed.reshape(-1)))
    np.testing.assert_array_equal(c.fixed_particles, left)
    assert c.has_prescribed
    v = torch.arange(len(c.free_dofs), dtype=torch.float64) + 1
    full = c.embed(v)
    assert full.shape == (p.n, 2) and torch.all(full[torch.as_tensor(fixed)] == 0)
    assert torch.equal(c.free(full), v)
    u = c.expand(v)
    assert torch.equal(u[torch.as_tensor(corner), 0], torch.full((int(corner.sum()),), 0.3))
    assert torch.all(u[torch.as_tensor(left), 1] == 0) and torch.equal(c.free(u), v)
    with pytest.raises(ValueError, match="without a pattern"):
        c.pattern
    with pytest.raises(ValueError, match="needs 2 components"):
        Constraints(p, None, [bp.Dirichlet(left, (0.0, 0.0, 0.0))])


def test_reduced_system_solves_the_full_one():
    """K_ff from ``free_values`` is the dense K[free][:, free] entry for entry, and
    K_ff u_f = f_f - K_fc u_c with u_c the prescribed values gives the u that solves the full
    system's free rows (residual at rounding, 1e-12)."""
    rng = np.random.default_rng(5)
    p = bp.grid_2d(4.0, 3.0, 1.0)
    pattern, A = random_pattern(2 * p.n, rng)
    c = Constraints(p, pattern, [bp.Dirichlet(p.layer("left", 1.0), (0.2, -0.1))])
    values = torch.as_tensor(A.data)
    Kff = sp.csc_matrix((c.free_values(values).numpy(), (c.pattern.rows, c.pattern.cols)),
                        shape=(c.pattern.n, c.pattern.n)).toarray()
    free = c.free_mask
    np.testing.assert_array_equal(Kff, A.toarray()[free][:, free])
    f = rng.standard_normal(2 * p.n)
    uc = c.prescribed.reshape(-1).numpy()
    rhs = f[free] - (A.toarray()[free][:, ~free] @ uc[~free])
    u = c.expand(torch.as_tensor(np.linalg.solve(Kff, rhs))).reshape(-1).numpy()
    np.testing.assert_allclose((A @ u)[free], f[free], rtol=0, atol=1e-12 * np.abs(f).max())
    np.testing.assert_array_equal(u[~free], uc[~free])


def test_empty_regions(plate):
    p = plate[0]
    with pytest.raises(ValueError, match="load region is empty"):
        bp.Load(p.box((100, 100), (101, 101)), (1.0, 0.0))
    with pytest.raises(ValueError, match="Dirichlet region is empty"):
        bp.Dirichlet(np.zeros(p.n, bool))


def test_non_finite_load():
    p = bp.grid_2d(6.0, 4.0, 1.0)
    with pytest.raises(ValueError, match="load contains NaN"):
        bp.Load(p.layer("right", 1.0), (np.nan, 0.0))


@pytest.mark.parametrize("value", [(np.nan, 0.0), (0.0, np.inf), (None, -np.inf)])
def test_non_finite_dirichlet_value(value):
    p = bp.grid_2d(6.0, 4.0, 1.0)
    with pytest.raises(ValueError, match=r"Dirichlet value of component \d contains NaN or inf.*None leaves"):
        bp.Dirichlet(p.layer("left", 2.0), value)
