"""Factorisations of a Gram-sum stiffness on the free dofs (``bayespd.linalg.stiffness_solver``):
the direct factor's residual, the matrix-free product and its threads, and PCG against the
direct solvers, with the failures it must report."""
import numpy as np
import pytest

import bayespd as bp
from bayespd import linalg
from bayespd.linalg import sparse
from bayespd.linalg.stiffness_solver import Assembly
from tests.linalg.linalg_systems import lps_terms

BACKENDS = ["splu"] + (["cholmod"] if sparse.cholmod is not None else [])


def clamped():
    p, bonds, mat, terms = lps_terms()
    asm = Assembly(mat.grams(), ~np.repeat(p.layer("left", 2.6), 2))
    K = sum(g.matrix(d.numpy(), w.numpy()) for g, d, w in terms).toarray()
    return asm, terms, K[np.ix_(asm.free_index, asm.free_index)]


@pytest.mark.parametrize("backend", BACKENDS)
def test_direct_factor_solves_the_free_system(backend):
    """K_ff from the Assembly's values equals the restricted dense K to 1e-14 relative, and
    its factor's solve has relative residual <= 1e-12."""
    asm, terms, K = clamped()
    assert np.abs(asm.free_pattern.matrix(asm.values(terms)).toarray() - K).max() <= 1e-14 * np.abs(K).max()
    rhs = np.random.default_rng(2).standard_normal((len(asm.free_index), 2))
    x = asm.factorize(terms, "direct", backend=backend).solve(rhs)
    assert np.linalg.norm(K @ x - rhs) <= 1e-12 * np.linalg.norm(rhs)


def test_operator_threads_follow_the_settings():
    """The matrix-free product equals K_ff x to 1e-14 relative with one or three row blocks;
    its thread count comes from ``linalg.settings`` unless the call names one, and gives
    the same bits either way."""
    asm, terms, K = clamped()
    x = np.random.default_rng(3).standard_normal((len(asm.free_index), 2))
    one = asm.operator(terms)(x)
    assert np.abs(one - K @ x).max() <= 1e-14 * np.abs(K @ x).max()
    three = asm.operator(terms, threads=3)(x)
    assert np.abs(three - K @ x).max() <= 1e-14 * np.abs(K @ x).max()
    with linalg.settings(matvec_threads=3):
        assert np.array_equal(asm.operator(terms)(x), three)
        assert np.array_equal(asm.operator(terms, threads=1)(x), one)


@pytest.mark.parametrize("flip", [False, True])
def test_operator_with_the_shared_bond_operator(flip):
    """With K_b given (``pair``, as the AMG path shares it), the product is K_b x plus the other
    rows: equal to K_ff x to 1e-14 relative, also when some bonds carry negative weights
    (``flip``: every 7th; such rows are left out of K_b and kept in the other rows)."""
    from bayespd.linalg.amg import pair_operator
    asm, terms, _ = clamped()
    terms = [(g, d.numpy(), w.numpy().copy()) for g, d, w in terms]
    if flip:
        terms[0][2][::7] *= -1.0
    K = sum(g.matrix(d, w) for g, d, w in terms).toarray()[np.ix_(asm.free_index, asm.free_index)]
    x = np.random.default_rng(4).standard_normal((len(asm.free_index), 2))
    split = asm.operator(terms, threads=1, pair=pair_operator(terms, asm.free_index))
    for v in (x, x[:, 0]):
        assert np.abs(split(v) - K @ v).max() <= 1e-14 * np.abs(K @ v).max()


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
