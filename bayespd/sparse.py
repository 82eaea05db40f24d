"""Differentiable sparse symmetric positive-definite solve (the adjoint is a solve, not a tape).

``solve(pattern, values, rhs)`` factorises K once; its backward solves K lambda = grad_u with
the same factorisation (K is symmetric: seed 000 §3.3) and returns

    grad_values[k] = -lambda[rows[k]] * u[cols[k]],   grad_rhs = lambda,

computed from the index lists (never a dense n x n matrix). The general form, ``solve_form``,
takes K(params) through its bilinear form v^T K(params) u, so a material can return
grad_params = -d/dparams (lambda^T K u) matrix-free, at O(bonds) cost, without building the
stiffness values' autograd graph (seed 000 eqs 14-19). The backward calls the same Function,
so second derivatives and Hessian-vector products exist.

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

    def position(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """Entry index of each (row, col); every pair must be in the pattern."""
        keys = self.cols * self.n + self.rows
        query = np.asarray(cols, dtype=np.int64) * self.n + np.asarray(rows, dtype=np.int64)
        idx = np.searchsorted(keys, query)
        if not (np.all(idx < len(keys)) and np.array_equal(keys[idx], query)):
            raise KeyError("an entry is not in the pattern")
        return idx

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


class ValuesForm:
    """The bilinear form v^T K u of a matrix given by its values on a pattern."""

    def __init__(self, pattern: Pattern):
        self.pattern = pattern

    def __call__(self, v, u, values):
        p = self.pattern
        return (values.reshape(-1, *([1] * (u.dim() - 1))) * v[p.rows_t] * u[p.cols_t]).sum()


def _grad(out, inputs, **kw):
    grads = torch.autograd.grad(out, inputs, allow_unused=True, **kw)
    return [torch.zeros_like(x) if g is None else g for g, x in zip(grads, inputs)]


def _leaves(*tensors):
    return [t.detach().requires_grad_() for t in tensors]


class _FormGradient(torch.autograd.Function):
    """d/dparams of the bilinear form a(v, u; params) = v^T K(params) u at fixed v, u.

    Its backward differentiates once more (a Hessian-vector product of the form), which is
    what second derivatives of a solve need.
    """

    @staticmethod
    def forward(ctx, form, v, u, *params):
        ctx.form = form
        ctx.save_for_backward(v, u, *params)
        with torch.enable_grad():
            leaves = _leaves(*params)
            return tuple(_grad(form(v.detach(), u.detach(), *leaves), leaves))

    @staticmethod
    def backward(ctx, *w):
        v, u, *params = ctx.saved_tensors
        with torch.enable_grad():
            v_, u_, *leaves = _leaves(v, u, *params)
            grads = _grad(ctx.form(v_, u_, *leaves), leaves, create_graph=True)
            directional = sum((g * wi).sum() for g, wi in zip(grads, w))
            if not directional.requires_grad:  # no parameter enters the form
                return (None, None, None, *[None] * len(params))
            dv, du, *dp = _grad(directional, [v_, u_, *leaves])
        return (None, dv, du, *dp)


class _Solve(torch.autograd.Function):
    """u = K(params)^-1 rhs with a given factor; backward: one more solve with that factor."""

    @staticmethod
    def forward(ctx, form, factor, rhs, *params):
        u = torch.as_tensor(factor.solve(rhs.detach().cpu().numpy()), dtype=rhs.dtype,
                            device=rhs.device)
        ctx.form, ctx.factor = form, factor
        ctx.save_for_backward(u, *params)
        return u

    @staticmethod
    def backward(ctx, grad_u):
        u, *params = ctx.saved_tensors
        lam = _Solve.apply(ctx.form, ctx.factor, grad_u, *params)
        grads = [None] * len(params)
        if any(ctx.needs_input_grad[3:]):
            grads = [-g for g in _FormGradient.apply(ctx.form, lam, u, *params)]
        return (None, None, lam, *grads)


def solve_form(form, factor: Factor, rhs: torch.Tensor, params) -> torch.Tensor:
    """u = K^-1 rhs where ``factor`` factorises K(params) and ``form(v, u, *params)`` is
    v^T K(params) u (differentiable). The gradient with respect to params is
    -d/dparams form(lambda, u) with K lambda = grad_u: one extra solve, twice differentiable."""
    return _Solve.apply(form, factor, rhs, *params)


def solve(pattern: Pattern, values: torch.Tensor, rhs: torch.Tensor) -> torch.Tensor:
    """u = K(values)^-1 rhs for symmetric positive-definite K on ``pattern``; differentiable
    (twice) in ``values`` and ``rhs``, with grad_values[k] = -lambda[rows[k]] u[cols[k]].
    ``rhs`` is (n,) or (n, k)."""
    if values.shape != (pattern.nnz,):
        raise ValueError(f"values must have shape ({pattern.nnz},), got {tuple(values.shape)}")
    if rhs.shape[0] != pattern.n:
        raise ValueError(f"rhs must have {pattern.n} rows, got {rhs.shape[0]}")
    return solve_form(ValuesForm(pattern), pattern.factorize(values.detach()), rhs, (values,))
