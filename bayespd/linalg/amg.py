"""Algebraic-multigrid preconditioner for the matrix-free PCG of a Gram-sum stiffness.

Smoothed aggregation (pyamg; Vanek, Mandel & Brezina 1996) on the *pair operator*
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
each level together. numpy's BLAS runs on one thread in it (``threadpoolctl``): on two shared
cores a second BLAS thread made pyamg's set-up 10x and each cycle 4x slower.
"""
from __future__ import annotations

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp
from threadpoolctl import threadpool_limits

import pyamg
from pyamg import amg_core


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


def pair_operator(terms, free_index: np.ndarray) -> sp.csr_matrix:
    """K_b on the free dofs: the two-particle rows of every (gram, data, w) term, weights
    clipped at 0."""
    parts = []
    for g, d, w in terms:
        _, ptr = g.block_parts()
        two = np.flatnonzero(np.diff(ptr) == 2)
        if len(two) == 0:
            continue
        A = g.operator(d)[two]
        parts.append(A.T @ sp.diags(np.maximum(np.asarray(w, dtype=np.float64)[two], 0.0)) @ A)
    if not parts:
        raise ValueError("no two-particle rows (bonds) to build the AMG preconditioner from")
    K = sum(parts).tocsr()
    return K[free_index][:, free_index].tocsr()


class VCycle:
    """r -> M^-1 r, one symmetric V-cycle of a pyamg hierarchy, for r of shape (n,) or (n, k)."""

    def __init__(self, hierarchy):
        self.levels = [(lv.A.tocsr(), lv.P.tocsr(), lv.R.tocsr()) for lv in hierarchy.levels[:-1]]
        self.coarse = sla.cho_factor(hierarchy.levels[-1].A.toarray())

    def __call__(self, r: np.ndarray) -> np.ndarray:
        B = np.ascontiguousarray((r[:, None] if r.ndim == 1 else r).T)  # columns as rows
        with threadpool_limits(1, user_api="blas"):
            X = self._cycle(0, B)
        return X[0] if r.ndim == 1 else X.T

    def _cycle(self, k: int, B: np.ndarray) -> np.ndarray:
        if k == len(self.levels):
            return np.ascontiguousarray(sla.cho_solve(self.coarse, B.T).T)
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


def amg_preconditioner(terms, free_index: np.ndarray, positions: np.ndarray) -> VCycle:
    """The V-cycle of smoothed aggregation on K_b (``pair_operator``) with the rigid-body
    modes of ``positions`` (N, dim) as near-null space."""
    modes = rigid_body_modes(np.asarray(positions, dtype=np.float64))[free_index]
    return v_cycle(pair_operator(terms, free_index), modes)


def v_cycle(K: sp.csr_matrix, modes: np.ndarray) -> VCycle:
    """The V-cycle of smoothed aggregation on an SPD matrix K with near-null space ``modes``
    (its rigid-body modes, for elasticity)."""
    smoother = ("gauss_seidel", {"sweep": "forward"})
    with threadpool_limits(1, user_api="blas"):
        hierarchy = pyamg.smoothed_aggregation_solver(
            sp.csr_matrix(K), B=modes, max_coarse=300, improve_candidates=None, presmoother=smoother,
            postsmoother=("gauss_seidel", {"sweep": "backward"}))
    return VCycle(hierarchy)
