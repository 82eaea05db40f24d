"""Assembly and sparse solvers: the fast (particle-block) assembly against scipy's products,
PCG against CHOLMOD/SuperLU, and the failures they must report."""
import os

import numpy as np
import pytest
import scipy.sparse as sp
import torch

import bayespd as bp
from bayespd.linalg import sparse
from bayespd.linalg.assembly import Gram, internal_force, numeric_values, union_pattern
from bayespd.linalg.stiffness_solver import Assembly


def lps_terms(nx=14, ny=8, m=2.6, delta=2.4, plane="stress"):
    p = bp.grid_2d(float(nx), float(ny), 1.0)
    bonds = bp.find_bonds(p, m)
    mat = bp.LPS(p, bonds, plane=plane)
    terms = mat.terms({"K": torch.tensor(3000.0), "G": torch.tensor(1500.0), "delta": torch.tensor(delta)})
    return p, bonds, mat, terms


def reference_matrix(terms):
    return sum(g.matrix(d.numpy(), w.numpy()) for g, d, w in terms).toarray()


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
    K = g.matrix(data, w).toarray()
    values = numeric_values(pattern, [(g, torch.as_tensor(data), torch.as_tensor(w))])
    np.testing.assert_allclose(pattern.matrix(values).toarray(), K, atol=1e-14)


def test_internal_force_matches_assembled_matrix():
    p, _, mat, terms = lps_terms()
    u = torch.randn(2 * p.n, generator=torch.Generator().manual_seed(3))
    K = reference_matrix(terms)
    np.testing.assert_allclose(internal_force(terms, u).numpy(), K @ u.numpy(), rtol=1e-12,
                               atol=1e-12 * abs(K).max())


def test_pattern_must_be_sorted():
    with pytest.raises(ValueError, match="sorted"):
        sparse.Pattern(np.array([1, 0]), np.array([0, 0]), 2)


@pytest.mark.parametrize("plane", ["stress", "strain"])
def test_pcg_matches_direct_solvers(plane):
    """PCG (matrix-free K, bond-Laplacian preconditioner) reaches the direct solution to its
    tolerance, with a clamp on the left and a roller (y only) on the right."""
    p, bonds, mat, terms = lps_terms(plane=plane)
    fixed = np.zeros((p.n, 2), dtype=bool)
    fixed[p.layer("left", 2.6)] = True
    fixed[p.layer("right", 1.0), 1] = True
    asm = Assembly(mat.grams(), ~fixed.reshape(-1))
    rhs = np.random.default_rng(0).standard_normal((asm.free_index.size, 2))
    backends = ["splu"] + (["cholmod"] if sparse.cholmod is not None else [])
    direct = {b: asm.factorize(terms, "direct", backend=b).solve(rhs) for b in backends}
    for b in backends:
        for rows in (None, {mat.grams()[0]: bonds.length <= 1.5}):
            f = asm.factorize(terms, "pcg", backend=b, rtol=1e-12, precondition_rows=rows)
            u = f.solve(rhs)
            assert 0 < f.iterations < 100
            np.testing.assert_allclose(u, direct[b], rtol=0, atol=1e-9 * abs(direct[b]).max())
            np.testing.assert_allclose(f.solve(rhs[:, 0]), u[:, 0], rtol=0, atol=1e-9 * abs(u).max())
    if len(backends) == 2:
        np.testing.assert_allclose(direct["cholmod"], direct["splu"], rtol=0, atol=1e-10 * abs(direct["splu"]).max())


def test_pcg_reports_non_convergence_and_indefiniteness():
    p, _, mat, terms = lps_terms()
    asm = Assembly(mat.grams(), ~np.repeat(p.layer("left", 2.6), 2))
    rhs = np.ones(asm.free_index.size)
    with pytest.raises(sparse.ConvergenceError, match="did not converge"):
        asm.factorize(terms, "pcg", rtol=1e-14, maxiter=3).solve(rhs)
    negative = [(g, d, -w) for g, d, w in terms]
    with pytest.raises(bp.NotPositiveDefiniteError):
        asm.factorize(negative, "pcg").solve(rhs)


def test_unconstrained_pcg_is_not_silent():
    """No constraint: K is singular; PCG must raise rather than return a rigid-body drift."""
    _, _, mat, terms = lps_terms(nx=8, ny=6)
    asm = Assembly(mat.grams())
    with pytest.raises((bp.NotPositiveDefiniteError, sparse.ConvergenceError)):
        asm.factorize(terms, "pcg", maxiter=500).solve(np.ones(asm.n))


@pytest.mark.skipif(sparse._OPENBLAS is None, reason="CHOLMOD's OpenBLAS is not loaded")
def test_factor_threads_keep_a_worker_limit():
    """FACTOR_THREADS = None leaves a threadpoolctl limit in place (MCMC chain workers limit
    every BLAS to their share of the cores); a number sets the count and restores it after."""
    from threadpoolctl import threadpool_limits

    count = sparse._OPENBLAS.openblas_get_num_threads
    with threadpool_limits(1):
        with sparse.blas_threads(None):
            assert count() == 1
        if (os.cpu_count() or 1) >= 2:  # OpenBLAS may cap the count at the cores
            with sparse.blas_threads(2):
                assert count() == 2
        assert count() == 1
