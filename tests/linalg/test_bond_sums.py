"""BondSums (A = S B, the LPS dilatation kept factored): its products equal the explicit
operator's, its explicit form equals the sparse product S B, and its family ends come out in
row-major order."""
import numpy as np
import pytest
import scipy.sparse as sp
import torch

from bayespd import bond_loops
from bayespd.linalg.assembly import Gram
from bayespd.linalg.bond_sums import BondSums, _family_ends


def bond_operator(n, dim, rng, bonds=300):
    """A Gram of bond rows with random blocks a (on p) and c (on q), p < q, sorted by (p, q)."""
    pairs = set()
    while len(pairs) < bonds:
        p, q = sorted(rng.integers(0, n, 2))
        if p != q:
            pairs.add((p, q))
    p, q = np.array(sorted(pairs)).T
    a = np.arange(dim)
    rows = np.repeat(np.arange(len(p)), 2 * dim)
    cols = np.concatenate([dim * p[:, None] + a, dim * q[:, None] + a], axis=1).reshape(-1)
    data = torch.as_tensor(rng.standard_normal(2 * dim * len(p)))
    return Gram(rows, cols, len(p), dim * n), data, p, q


@pytest.mark.parametrize("dim", [2, 3])
def test_products_equal_the_sparse_product_s_b(dim):
    """apply, apply_transpose, the explicit Gram and normal_product (compiled and numpy, some
    dofs constrained; with B's own term B^T diag(k) B too) against S B formed by scipy, to
    rounding (1e-13 relative)."""
    rng = np.random.default_rng(dim)
    n = 60
    B, bdata, p, q = bond_operator(n, dim, rng)
    A = BondSums(B, bdata, n)
    s = torch.as_tensor(rng.standard_normal((2, len(p))))
    S = sp.csr_matrix((np.concatenate([s[0], s[1]]), (np.concatenate([p, q]), np.tile(np.arange(len(p)), 2))),
                      shape=(n, len(p)))
    D = (S @ B.operator(bdata.numpy())).toarray()
    x, y = rng.standard_normal(dim * n), rng.standard_normal(n)
    scale = np.abs(D).max() * np.abs(x).max()
    assert np.abs(A.apply(s, torch.as_tensor(x)).numpy() - D @ x).max() <= 1e-13 * scale
    assert np.abs(A.apply_transpose(s, torch.as_tensor(y)).numpy() - D.T @ y).max() <= 1e-13 * scale
    assert np.abs(A.operator(s).toarray() - D).max() <= 1e-14 * np.abs(D).max()
    w, k = rng.standard_normal(n), rng.random(len(p))
    free = np.flatnonzero(rng.random(dim * n) > 0.2)
    Bd = B.operator(bdata.numpy()).toarray()
    K = (D.T @ np.diag(w) @ D)[np.ix_(free, free)]
    Kb = (Bd.T @ np.diag(k) @ Bd)[np.ix_(free, free)]
    for enabled in (True, False):
        bond_loops.ENABLED = enabled
        try:
            got = A.normal_product(s, w, free)(x[free])
            whole = A.normal_product(s, w, free, bond_weights=k)(x[free])
        finally:
            bond_loops.ENABLED = True
        scale = np.abs(K).max() * np.abs(x).max() * n
        assert np.abs(got - K @ x[free]).max() <= 1e-13 * scale
        assert np.abs(whole - (K + Kb) @ x[free]).max() <= 1e-13 * (scale + np.abs(Kb).max() * np.abs(x).max() * n)


def test_apply_is_differentiable_in_the_weights_and_the_vector():
    rng = np.random.default_rng(5)
    B, bdata, p, q = bond_operator(12, 2, rng, bonds=30)
    A = BondSums(B, bdata, 12)
    s = torch.tensor(rng.standard_normal((2, len(p))), requires_grad=True)
    x = torch.tensor(rng.standard_normal(24), requires_grad=True)
    assert torch.autograd.gradcheck(lambda s, x: A.apply(s, x), (s, x))
    assert torch.autograd.gradcheck(lambda s: A.explicit_data(s), (s,))


def test_refuses_an_operator_that_is_not_on_bonds():
    g = Gram(np.array([0, 0, 0, 0, 0, 0]), np.array([0, 1, 2, 3, 4, 5]), 1, 6)
    with pytest.raises(ValueError, match="two particles"):
        BondSums(g, torch.ones(6), 3)


def test_family_ends_in_row_major_order_without_a_sort():
    """The family ends come out in (owner, node) order with their end ids (bond b as (i, j): b,
    as (j, i): nb + b, self: 2 nb + k), as a lexsort gives, for bonds in any order; a repeated
    bond is refused."""
    rng = np.random.default_rng(0)
    n, pairs = 40, set()
    while len(pairs) < 150:
        a, b = rng.integers(0, n, 2)
        if a != b and (b, a) not in pairs:
            pairs.add((a, b))
    i, j = np.array(sorted(pairs)).T
    shuffle = rng.permutation(len(i))
    i, j = i[shuffle], j[shuffle]
    owner = np.concatenate([i, j, np.arange(n)])
    node = np.concatenate([j, i, np.arange(n)])
    expect = np.lexsort((node, owner))
    o, nd, order = _family_ends(i, j, n)
    assert np.array_equal(order.numpy(), expect)
    assert np.array_equal(o, owner[expect]) and np.array_equal(nd, node[expect])
    with pytest.raises(ValueError, match="distinct pairs"):
        _family_ends(np.append(i, j[0]), np.append(j, i[0]), n)
