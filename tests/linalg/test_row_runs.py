"""A CSR matrix in runs of rows on two threads (``bayespd.linalg.row_runs``): its product is
scipy's; the hybrid Gauss-Seidel sweeps are Gauss-Seidel inside each run and Jacobi between
runs, one run being pyamg's sweep; the V-cycle built on them is symmetric, the same bits on one
thread or two, and preconditions PCG as pyamg's does."""
import copy

import numpy as np
import pytest
import scipy.sparse as sp
import torch
from pyamg import amg_core

from bayespd import bond_loops
from bayespd.linalg import row_runs, sparse
from bayespd.linalg.amg import amg_preconditioner, pair_operator
from bayespd.linalg.row_runs import RowRuns
from bayespd.linalg.stiffness_solver import Assembly
from tests.linalg.linalg_systems import lps_terms
from tests.linalg.test_amg import clamped

pytestmark = pytest.mark.skipif(bond_loops.numba is None, reason="needs numba (the 'fast' or 'dev' extra)")


@pytest.fixture(autouse=True)
def short_runs(monkeypatch):
    """Runs of >= 256 rows (4,096 in use) whatever the bandwidth (3 in use), so that small
    matrices have several."""
    monkeypatch.setattr(row_runs, "MIN_ROWS", 256)
    monkeypatch.setattr(row_runs, "BANDWIDTHS", 0)


@pytest.fixture(scope="module")
def bond_operator():
    """K_b of a clamped LPS plate, 30 x 12 particles (648 free dofs: two runs of rows)."""
    p, asm, terms = clamped()
    num = [(g, d.numpy(), w.numpy()) for g, d, w in terms]
    return p, asm, num, pair_operator(num, asm.free_index)


def rounded(A):
    """A with its entries rounded to single precision (what the default smoother reads)."""
    return sp.csr_matrix((A.data.astype(np.float32).astype(np.float64), A.indices, A.indptr), shape=A.shape)


def block_reference(A, b, x, runs, forward):
    """One l1 hybrid sweep by dense algebra: x + (D + D_l1 + L_run)^-1 (b - A x) per run
    (forward), (D + D_l1 + U_run)^-1 (backward), L_run / U_run the strict triangles inside the
    run, D_l1 the absolute row sums outside it."""
    A = A.toarray()
    out = x.copy()
    for lo, hi in runs:
        block = A[lo:hi, lo:hi]
        l1 = np.abs(A[lo:hi]).sum(axis=1) - np.abs(block).sum(axis=1)
        M = (np.tril(block) if forward else np.triu(block)) + np.diag(l1)
        out[lo:hi] = x[lo:hi] + np.linalg.solve(M, b[lo:hi] - A[lo:hi] @ x)
    return out


def test_one_sweep_is_gauss_seidel_inside_each_run_and_jacobi_between(bond_operator):
    """pre(b) = blockdiag(D + D_l1 + L)^-1 b and post(x, b) = x + blockdiag(D + D_l1 + U)^-1 (b - A x) to
    1e-12 relative (triangular solves of a diagonally dominant-ish SPD matrix: a few ulp times
    the row length), A's entries rounded to single precision; the residual after the pre-sweep b - A x."""
    *_, A = bond_operator
    smooth = RowRuns.smoother(A)
    A = rounded(A)
    assert len(smooth.runs) == 2
    rng = np.random.default_rng(0)
    b, x = rng.standard_normal(A.shape[0]), rng.standard_normal(A.shape[0])
    pre = block_reference(A, b, np.zeros_like(b), smooth.runs, True)
    post = block_reference(A, b, x, smooth.runs, False)
    np.testing.assert_allclose(smooth.pre(b), pre, rtol=0, atol=1e-12 * np.abs(pre).max())
    np.testing.assert_allclose(smooth.post(x, b), post, rtol=0, atol=1e-12 * np.abs(post).max())
    x = smooth.pre(b)
    np.testing.assert_allclose(smooth.residual_after_pre(x, b), b - A @ x, rtol=0, atol=1e-12 * np.abs(b).max())


def test_the_product_is_scipys_for_vectors_and_columns():
    """A x for a rectangular A (rows in 3 runs) and x of shape (m,) or (m, 2): scipy's product
    to 1e-14 of its largest term (the loop sums in another order), the same bits on 1 or 2
    threads."""
    A = sp.random(3 * 256 + 5, 700, density=0.02, format="csr", random_state=4)
    runs = RowRuns(A)
    assert len(runs.runs) == 3
    x = np.random.default_rng(4).standard_normal((700, 2))
    scale = (abs(A) @ np.abs(x)).max()
    np.testing.assert_allclose(runs.product(x[:, 0]), A @ x[:, 0], rtol=0, atol=1e-14 * scale)
    np.testing.assert_allclose(runs.product(x), A @ x, rtol=0, atol=1e-14 * scale)
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        one = runs.product(x)
    finally:
        torch.set_num_threads(before)
    assert np.array_equal(one, runs.product(x))


def test_the_l1_smoother_converges_where_plain_hybrid_gauss_seidel_does_not():
    """An SPD matrix far from diagonal dominance (B^T B, B sparse random + I), two runs: with
    the l1 pivots M + M^T - A is positive definite (Baker et al. 2011, Theorem 6.2: the
    smoother converges, the cycle is SPD), where blockdiag(D + L) gives an indefinite one
    (what made the FE peer of fe_convergence diverge)."""
    B = sp.random(600, 600, density=0.01, random_state=5) + sp.identity(600)
    A = (B.T @ B).tocsr()
    smooth = RowRuns.smoother(A)
    assert len(smooth.runs) == 2
    M = np.linalg.inv(np.column_stack([smooth.pre(e) for e in np.identity(600)]))
    dense = rounded(A).toarray()  # the entries the sweeps read
    assert np.linalg.eigvalsh(M + M.T - dense).min() > 0
    plain = np.zeros_like(dense)
    for lo, hi in smooth.runs:
        plain[lo:hi, lo:hi] = np.tril(dense[lo:hi, lo:hi])
    assert np.linalg.eigvalsh(plain + plain.T - dense).min() < 0


def test_a_smoothers_runs_span_three_bandwidths(monkeypatch):
    """A banded SPD matrix of bandwidth 300 on 4,000 rows: the smoother's runs are >= 900 rows
    (4 runs), the product's only >= MIN_ROWS (8 runs: it crosses no coupling)."""
    monkeypatch.setattr(row_runs, "BANDWIDTHS", 3)
    A = sp.diags([np.full(4000 - abs(k), 1.0 if k else 700.0) for k in (-300, -1, 0, 1, 300)],
                 [-300, -1, 0, 1, 300], format="csr")
    smooth, product = RowRuns.smoother(A), RowRuns(A)
    assert len(smooth.runs) == 4 and min(hi - lo for lo, hi in smooth.runs) >= 900
    assert len(product.runs) == 8


def test_one_run_is_pyamgs_sweep(bond_operator, monkeypatch):
    """With a single run the hybrid sweep is plain Gauss-Seidel: pyamg's forward sweep from 0 and
    its backward sweep, to 1e-12 relative (the compiled loop sums a row in another order)."""
    monkeypatch.setattr(row_runs, "RUNS", 1)
    *_, A = bond_operator
    smooth = RowRuns.smoother(A, single=False)
    assert smooth.runs == [(0, A.shape[0])]
    rng = np.random.default_rng(1)
    b, x = rng.standard_normal(A.shape[0]), rng.standard_normal(A.shape[0])
    forward, backward = np.zeros_like(b), x.copy()
    amg_core.gauss_seidel(A.indptr, A.indices, A.data, forward, b, 0, A.shape[0], 1)
    amg_core.gauss_seidel(A.indptr, A.indices, A.data, backward, b, A.shape[0] - 1, -1, -1)
    np.testing.assert_allclose(smooth.pre(b), forward, rtol=0, atol=1e-12 * np.abs(forward).max())
    np.testing.assert_allclose(smooth.post(x, b), backward, rtol=0, atol=1e-12 * np.abs(backward).max())


def test_single_precision_sweeps_are_the_double_sweeps_of_the_rounded_matrix(bond_operator):
    """The default smoother reads A's entries in single precision and computes in double: the
    same bits as the double smoother of A rounded to single; a diagonal outside single's range
    (1e-30, 1e30) keeps A's own entries."""
    *_, A = bond_operator
    single, double = RowRuns.smoother(A), RowRuns.smoother(rounded(A), single=False)
    assert single.data.dtype == np.float32 and double.data.dtype == np.float64
    b, x = np.random.default_rng(6).standard_normal((2, A.shape[0]))
    assert np.array_equal(single.pre(b), double.pre(b)) and np.array_equal(single.post(x, b), double.post(x, b))
    x = single.pre(b)
    assert np.array_equal(single.residual_after_pre(x, b), double.residual_after_pre(x, b))
    d = A.diagonal()
    for scale in (1e-31 / d.min(), 1e31 / d.max()):
        assert RowRuns.smoother(scale * A).data.dtype == np.float64


def test_a_row_without_diagonal_keeps_its_value():
    """A zero row (a dof no bond reaches) and an unsorted matrix: the row keeps x (0 from the
    pre-smoother), as in pyamg's sweep; the others are Gauss-Seidel on the sorted matrix."""
    A = sp.csr_matrix((np.array([1.0, 4.0, 1.0, 3.0]), np.array([2, 0, 0, 2]), np.array([0, 2, 2, 4])), shape=(3, 3))
    assert not A.has_sorted_indices  # [[4, 0, 1], [0, 0, 0], [1, 0, 3]], row 0 unsorted
    smooth = RowRuns.smoother(A)
    b, x = np.array([1.0, 2.0, 3.0]), np.array([0.5, 7.0, -1.0])
    np.testing.assert_allclose(smooth.pre(b), [0.25, 0.0, (3.0 - 0.25) / 3.0], rtol=1e-15)
    np.testing.assert_allclose(smooth.post(x, b), [(1.0 - 2.5 / 3.0) / 4.0, 7.0, 2.5 / 3.0], rtol=1e-15)
    x = smooth.pre(b)
    np.testing.assert_allclose(smooth.residual_after_pre(x, b), b - A @ x, rtol=0, atol=1e-15)


def test_the_cycle_is_symmetric_and_the_same_bits_on_one_thread_or_two(bond_operator):
    """x . C y = y . C x to 1e-13 relative (post-smoother the adjoint of the pre-smoother), and
    the cycle on 1 and 2 threads is bit for bit one function (runs fixed, not threads)."""
    p, asm, num, A = bond_operator
    cycle = amg_preconditioner(num, asm.free_index, p.x, pair=A)
    assert cycle.smoothers is not None and len(cycle.smoothers[0][0].runs) == 2
    rng = np.random.default_rng(2)
    x, y = rng.standard_normal(A.shape[0]), rng.standard_normal(A.shape[0])
    Cx, Cy = cycle(x), cycle(y)
    assert abs(y @ Cx - x @ Cy) <= 1e-13 * abs(x @ Cx)
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        one = cycle(x)
        torch.set_num_threads(2)
        two = cycle(x)
    finally:
        torch.set_num_threads(before)
    assert np.array_equal(one, two) and np.array_equal(one, Cx)


def test_pcg_with_the_hybrid_cycle_solves_as_pyamgs_does(bond_operator):
    """The same hierarchy with the hybrid smoother and with pyamg's sweep: PCG to rtol 1e-10
    within one iteration of each other, solutions equal to kappa(K) rtol (1e-8 relative)."""
    p, asm, num, A = bond_operator
    hybrid = amg_preconditioner(num, asm.free_index, p.x, pair=A)
    plain = copy.copy(hybrid)
    plain.smoothers = None
    matvec = asm.operator(num, pair=A)
    rhs = np.random.default_rng(3).standard_normal(A.shape[0])
    solves = [sparse.PCGFactor(matvec, M, A.shape[0], rtol=1e-10) for M in (hybrid, plain)]
    u, v = (f.solve(rhs) for f in solves)
    assert abs(solves[0].iterations - solves[1].iterations) <= 1, [f.iterations for f in solves]
    assert np.linalg.norm(u - v) <= 1e-8 * np.linalg.norm(v)


def test_without_the_compiled_loops_the_cycle_is_pyamgs(bond_operator, monkeypatch):
    """BAYESPD_BOND_LOOPS=0 (``bond_loops.ENABLED`` False): no hybrid smoother, pyamg's sweep."""
    monkeypatch.setattr(bond_loops, "ENABLED", False)
    p, asm, num, A = bond_operator
    assert amg_preconditioner(num, asm.free_index, p.x, pair=A).smoothers is None


@pytest.mark.parametrize("contrast", [1e3, 1e8])
def test_single_precision_sweeps_serve_as_double_ones_on_a_stiff_contrast(contrast):
    """A shear-modulus field spanning ``contrast`` along a clamped plate (K_b's entries over as
    many decades): PCG preconditioned by the cycle with single-precision sweeps takes the
    iterations of the double ones (+-1: the sweeps' entries move by 6e-8 relative; the coarse
    levels are the same) and reaches the direct solution to kappa(K) rtol."""
    p, bonds, mat, _ = lps_terms(nx=30, ny=12)
    asm = Assembly(mat.grams(), ~np.repeat(p.layer("left", 2.6), 2))
    G = torch.as_tensor(1500.0 * contrast ** (p.x[:, 0] / p.x[:, 0].max()))
    terms = [(g, d.numpy(), w.numpy()) for g, d, w in mat.terms({"K": 2 * G, "G": G, "delta": 2.6})]
    A = pair_operator(terms, asm.free_index)
    single = amg_preconditioner(terms, asm.free_index, p.x, pair=A)
    double = copy.copy(single)
    double.smoothers = [(RowRuns.smoother(L, single=False), P, R) for L, (_, P, R) in
                        zip([lv[0] for lv in single.levels], single.smoothers)]
    assert single.smoothers[0][0].data.dtype == np.float32
    rhs = np.random.default_rng(7).standard_normal(A.shape[0])
    matvec = asm.operator(terms, pair=A)
    solves = [sparse.PCGFactor(matvec, M, A.shape[0], rtol=1e-10) for M in (single, double)]
    u = solves[0].solve(rhs)
    solves[1].solve(rhs)
    assert abs(solves[0].iterations - solves[1].iterations) <= 1, [f.iterations for f in solves]
    exact = asm.factorize(mat.terms({"K": 2 * G, "G": G, "delta": 2.6}), "direct", backend="splu").solve(rhs)
    eigenvalues = np.linalg.eigvalsh(matvec(np.identity(A.shape[0])))
    kappa = eigenvalues[-1] / eigenvalues[0]
    assert np.linalg.norm(u - exact) <= kappa * 1e-10 * np.linalg.norm(exact)
