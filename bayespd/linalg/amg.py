"""Algebraic-multigrid preconditioner for the matrix-free PCG of a Gram-sum stiffness.

Smoothed aggregation (Vanek, Mandel & Brezina 1996; pyamg's defaults and its aggregation and
candidate fit, the rest in ``smoothed_aggregation``; in 2D the finest level aggregated by
cells of particles, ``cell_aggregates``) on the *pair operator*
K_b = sum_t A_t^T diag(max(w_t, 0)) A_t over the rows of A_t that touch two particles (the
bonds): the whole stiffness of a bond-based law, the bond part of LPS (its dilatation rows are
left out: they couple whole families, and K - K_b is positive semi-definite). The near-null
space given to the aggregation is the rigid-body modes restricted to the free dofs (3 in 2D, 6
in 3D), so aggregates carry rotations: a slender body in bending converges in 18-25
iterations where the scalar bond-graph Laplacian needs 105 (benchmarks/README.md, issue 31).

One application is a V-cycle: forward Gauss-Seidel, restriction, the coarser cycle (a dense
Cholesky solve on the coarsest level), prolongation, backward Gauss-Seidel. Backward after
forward makes the cycle a symmetric positive-definite operator, so it preconditions CG and the
adjoint's solve alike (K is symmetric). Columns of a multi-column right-hand side go through
each level together. Where numba is installed the sweeps are hybrid Gauss-Seidel (Gauss-Seidel
inside runs of rows, Jacobi between) and they, the residuals and the transfers run on two
threads (``row_runs``); elsewhere pyamg's sweep, which holds the GIL, runs on one. numpy's BLAS
runs on one thread in it (``threadpoolctl``): on two shared cores a second BLAS thread made
pyamg's set-up 10x and each cycle 4x slower.
"""
from __future__ import annotations

import copy
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp
from threadpoolctl import ThreadpoolController

import pyamg
from pyamg import amg_core

from bayespd import bond_loops
from bayespd.linalg import pair_loops, row_runs
from bayespd.linalg.assembly import to_numpy
from bayespd.linalg.page_advice import without_huge_pages
from bayespd.linalg.row_runs import RowRuns


_BLAS = []  # numpy's and scipy's BLAS libraries, found once (a lookup costs 0.6-2 ms)


def one_blas_thread():
    """A context that runs numpy's and scipy's BLAS on one thread (``threadpoolctl``)."""
    if not _BLAS:
        _BLAS.append(ThreadpoolController().select(user_api="blas"))
    return _BLAS[0].limit(limits=1)


def rigid_body_modes(x: np.ndarray, component: np.ndarray | None = None) -> np.ndarray:
    """(n, 3 or 6) rigid-body displacements (translations, then rotations about the centroid)
    at n dofs located at ``x`` (n, dim), dof k displacing along axis ``component[k]``. Without
    ``component``, ``x`` are particles (N, dim) and the dofs node-major (N * dim of them)."""
    if component is None:
        n, dim = x.shape
        x, component = np.repeat(x, dim, axis=0), np.tile(np.arange(dim), n)
    dim = x.shape[1]
    if dim not in (2, 3):
        raise ValueError(f"rigid-body modes need 2D or 3D positions, got dim = {dim}")
    x = x - x.mean(axis=0)
    planes = [(0, 1)] if dim == 2 else [(0, 1), (1, 2), (2, 0)]  # rotation in the (a, b) plane
    B = np.zeros((len(x), dim + len(planes)))
    rows = np.arange(len(x))
    B[rows, component] = 1.0
    for k, (a, b) in enumerate(planes):
        B[:, dim + k] = np.where(component == a, -x[:, b], 0.0) + np.where(component == b, x[:, a], 0.0)
    return B


def pair_rows(g, w) -> np.ndarray:
    """Rows of a term's operator that enter K_b: those touching two particles (bonds) whose
    weight is >= 0 (a negative weight counts as 0 in K_b, so its row is left out)."""
    two = g.two_block_rows
    return two[np.asarray(w)[two] >= 0]


@without_huge_pages()
def pair_operator(terms, free_index: np.ndarray, pattern=None) -> sp.csr_matrix:
    """K_b on the free dofs: the ``pair_rows`` of every (gram, data, w) term (sorted indices);
    by compiled loops where numba is installed (``pair_loops``; on ``pattern``, from
    ``pair_pattern``, when given), else each A_t restricted to those rows and the free
    columns before its product."""
    if row_runs.usable():
        return pair_loops.pair_operator(_pair_terms(terms), np.asarray(free_index), terms[0][0].shape[1], pattern)
    K = None
    for g, d, w in terms:
        two = pair_rows(g, w)
        if len(two) == 0:
            continue
        A = g.operator(d)
        A = (A[two] if len(two) < A.shape[0] else A)[:, free_index]
        weights = np.repeat(np.asarray(w, dtype=np.float64)[two], np.diff(A.indptr))
        WA = sp.csr_matrix((A.data * weights, A.indices, A.indptr), shape=A.shape, copy=False)
        part = A.T.tocsr() @ WA
        K = part if K is None else K + part
    if K is None:
        raise ValueError("no two-particle rows (bonds) to build the AMG preconditioner from")
    K = K.tocsr()
    K.sort_indices()
    return K


@without_huge_pages()
def pair_pattern(terms, free_index: np.ndarray):
    """K_b's pattern for ``terms`` (``pair_loops.PairPattern``), to assemble K_b at other
    weights of the same rows; None where numba is not installed."""
    if not row_runs.usable():
        return None
    return pair_loops.PairPattern(_pair_terms(terms), np.asarray(free_index), terms[0][0].shape[1])


def _pair_terms(terms) -> list:
    """[(gram, data, w, pair rows)] of the terms that have pair rows (numpy)."""
    chosen = [(g, to_numpy(d), to_numpy(w)) for g, d, w in terms]
    chosen = [(g, d, w, rows) for g, d, w in chosen if len(rows := pair_rows(g, w))]
    if not chosen:
        raise ValueError("no two-particle rows (bonds) to build the AMG preconditioner from")
    return chosen


class VCycle:
    """r -> M^-1 r, one symmetric V-cycle of a hierarchy (``smoothed_aggregation``), for r of
    shape (n,) or (n, k); ``hybrid``: the two-thread l1 hybrid smoother where numba is
    installed (else pyamg's sweep)."""

    def __init__(self, levels, coarse: sp.csr_matrix, hybrid: bool = True):
        self.levels = levels
        self.smoothers = None  # per level: (A, P, R) in runs of rows (``row_runs``)
        if hybrid and row_runs.usable():
            self.smoothers = [(RowRuns.smoother(A), RowRuns(P), RowRuns(R)) for A, P, R in levels]
        dense = coarse.toarray()
        lost = np.flatnonzero(np.diag(dense) == 0)  # a mode an aggregate could not carry: decoupled
        dense[lost, lost] = 1.0
        with one_blas_thread():
            self.coarse = sla.cho_factor(dense)

    def with_finest(self, A: sp.csr_matrix) -> "VCycle | None":
        """This hierarchy with its finest level smoothing on A, a matrix of the same size (K_b
        at new weights), P, R and the coarser levels kept; None when the hierarchy has no
        level above its coarsest (a dense solve of the old matrix). Still a symmetric
        positive-definite preconditioner: the smoother converges for any SPD A (l1 pivots,
        or pyamg's symmetric sweep) and the coarse correction is SPD; weaker the further A is
        from the matrix the hierarchy was built on."""
        if not self.levels:
            return None
        new = copy.copy(self)
        _, P, R = self.levels[0]
        new.levels = [(A, P, R)] + self.levels[1:]
        if self.smoothers is not None:
            new.smoothers = [(RowRuns.smoother(A), *self.smoothers[0][1:])] + self.smoothers[1:]
        return new

    def __call__(self, r: np.ndarray) -> np.ndarray:
        B = np.ascontiguousarray((r[:, None] if r.ndim == 1 else r).T)  # columns as rows
        with one_blas_thread():
            X = self._cycle(0, B)
        return X[0] if r.ndim == 1 else X.T

    def _cycle(self, k: int, B: np.ndarray) -> np.ndarray:
        if k == len(self.levels):
            return np.ascontiguousarray(sla.cho_solve(self.coarse, B.T).T)
        if self.smoothers is not None:
            return self._hybrid_cycle(k, B)
        A, P, R = self.levels[k]
        n = A.shape[0]
        X = np.zeros_like(B)
        for j in range(len(B)):
            amg_core.gauss_seidel(A.indptr, A.indices, A.data, X[j], B[j], 0, n, 1)
        coarse = self._cycle(k + 1, np.ascontiguousarray((R @ (B.T - A @ X.T)).T))
        X += (P @ coarse.T).T
        for j in range(len(B)):
            amg_core.gauss_seidel(A.indptr, A.indices, A.data, X[j], B[j], n - 1, -1, -1)
        return X

    def _hybrid_cycle(self, k: int, B: np.ndarray) -> np.ndarray:
        """``_cycle`` with the hybrid Gauss-Seidel of ``row_runs`` (two threads)."""
        smooth, P, R = self.smoothers[k]
        X = _rows([smooth.pre(b) for b in B])
        coarse = _rows([R.product(smooth.residual_after_pre(x, b)) for x, b in zip(X, B)])
        X += _rows([P.product(e) for e in self._cycle(k + 1, coarse)])
        return _rows([smooth.post(x, b) for x, b in zip(X, B)])


def _rows(vectors: list) -> np.ndarray:
    """``np.stack(vectors)``, a view for one vector (a V-cycle's usual right-hand side)."""
    return vectors[0][None] if len(vectors) == 1 else np.stack(vectors)


def amg_preconditioner(terms, free_index: np.ndarray, positions: np.ndarray,
                       pair: sp.csr_matrix | None = None) -> VCycle:
    """The V-cycle of smoothed aggregation on K_b (``pair``, by default ``pair_operator``)
    with the rigid-body modes of ``positions`` (N, dim) as near-null space; in 2D the finest
    level aggregated by cells (``cell_aggregates``), in 3D by pyamg's standard aggregation
    (cells of the same rule gave 24 PCG iterations against its 16 on the cantilever of
    ``fe_convergence``, 20k particles, m = 2; side 4 h gave 15 and no cheaper set-up)."""
    row_runs.warm_up()
    positions = np.asarray(positions, dtype=np.float64)
    modes = rigid_body_modes(positions)[free_index]
    aggregates = None
    if positions.shape[1] == 2:
        aggregates = lambda: cell_aggregates(positions, *bond_ends(terms), np.asarray(free_index) // 2)  # noqa: E731
    return v_cycle(pair_operator(terms, free_index) if pair is None else pair, modes, aggregates)


def bond_ends(terms) -> tuple[np.ndarray, np.ndarray]:
    """Particles (i, j) at the ends of the two-particle rows with a positive weight (the
    bonds that K_b holds) of every (gram, data, w) term."""
    ends = []
    for g, _, w in terms:
        two = g.two_block_rows[np.asarray(w)[g.two_block_rows] > 0]
        if len(two) == 0:
            continue
        ind, ptr = g.block_parts()
        ends.append((ind[ptr[two]], ind[ptr[two] + 1]))
    return np.concatenate([a for a, _ in ends]), np.concatenate([b for _, b in ends])


def cell_aggregates(positions: np.ndarray, i: np.ndarray, j: np.ndarray,
                    dof_particle: np.ndarray) -> sp.csr_matrix:
    """The finest level's aggregates, (dofs, aggregates) with one 1 per row: the particles
    of one square (cubic) cell of side s h, split into the parts the bonds (i, j) inside it
    connect (a crack or a hole through a cell gives two aggregates); each dof goes with its
    particle (``dof_particle``). h and r are the shortest and longest bond. One Jacobi step
    spreads a prolongator column r beyond its cell and K_b couples within r, so two cells
    couple on the coarse level when their particles lie within 3 r of each other; the
    smallest s with (s + 1) h > 3 r, s = floor(3 r / h), leaves only the 3^d neighbouring
    cells coupled: at 160k particles, m = 2, a coarse level of 0.36 M entries and 17 PCG
    iterations against pyamg's standard aggregation's 1.75 M and 19 (benchmarks/README.md,
    issue 31, fifth pass)."""
    x = np.asarray(positions, dtype=np.float64)
    if len(i) == 0:
        raise ValueError("no bonds with a positive weight to aggregate the particles by")
    xi = np.take(x, j, axis=0) - np.take(x, i, axis=0)
    squared = np.einsum("bk,bk->b", xi, xi)
    h, r = float(np.sqrt(squared.min())), float(np.sqrt(squared.max()))
    side = h * np.floor(3 * r / h)
    cell = np.floor((x - x.min(axis=0) + h / 2) / side).astype(np.int64)  # no particle on a cell face
    cell = np.ravel_multi_index(cell.T, cell.max(axis=0) + 1)
    count, part = bond_loops.components(len(x), i, j, keep=cell[i] == cell[j])
    part = part[dof_particle]
    used = np.zeros(count, dtype=bool)
    used[part] = True
    aggregate = (np.cumsum(used) - 1)[part]  # the parts that hold a dof, numbered in order
    rows = np.arange(len(aggregate))
    return sp.csr_matrix((np.ones(len(rows)), (rows, aggregate)), shape=(len(rows), aggregate.max() + 1))


@without_huge_pages()
def v_cycle(K: sp.csr_matrix, modes: np.ndarray, aggregates=None, hybrid: bool = True) -> VCycle:
    """The V-cycle of smoothed aggregation on an SPD matrix K with near-null space ``modes``
    (its rigid-body modes, for elasticity); ``aggregates``: the finest level's (default:
    pyamg's standard aggregation); ``hybrid``: as for ``VCycle``."""
    with one_blas_thread():
        return VCycle(*smoothed_aggregation(K, modes, aggregates=aggregates), hybrid=hybrid)


def smoothed_aggregation(K: sp.csr_matrix, modes: np.ndarray, max_coarse: int = 300,
                         max_levels: int = 10, omega: float = 4.0 / 3.0,
                         aggregates=None):
    """([(A, P, R) per level], coarsest A): pyamg's smoothed aggregation with its defaults
    (coarsening while a level has more than ``max_coarse`` nodes, a coarse node being the
    len(modes) dofs of one aggregate, aggregated whole; strength theta = 0, i.e. A's own pattern; standard aggregation; tentative prolongator T
    fitted to ``modes``; one Jacobi step P = T - omega / rho(D^-1 A) D^-1 A T), the products
    in CSR (pyamg's 1 x 1-block BSR products took half its set-up) and rho by a seeded Lanczos
    on D^-1/2 A D^-1/2 (same spectrum, symmetric), estimated in a second thread while the
    aggregates, T and A T are made. ``aggregates``: the finest level's, as (dofs, aggregates)
    CSR with one 1 per row (``cell_aggregates``) instead of pyamg's, or a function of nothing
    that makes them (then called beside the rho estimate); used when they leave more than
    ``max_coarse`` coarse nodes, i.e. a coarse level that is coarsened again. Below that the
    method has two levels and pyamg's smaller aggregates give a larger coarse level, solved
    exactly, in fewer iterations (three-point beam, 16k particles, m = 4: 12 against 17;
    benchmarks/README.md, issue 31, fifth pass)."""
    A, B, levels = sp.csr_matrix(K), np.asarray(modes, dtype=np.float64), []
    A.sort_indices()  # in place (no copy; a no-op when sorted): aggregation visits neighbours in index order: unsorted products cost 2 iterations
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="bayespd-amg") as helper:  # per call: no pool to outlive a fork
        while A.shape[0] // (B.shape[1] if levels else 1) > max_coarse and len(levels) < max_levels - 1:
            d = A.diagonal()
            d_inv = np.divide(1.0, d, out=np.zeros_like(d), where=d != 0)  # a dof no bond reaches: T's row is 0
            rho = helper.submit(_jacobi_radius, A, d_inv)  # beside the aggregation and A T
            if callable(aggregates) and not levels:
                aggregates = aggregates()
            if aggregates is not None and not levels and aggregates.shape[1] <= max_coarse:
                aggregates = None  # a two-level method: its coarse level is solved exactly
            if aggregates is None or levels:
                aggregates, _ = pyamg.aggregation.standard_aggregation(_node_graph(A, B.shape[1] if levels else 1))
            T, B = pyamg.aggregation.fit_candidates(aggregates, B)
            T = T.tocsr()
            AT = A @ T
            AT.data *= np.repeat(d_inv * (omega / rho.result()), np.diff(AT.indptr))  # D^-1 A T, rows scaled in place
            P = (T - AT).tocsr()
            del AT, T
            R = P.T.tocsr()
            levels.append((A, P, R))
            A = (R @ (A @ P)).tocsr()
    return levels, A


def _node_graph(A: sp.csr_matrix, k: int) -> sp.csr_matrix:
    """The pattern of A's k x k blocks (a coarse level's nodes: one aggregate's k dofs), so
    that an aggregate holds whole nodes and keeps all k modes (pyamg's BSR levels)."""
    if k == 1:
        return A
    blocks = A.tobsr(blocksize=(k, k))
    return sp.csr_matrix((np.ones(len(blocks.indices)), blocks.indices, blocks.indptr),
                         shape=(A.shape[0] // k, A.shape[1] // k))


def _jacobi_radius(A: sp.csr_matrix, d_inv: np.ndarray, steps: int = 15) -> float:
    """rho(D^-1 A), the largest Ritz value of ``steps`` seeded Lanczos steps on the symmetric
    D^-1/2 A D^-1/2 (a lower bound, converging fast at the end of the spectrum); A's products
    in runs of rows from its entries in single precision where numba is installed (rho to
    1e-7; each product 1.5x faster than scipy's)."""
    s = np.sqrt(d_inv)
    n = A.shape[0]
    product = RowRuns(A, single=True).product if row_runs.usable() else A.__matmul__
    q = np.random.default_rng(0).standard_normal(n)
    q /= np.linalg.norm(q)
    q_prev, beta, alphas, betas = np.zeros(n), 0.0, [], []
    for _ in range(min(steps, n)):
        w = s * product(s * q) - beta * q_prev
        alpha = q @ w
        w -= alpha * q
        alphas.append(alpha)
        beta = np.linalg.norm(w)
        if beta <= 1e-12 * abs(alpha):
            break
        betas.append(beta)
        q_prev, q = q, w / beta
    return float(sla.eigvalsh_tridiagonal(np.array(alphas), np.array(betas[:len(alphas) - 1]))[-1])
