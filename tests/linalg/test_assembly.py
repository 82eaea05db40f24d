"""Assembly of Gram sums K = sum_t A_t^T diag(w_t) A_t (``bayespd.linalg.assembly``): the
node-block (BSR) assembly and the torch assembly against scipy's products and a dense
reference, the map cache the pattern keeps, and the matrix-free product."""
import numpy as np
import scipy.sparse as sp
import torch

from bayespd.linalg.assembly import Gram, internal_force, numeric_values, union_pattern
from tests.linalg.linalg_systems import lps_terms


def reference_matrix(terms):
    return sum(g.matrix(d.numpy(), w.numpy()) for g, d, w in terms).toarray()


def block_gram(rng, n_rows, nodes, per_row, b=2):
    """A Gram whose rows each touch ``per_row`` distinct nodes, with all b dofs of each
    (entries given in a shuffled order), and random data and weights."""
    picks = np.array([rng.choice(nodes, per_row, replace=False) for _ in range(n_rows)])
    rows = np.repeat(np.arange(n_rows), per_row * b)
    cols = (b * picks[:, :, None] + np.arange(b)).reshape(-1)
    order = rng.permutation(len(rows))
    g = Gram(rows[order], cols[order], n_rows, b * nodes)
    return g, torch.as_tensor(rng.standard_normal(len(rows))), torch.as_tensor(rng.random(n_rows))


def dense(g, data, w):
    A = np.zeros(g.shape)
    np.add.at(A, (g.rows, g.cols), g.ordered(data.numpy()))
    return A.T @ np.diag(w.numpy()) @ A


def test_node_block_assembly_equals_a_dense_reference(rng):
    """Two node-block Grams: the pattern declares its node blocks, and the scipy (BSR) and
    torch assemblies equal the dense A^T diag(w) A to 1e-14 relative, for the full sum and
    for a subset of the terms (a second map in the pattern's cache)."""
    terms = [block_gram(rng, 30, 9, 2), block_gram(rng, 9, 9, 1)]
    grams = [g for g, _, _ in terms]
    assert [g.block for g in grams] == [2, 2]
    pattern = union_pattern(grams)
    assert pattern.blocks.size == 2 and len(pattern.blocks.maps) == 1
    for subset in (terms, terms[:1]):
        K = sum(dense(*t) for t in subset)
        scale = np.abs(K).max()
        values = numeric_values(pattern, subset)
        assert np.abs(pattern.matrix(values).toarray() - K).max() <= 1e-14 * scale
        torch_values = sum(g.values(d, w, pattern) for g, d, w in subset)
        assert np.abs(pattern.matrix(torch_values).toarray() - K).max() <= 1e-14 * scale
    assert len(pattern.blocks.maps) == 2


def test_block_pattern_and_values_match_scipy_products():
    _, _, mat, terms = lps_terms()
    grams = [g for g, _, _ in terms]
    assert [g.block for g in grams] == [2, 2]
    pattern = union_pattern(grams)
    S = sum(g.structure() for g in grams) + sp.identity(grams[0].shape[1])
    assert pattern.nnz == S.nnz  # same structural entries as the product of the structures
    K = reference_matrix(terms)
    values = numeric_values(pattern, terms)
    np.testing.assert_allclose(pattern.matrix(values).toarray(), K, rtol=0, atol=1e-12 * abs(K).max())
    np.testing.assert_array_equal(numeric_values(pattern, terms), values)  # cached map reused
    sub = numeric_values(pattern, terms[:1])  # a subset of the terms: scattered, zeros elsewhere
    K1 = reference_matrix(terms[:1])
    np.testing.assert_allclose(pattern.matrix(sub).toarray(), K1, rtol=0, atol=1e-12 * abs(K1).max())


def test_scalar_gram_falls_back_to_scipy_products(rng):
    rows, cols = rng.integers(0, 7, 40), rng.integers(0, 9, 40)
    g = Gram(rows, cols, 7, 9)
    assert g.block == 1
    data, w = rng.standard_normal(40), rng.random(7)
    pattern = union_pattern([g])
    assert pattern.blocks is None
    K = g.matrix(data, w).toarray()
    values = numeric_values(pattern, [(g, torch.as_tensor(data), torch.as_tensor(w))])
    np.testing.assert_allclose(pattern.matrix(values).toarray(), K, atol=1e-14)


def test_internal_force_matches_assembled_matrix():
    p, _, mat, terms = lps_terms()
    u = torch.randn(2 * p.n, generator=torch.Generator().manual_seed(3))
    K = reference_matrix(terms)
    np.testing.assert_allclose(internal_force(terms, u).numpy(), K @ u.numpy(), rtol=1e-12,
                               atol=1e-12 * abs(K).max())


def test_a_gram_of_blocks_is_the_gram_of_its_entries():
    """``Gram.of_blocks`` gives the constructor's Gram (rows, columns, row pointers, block,
    order; products to rounding: it gathers whole nodes) for rows with increasing nodes, and
    falls back to it otherwise."""
    rng = np.random.default_rng(3)
    for b in (2, 3):
        nodes = np.sort(np.array([rng.choice(30, 2, replace=False) for _ in range(50)]), axis=1)
        for picks in (nodes, nodes[:, ::-1]):
            g = Gram.of_blocks(picks, b * 30, b)
            ref = Gram(np.repeat(np.arange(50), 2 * b), (b * picks[:, :, None] + np.arange(b)).reshape(-1), 50, b * 30)
            assert g.block == ref.block == b
            for name in ("rows", "cols", "indptr"):
                assert np.array_equal(getattr(g, name), getattr(ref, name))
            assert (g.order is None) == (ref.order is None) and (g.order is None or np.array_equal(g.order, ref.order))
            data = torch.as_tensor(rng.standard_normal(100 * b))
            x, y = torch.as_tensor(rng.standard_normal(b * 30)), torch.as_tensor(rng.standard_normal(50))
            torch.testing.assert_close(g.apply(data, x), ref.apply(data, x), rtol=1e-14, atol=1e-14)
            torch.testing.assert_close(g.apply_transpose(data, y), ref.apply_transpose(data, y), rtol=1e-14, atol=1e-14)
