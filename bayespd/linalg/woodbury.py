"""Solves with a sparse SPD operator after a local change, without refactorising it.

When bonds break, the operator of the implicit steps changes only on the dofs of their end
particles (and, for LPS, of their neighbours): A = A0 + Delta, Delta supported on rows R with
k = |R| << n. With a factor P of M0 = diag(s) + b A0, M = M0 + E D E^T (E the columns of the
identity on R, D = b Delta_RR) and the Woodbury identity (Golub & Van Loan 2013, §2.1.4),

    M^-1 r = x0 - W (I + D W_R)^-1 D x0_R,   x0 = P^-1 r,  W = P^-1 E,  W_R = E^T W,

one solve with P plus O(n k) work per step. The k x k capacitance is taken in its symmetric
form: with X = W_R^-1 + D, I + D W_R = X W_R, so

    (I + D W_R)^-1 D = W_R^-1 - W_R^-1 X^-1 W_R^-1,

and X is the Schur complement of M on the rows R (W_R^-1 is M0's, and the change adds D
there): X is positive definite exactly when M is, so one Cholesky factorisation of X per
change (k^3 / 3 flops) both solves and checks (the LU of I + D W_R it replaces took 2 k^3 / 3
flops plus the product D W_R, and the sign of its determinant let an even number of negative
eigenvalues pass). W_R^-1 grows by bordering as rows join R (O(k^2) per new row). A
column of W is solved once per row that joins R and kept while R grows (bonds only break),
so a run of many small changes costs one factorisation plus one solve per changed dof.
With ``groups`` (a label per row, e.g. a spatial tile of the dofs) the columns of a row's
whole group are solved in one batched solve when the first of them is needed: a crack
touches the rows next to those it touched last, and a block solve costs far less than as
many single ones.

With ``region`` (the rows a change may touch, known in advance: a band where the crack can
run) the factor orders them last (``trailing.TrailingFactor``, P M0 P^T = L L^T) and the
identity is applied in the half-solved variables: with G = L^-1 E, z = L^-1 r,

    M^-1 r = L^-T (z - G c),   c = (I + D W_R)^-1 D G^T z,   W_R = G^T G,

(W = L^-T G, so x0_R = G^T z and W_R = G^T G), where G is supported on the region and read
off the dense inverse of the factor's trailing block: no solve per changed row, and O(|region| k)
work per step instead of O(n k).
"""
from __future__ import annotations

import copy
from dataclasses import dataclass

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp

from bayespd.linalg import trailing
from bayespd.linalg.factors import spd_factor
from bayespd.linalg.sparse import Factor, NotPositiveDefiniteError, PCGFactor


@dataclass(frozen=True)
class LocalChange:
    """A symmetric n x n change supported on few rows: entries ``v`` at (``r``, ``c``)
    (repeated positions add up), and ``rows``, the sorted rows they touch."""

    n: int
    rows: np.ndarray
    r: np.ndarray
    c: np.ndarray
    v: np.ndarray

    @classmethod
    def of(cls, delta) -> "LocalChange":
        """The change given as a symmetric scipy sparse matrix."""
        delta = sp.coo_matrix(sp.csr_matrix(delta))
        delta.eliminate_zeros()
        if delta.shape[0] != delta.shape[1]:
            raise ValueError(f"a change must be square, got {delta.shape}")
        return cls(delta.shape[0], np.unique(delta.row), delta.row, delta.col, delta.data)

    def __matmul__(self, x: np.ndarray) -> np.ndarray:
        return sp.coo_matrix((self.v, (self.r, self.c)), shape=(self.n, self.n)) @ x

    def placed(self, order: np.ndarray) -> np.ndarray:
        """The dense change on the rows ``order`` (k, k), which holds every one of ``rows``
        in any order (the Woodbury columns' order of touch)."""
        k = len(order)
        at = np.full(self.n, -1)
        at[order] = np.arange(k)
        if np.any(at[self.rows] < 0):
            raise ValueError("order must hold every row of the change")
        return np.bincount(at[self.r] * k + at[self.c], self.v, minlength=k * k).reshape(k, k)


class LocallyUpdated:
    """The symmetric operator A = A0 (scipy sparse n x n), or A0 + delta (a ``LocalChange``)
    for an operator ``changed`` from it, with ``A @ v`` and ``shifted_factor(s, b)``, a factor
    of diag(s) + b A made from the one of diag(s) + b A0 (shared by every operator ``changed``
    from the same A0).
    ``max_rank``: the most rows a change may touch before ``changed`` asks for a new A0;
    ``groups``: (n,) labels of the rows whose columns are solved together (default: each row
    alone; module docstring); ``region``: the rows a change may touch, ordered last in the
    factor (``trailing.TrailingFactor``: the columns are then read off one dense triangular
    inverse, no solve per row; a change outside it asks for a new A0; CHOLMOD only)."""

    def __init__(self, A0, max_rank: int = 512, groups=None, region=None):
        self.A0, self.delta, self.max_rank = shared_operator(A0), None, int(max_rank)
        self.shape = self.A0.shape
        if groups is not None and np.shape(groups) != (self.shape[0],):
            raise ValueError(f"groups must hold one label per row ({self.shape[0]})")
        if region is not None and not trailing.available():
            raise ValueError("region= needs CHOLMOD (the 'fast' extra); use groups= without it")
        self.groups = None if groups is None else np.asarray(groups)
        self.region = None if region is None else np.asarray(region, dtype=np.int64)
        self._inside = None
        if region is not None:
            self._inside = np.zeros(self.shape[0], dtype=bool)
            self._inside[self.region] = True
        self._bases = {}

    def changed(self, delta) -> "LocallyUpdated | None":
        """A0 + delta, delta (a ``LocalChange`` or a symmetric scipy sparse matrix) the whole
        change since A0; None when it touches more than ``max_rank`` rows, or rows outside
        ``region`` (factorise a new A0). It shares A0, its masks and its factors with this one."""
        delta = delta if isinstance(delta, LocalChange) else LocalChange.of(delta)
        if delta.n != self.shape[0]:
            raise ValueError(f"the change must be {self.shape[0]} x {self.shape[1]} like A0")
        rows = delta.rows
        if len(rows) > self.max_rank or (self._inside is not None and not self._inside[rows].all()):
            return None
        out = copy.copy(self)
        out.delta = delta if len(rows) else None
        return out

    def __matmul__(self, v):
        out = self.A0 @ v
        return out if self.delta is None else out + self.delta @ v

    def shifted_factor(self, s: np.ndarray, b: float) -> Factor:
        """A factor (``.solve``) of diag(s) + b A; raises NotPositiveDefiniteError if the
        change made it indefinite."""
        key = (float(b), np.asarray(s, dtype=np.float64).tobytes())
        if key not in self._bases:
            M0 = sp.diags(s) + b * self.A0
            self._bases.clear()  # the latest only, in the dict every operator changed from A0 shares
            if self.region is None:
                # solved many times: METIS's smaller fill makes each solve faster than AMD's
                self._bases[key] = _Solved(spd_factor(M0, ordering="metis"), self.shape[0], self.max_rank, self.groups)
            else:
                self._bases[key] = _Trailing(trailing.shared(M0, self.region), self.max_rank)
        base = self._bases[key]
        if self.delta is None:
            return Factor(base.solve)
        order = base.touch(self.delta.rows)
        inverse = base.gram_inverse()
        schur = _cholesky(inverse + b * self.delta.placed(order),
                          "the operator is not positive definite after the change: factorise it afresh")

        def correct(x_R):  # (I + D W_R)^-1 D x_R (module docstring)
            return inverse @ (x_R - sla.cho_solve(schur, inverse @ x_R, check_finite=False))

        return Factor(base.corrected(correct))


_OPERATORS: dict = {}  # digest -> the read-only CSR operator (the latest two)


def shared_operator(A0) -> sp.csr_matrix:
    """A0 as a read-only CSR matrix, the same object for every A0 equal to it bit for bit
    among the latest two of the process: the runs of an ensemble that start from one operator
    (``trailing.shared``) then hold one copy of it, not one each (15 MB at 10k particles)."""
    A = sp.csr_matrix(A0)
    key = trailing.digest(np.asarray(A.shape), A.indptr, A.indices, A.data)

    def frozen():
        for a in (A.data, A.indices, A.indptr):
            a.setflags(write=False)
        return A

    return trailing.kept(_OPERATORS, 2, key, frozen)


def _cholesky(X: np.ndarray, message: str):
    """scipy's (lower) Cholesky factor of the symmetric X (overwritten); NotPositiveDefiniteError
    with ``message`` when X is not positive definite."""
    try:
        factor = sla.cho_factor(X, lower=True, overwrite_a=True, check_finite=False)
    except np.linalg.LinAlgError:
        raise NotPositiveDefiniteError(message) from None
    if not np.all(np.isfinite(np.diag(factor[0]))):
        raise NotPositiveDefiniteError(message)
    return factor


GROWTH = 1.25  # the columns' buffer grows to this times the rows it must hold


class _Columns:
    """The columns of rows (of an n x n operator) touched so far, as rows of a buffer in the
    order the rows were first touched (grown by GROWTH as they come, from 64 rows, at most
    ``capacity`` while they fit: a run holds ~1.25 k rows, not max_rank);
    ``_new(rows)`` makes the columns of new rows, (len(rows), width); ``gram_inverse()`` is
    W_R^-1 in ``order``, bordered as rows join with the blocks ``_bordering(old)`` of W_R."""

    def __init__(self, n: int, width: int, capacity: int):
        self.width, self.k, self.capacity = width, 0, max(int(capacity), 16)
        self.order = np.zeros(0, dtype=np.int64)
        self._touched = np.zeros(n, dtype=bool)  # the rows in order
        self._rows = np.empty((0, width))
        self._inverse = np.zeros((0, 0))

    def gram_inverse(self) -> np.ndarray:
        """W_R^-1 for the rows touched so far: for W_R = [[A, B], [B^T, C]] with A^-1 known and
        the Schur complement S = C - B^T A^-1 B of the new rows, W_R^-1 = [[A^-1 + F S^-1 F^T,
        -F S^-1], [-S^-1 F^T, S^-1]], F = A^-1 B."""
        old = len(self._inverse)
        if self.k > old:
            B, C = self._bordering(old)
            F = self._inverse @ B
            S = _cholesky(C - B.T @ F,
                          "the Woodbury columns of the new rows are numerically dependent (W_R singular): "
                          "factorise the operator afresh")
            S_inv = sla.cho_solve(S, np.eye(self.k - old), check_finite=False)
            FS = F @ S_inv
            grown = np.empty((self.k, self.k))
            grown[:old, :old] = self._inverse + FS @ F.T
            grown[:old, old:] = -FS
            grown[old:, :old] = -FS.T
            grown[old:, old:] = S_inv
            self._inverse = grown
        return self._inverse

    def touch(self, rows: np.ndarray) -> np.ndarray:
        """Make the columns of the ``rows`` not touched before; return the order of all."""
        new = np.unique(rows[~self._touched[rows]])
        if len(new):
            if self.k + len(new) > len(self._rows):
                need = self.k + len(new)
                size = max(need, min(max(int(GROWTH * need), 64), self.capacity))
                grown = np.empty((size, self.width))
                grown[: self.k] = self._rows[: self.k]
                self._rows = grown
            self._rows[self.k: self.k + len(new)] = self._new(new)
            self.k += len(new)
            self.order = np.concatenate([self.order, new])
            self._touched[new] = True
        return self.order

    @property
    def columns(self) -> np.ndarray:
        return self._rows[: self.k].T


class _Solved(_Columns):
    """The factor P of diag(s) + b A0 and the columns W = P^-1 E solved so far; with
    ``groups``, the columns of a touched row's group that are not needed yet wait in
    ``_ready``. M^-1 r = x0 - W c, x0 = P^-1 r, c = correct(x0_R)."""

    def __init__(self, factor: Factor, n: int, capacity: int, groups=None):
        super().__init__(n, n, capacity)
        self.factor, self.groups = factor, groups
        self.solve = factor.solve
        self._ready = {}

    def _bordering(self, old: int) -> tuple[np.ndarray, np.ndarray]:
        """W_R = E^T P^-1 E between the first ``old`` rows in ``order`` and the rest, and among the rest."""
        W, first, rest = self.columns, self.order[:old], self.order[old:]
        return W[first, old:], W[rest, old:]

    def corrected(self, correct):
        W, order = self.columns, self.order

        def solve(r):
            x0 = np.asarray(self.factor.solve(r))
            return x0 - W @ correct(x0[order])

        return solve

    def _new(self, rows: np.ndarray) -> list:
        self._solve(np.array([r for r in rows.tolist() if r not in self._ready], dtype=np.int64))
        return [self._ready.pop(r) for r in rows.tolist()]

    def _solve(self, rows: np.ndarray):
        """Solve the columns of ``rows`` (and of the rest of their groups) into ``_ready``."""
        if len(rows) == 0:
            return
        if self.groups is not None:
            rows = np.flatnonzero(np.isin(self.groups, self.groups[rows]))
        E = np.zeros((self.width, len(rows)))
        E[rows, np.arange(len(rows))] = 1.0
        cols = np.asarray(self.factor.solve(E)).reshape(self.width, -1).T
        self._ready.update(zip(rows.tolist(), cols))


class _Trailing(_Columns):
    """A ``trailing.TrailingFactor`` L of diag(s) + b A0 with the region last, and the
    columns G = L^-1 E (on the region: columns of L_S^-1). W_R = G^T G = (S^-1)_RR and
    M^-1 r = L^-T (z - G c), z = L^-1 r, c = correct(G^T z): one forward and one backward
    half solve, O(|region| k) besides."""

    def __init__(self, factor: trailing.TrailingFactor, capacity: int):
        super().__init__(factor.n, len(factor.trailing_inverse), capacity)
        self.factor, self.solve = factor, factor.solve

    def _bordering(self, old: int) -> tuple[np.ndarray, np.ndarray]:
        """W_R = G^T G between the first ``old`` rows in ``order`` and the rest, and among the rest."""
        G = self.columns
        rows = G[:, old:].T @ G
        return rows[:, :old].T, rows[:, old:]

    def corrected(self, correct):
        G, m = self.columns, self.factor.n_first

        def solve(r):
            z = self.factor.forward(r)
            z[m:] -= G @ correct(G.T @ z[m:])
            return self.factor.backward(z)

        return solve

    def _new(self, rows: np.ndarray) -> np.ndarray:
        return self.factor.trailing_inverse[:, self.factor.position[rows]].T


class Refined:
    """An SPD operator known exactly only by its product ``matvec`` (numpy (n,) or (n, k)),
    with ``approx`` (a ``LocallyUpdated`` close to it: the factor of a stale tangent) as the
    preconditioner: ``shifted_factor(s, b)`` solves diag(s) + b A by conjugate gradients to
    ``rtol``; ``iterations`` is the count of the latest solve (how stale ``approx`` is)."""

    def __init__(self, matvec, approx: LocallyUpdated, rtol: float = 1e-8, maxiter: int = 200):
        self.matvec, self.approx, self.rtol, self.maxiter = matvec, approx, rtol, maxiter
        self.shape = approx.shape
        self._latest = None

    def __matmul__(self, v):
        return self.matvec(v)

    @property
    def iterations(self) -> int:
        return 0 if self._latest is None else self._latest.iterations

    def shifted_factor(self, s: np.ndarray, b: float) -> Factor:
        s = np.asarray(s, dtype=np.float64)
        pre, matvec = self.approx.shifted_factor(s, b), self.matvec  # no cycle through self

        def product(x):
            return s.reshape(-1, *([1] * (x.ndim - 1))) * x + b * matvec(x)

        self._latest = PCGFactor(product, pre.solve, self.shape[0], self.rtol, self.maxiter)
        return self._latest
