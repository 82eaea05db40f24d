"""Differentiable sparse symmetric positive-definite solve (the adjoint is a solve, not a tape).

``solve(pattern, values, rhs)`` factorises K once; its backward solves K lambda = grad_u with
the same factorisation (K is symmetric: Turner 2015 §3.3) and returns

    grad_values[k] = -lambda[rows[k]] * u[cols[k]],   grad_rhs = lambda,

computed from the index lists (never a dense n x n matrix). The general form, ``solve_form``,
takes K(params) through its bilinear form v^T K(params) u, so a material can return
grad_params = -d/dparams (lambda^T K u) matrix-free, at O(bonds) cost, without building the
stiffness values' autograd graph (Turner 2015 eqs 14-19). The backward calls the same Function,
so second derivatives and Hessian-vector products exist.
"""
from __future__ import annotations

import torch

from bayespd.linalg.sparse import Factor, Pattern


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
        needed = ctx.needs_input_grad[3:]  # only these become leaves: a parameter that needs
        # no gradient stays a constant (a fixed horizon: LPS's family is then its kept one)
        with torch.enable_grad():
            leaves = [p.detach().requires_grad_(need) for p, need in zip(params, needed)]
            wanted = [x for x, need in zip(leaves, needed) if need]
            grads = iter(_grad(form(v.detach(), u.detach(), *leaves), wanted) if wanted else ())
            return tuple(next(grads) if need else torch.zeros_like(x) for x, need in zip(leaves, needed))

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
