"""A sparse Cholesky factor with chosen rows ordered last, for changes confined to them.

Order the n rows as (I, B), the rows I first by METIS, the rows B (those a later change may
touch, e.g. a band where a crack can run) last. Then P M P^T = L L^T with

    L = [[L_II, 0], [L_BI, L_S]],   L_S L_S^T = S = M_BB - M_BI M_II^-1 M_IB,

so the forward solve z = L^-1 r ends in the trailing block, and for any E whose columns are
unit vectors on B, L^-1 E = [0; L_S^-1 E_B] is a set of columns of one dense triangular
inverse, made once per factor (LAPACK trtri, |B|^3 / 3 flops). A Woodbury update on B then
needs no sparse solve per changed row (``woodbury.LocallyUpdated(region=...)``). A band that
separates the domain is the top separator nested dissection would choose anyway, so ordering
it last costs little fill.

CHOLMOD only: its half solves are what make this work (SuperLU has none).
"""
from __future__ import annotations

import hashlib

import numpy as np
import scipy.linalg.lapack as lapack
import scipy.sparse as sp

from bayespd.linalg import lockstep, sparse
from bayespd.linalg.config import current_settings


_ORDERINGS: dict = {}  # pattern digest -> METIS permutation (the latest four; METIS is deterministic)
_FACTORS: dict = {}  # digest of (M, last) -> TrailingFactor (the latest two)


def digest(*arrays) -> str:
    """SHA-1 of the arrays' bytes (C order), for caches keyed by value."""
    sha = hashlib.sha1()
    for a in arrays:
        sha.update(np.ascontiguousarray(a).tobytes())
    return sha.hexdigest()


def kept(cache: dict, size: int, key: str, make):
    """``cache[key]``, made by ``make()`` when missing; the oldest entry goes beyond ``size``."""
    if key not in cache:
        if len(cache) >= size:
            cache.pop(next(iter(cache)))
        cache[key] = make()
    return cache[key]


def _metis_order(A: sp.csc_matrix) -> np.ndarray:
    """CHOLMOD's METIS permutation of A, kept per sparsity pattern: many runs in a process
    (the realisations of an ensemble) start from the same pattern."""
    return kept(_ORDERINGS, 4, digest(np.asarray(A.shape), A.indptr, A.indices),
                 lambda: sparse.cholmod.analyze(A, mode="supernodal", ordering_method="metis").P())


def shared(M, last: np.ndarray) -> "TrailingFactor":
    """``TrailingFactor(M, last)``, kept for the latest two (M, last) of the process and
    shared by every caller with the same values bit for bit (the runs of an ensemble whose
    operator does not depend on their parameters start from one factor). The factor is
    read-only."""
    M = sp.csc_matrix(M, dtype=np.float64)
    last = np.asarray(last, dtype=np.int64)
    return kept(_FACTORS, 2, digest(np.asarray(M.shape), M.indptr, M.indices, M.data, last),
                 lambda: TrailingFactor(M, last))


def available() -> bool:
    """True when the CHOLMOD backend (scikit-sparse) is installed."""
    return sparse.cholmod is not None


class TrailingFactor:
    """P M P^T = L L^T for a sparse SPD M (n x n) with the rows ``last`` ordered last:
    ``forward(r)`` = L^-1 P r, ``backward(z)`` = P^T L^-T z (so M^-1 = backward o forward),
    ``trailing_inverse`` = L_S^-1 (dense, |last| x |last|) and ``position``, the index of
    each row of M in ``last`` (-1 elsewhere). Raises NotPositiveDefiniteError."""

    def __init__(self, M, last: np.ndarray):
        if not available():
            raise ValueError("TrailingFactor needs CHOLMOD: install the 'fast' extra (scikit-sparse)")
        M = sp.csc_matrix(M, dtype=np.float64)
        n = M.shape[0]
        last = np.unique(np.asarray(last, dtype=np.int64))
        if len(last) == 0 or last[0] < 0 or last[-1] >= n:
            raise ValueError(f"last must be a non-empty set of row indices in [0, {n})")
        first = np.setdiff1d(np.arange(n), last)
        cholmod = sparse.cholmod
        try:
            with sparse.blas_threads(current_settings().factor_threads):
                if len(first):
                    first = first[_metis_order(M[first][:, first].tocsc())]
                self.perm = np.concatenate([first, last])
                Mp = M[self.perm][:, self.perm].tocsc()
                self._f = cholmod.analyze(Mp, mode="supernodal", ordering_method="natural").cholesky(Mp)
        except cholmod.CholmodNotPositiveDefiniteError as e:
            raise sparse.NotPositiveDefiniteError(f"the operator is not positive definite ({e})") from None
        sparse.check_pivots(self._f.D(), Mp.diagonal())
        self.n, self.n_first = n, len(first)
        L_S = self._f.L()[self.n_first:, self.n_first:].toarray()
        with sparse.blas_threads(1):
            inverse, info = lapack.dtrtri(L_S, lower=1)
        if info != 0:
            raise sparse.NotPositiveDefiniteError("the trailing block of the factor is singular")
        inverse.setflags(write=False)
        self.trailing_inverse = inverse
        self.position = np.full(n, -1, dtype=np.int64)
        self.position[last] = np.arange(len(last))
        self._inverse_perm = np.argsort(self.perm)

    def forward(self, r: np.ndarray) -> np.ndarray:
        return self._half(self._forward, r)

    def backward(self, z: np.ndarray) -> np.ndarray:
        return self._half(self._backward, z)

    def _half(self, solve, r):
        """One vector in a lock-step run joins the round's block (``lockstep``); else alone."""
        member = lockstep.current()
        if member is not None and np.ndim(r) == 1:
            return member.solve((id(self), solve.__name__), solve, r)
        return solve(r)

    def _forward(self, r: np.ndarray) -> np.ndarray:
        with sparse.blas_threads(1):
            return self._f.solve_L(np.asarray(r)[self.perm], use_LDLt_decomposition=False)

    def _backward(self, z: np.ndarray) -> np.ndarray:
        with sparse.blas_threads(1):
            return self._f.solve_Lt(z, use_LDLt_decomposition=False)[self._inverse_perm]

    def solve(self, r: np.ndarray) -> np.ndarray:
        return self.backward(self.forward(r))
