"""Differentiable sparse symmetric positive-definite solve (the adjoint is a solve, not a tape).

``solve(pattern, values, rhs)`` factorises K once; its backward solves K lambda = grad_u with
the same factorisation (K is symmetric: seed 000 §3.3) and returns

    grad_values[k] = -lambda[rows[k]] * u[cols[k]],   grad_rhs = lambda,

computed from the index lists (never a dense n x n matrix). The backward calls the same
Function, so second derivatives and Hessian-vector products exist.

Backends: CHOLMOD (scikit-sparse) when importable, analysing the pattern once and
refactorising per value; else scipy's SuperLU in symmetric mode with an AMD ordering.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import torch

try:  # optional extra `fast`
    from sksparse import cholmod
except ImportError:  # pragma: no cover - depends on the machine
    cholmod = None


class NotPositiveDefiniteError(RuntimeError):
    """The stiffness is not positive definite (unstable material, too few constraints, ...)."""


@dataclass(eq=False)
class Pattern:
    """A fixed sparsity pattern of an n x n matrix, entries in CSC order (column-major).

    ``rows``/``cols`` are int64 arrays; symmetric patterns list both triangles.
    """

    rows: np.ndarray
    cols: np.ndarray
    n: int
    _symbolic: object = field(default=None, repr=False)

    def __post_init__(self):
        order = np.lexsort((self.rows, self.cols))
        if not np.array_equal(order, np.arange(len(order))):
            raise ValueError("pattern entries must be sorted by (col, row)")
        self.indptr = np.searchsorted(self.cols, np.arange(self.n + 1)).astype(np.int64)
        self.rows_t = torch.as_tensor(self.rows)
        self.cols_t = torch.as_tensor(self.cols)

    @property
    def nnz(self) -> int:
        return len(self.rows)

    def matrix(self, values: torch.Tensor) -> sp.csc_matrix:
        v = values.detach().cpu().numpy()
        return sp.csc_matrix((v, self.rows, self.indptr), shape=(self.n, self.n))

    def matvec(self, values: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        """K x as a differentiable gather/scatter (x may be (n,) or (n, k))."""
        contrib = values.reshape(-1, *([1] * (x.dim() - 1))) * x[self.cols_t]
        return torch.zeros_like(x, dtype=contrib.dtype).index_add(0, self.rows_t, contrib)

    def restrict(self, keep: np.ndarray):
        """Sub-pattern on the dofs where ``keep`` is true, and which entries it keeps."""
        index = np.cumsum(keep) - 1
        entries = keep[self.rows] & keep[self.cols]
        sub = Pattern(index[self.rows[entries]], index[self.cols[entries]], int(keep.sum()))
        return sub, np.flatnonzero(entries)

    def factorize(self, values: torch.Tensor, backend: str | None = None) -> "Factor":
        backend = backend or default_backend()
        A = self.matrix(values)
        if not np.all(np.isfinite(A.data)):
            raise NotPositiveDefiniteError("stiffness has non-finite entries (check parameters)")
        if backend == "cholmod":
            return _cholmod_factor(self, A)
        if backend == "splu":
            return _splu_factor(A)
        raise ValueError(f"unknown backend {backend!r}: use 'cholmod' or 'splu'")


def default_backend() -> str:
    return "cholmod" if cholmod is not None else "splu"


class Factor:
    """A factorisation with ``solve(b)`` for numpy b of shape (n,) or (n, k)."""

    def __init__(self, solve_fn):
        self.solve = solve_fn


def _cholmod_factor(pattern: Pattern, A) -> Factor:
    try:
        if pattern._symbolic is None:
            pattern._symbolic = cholmod.analyze(A, mode="supernodal")
        f = pattern._symbolic.cholesky(A)
    except cholmod.CholmodNotPositiveDefiniteError as e:
        raise NotPositiveDefiniteError(f"stiffness is not positive definite ({e})") from None
    return Factor(f.solve_A)


def _splu_factor(A) -> Factor:
    with warnings.catch_warnings():
        warnings.simplefilter("error", sp.SparseEfficiencyWarning)
        try:
            lu = spla.splu(A, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                           options={"SymmetricMode": True})
        except RuntimeError as e:  # "Factor is exactly singular"
            raise NotPositiveDefiniteError(f"stiffness is singular ({e}): are rigid-body "
                                           "motions constrained?") from None
    # With diagonal pivots, K = P^T L U P^T with U's diagonal the pivots of an LDL^T:
    # K is positive definite iff they are all positive and no row swap was needed.
    pivots = lu.U.diagonal()
    if not (np.array_equal(lu.perm_r, lu.perm_c) and np.all(pivots > 0)):
        raise NotPositiveDefiniteError("stiffness is not positive definite (a non-positive "
                                       "pivot): check moduli, horizon and constraints")
    return Factor(lu.solve)


class _Solve(torch.autograd.Function):
    @staticmethod
    def forward(ctx, values, rhs, pattern, factor):
        if factor is None:
            factor = pattern.factorize(values)
        u = torch.as_tensor(factor.solve(rhs.detach().cpu().numpy()), dtype=rhs.dtype,
                            device=rhs.device)
        ctx.pattern, ctx.factor = pattern, factor
        ctx.save_for_backward(values, u)
        return u

    @staticmethod
    def backward(ctx, grad_u):
        values, u = ctx.saved_tensors
        p = ctx.pattern
        lam = _Solve.apply(values, grad_u, p, ctx.factor)
        grad_values = None
        if ctx.needs_input_grad[0]:
            prod = -lam[p.rows_t] * u[p.cols_t]
            grad_values = prod if prod.dim() == 1 else prod.sum(dim=-1)
        return grad_values, lam, None, None


def solve(pattern: Pattern, values: torch.Tensor, rhs: torch.Tensor) -> torch.Tensor:
    """u = K(values)^-1 rhs for symmetric positive-definite K on ``pattern``; differentiable
    (twice) in ``values`` and ``rhs``. ``rhs`` is (n,) or (n, k)."""
    if values.shape != (pattern.nnz,):
        raise ValueError(f"values must have shape ({pattern.nnz},), got {tuple(values.shape)}")
    if rhs.shape[0] != pattern.n:
        raise ValueError(f"rhs must have {pattern.n} rows, got {rhs.shape[0]}")
    return _Solve.apply(values, rhs, pattern, None)
