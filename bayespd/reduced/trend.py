"""The part of an approximation error that the parameters explain: a trend mu(theta) fitted to
errors eps_i at draws theta_i, in features phi(theta) (default: the log of every parameter).

* ``LinearTrend``: mu + B (phi - phi_bar), B by least squares (Kaipio & Somersalo 2007's
  enhanced error model with a conditional mean linear in phi).
* ``SmoothTrend``: the polyharmonic radial-basis interpolant of eps in the standardised
  features x = (phi - phi_bar) / s, kernel -r^5 plus a quadratic polynomial (Wendland 2005,
  "Scattered data approximation", ch. 8: unique for nodes unisolvent for quadratics; C^4, so a
  likelihood with it stays twice differentiable). Needed where eps is far from linear in phi
  (the horizon's error across delta in [h, 3h]). Its residuals are the leave-one-out errors,
  each an honest out-of-sample error, from one inverse by Rippa's formula e_i = a_i / (A^-1)_ii
  (Rippa 1999, Adv. Comput. Math. 11, 193-210; A the interpolation matrix with the polynomial
  block, a = A^-1 [eps; 0]).

Each ``fit_*`` returns (trend, residuals (draws, n), degrees of freedom): the residuals' sample
covariance over the dof is the term's Gamma_eps. A trend maps a params dict to the mean error,
flattened (n,), differentiably.
"""
from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import torch


@dataclass(frozen=True)
class LogFeatures:
    """phi(params) = log of each of ``names``: the default features (module-level, so a model
    holding it pickles into NUTS worker processes; a feature map of your own must too)."""

    names: tuple

    def __call__(self, params: dict) -> torch.Tensor:
        values = torch.stack([torch.as_tensor(params[k], dtype=torch.float64) for k in self.names])
        if not bool((values > 0).all()):
            raise ValueError(f"LogFeatures uses log(params) of {list(self.names)}: every value must be positive, got "
                             f"{dict(zip(self.names, values.tolist()))}")
        return values.log()


@dataclass(frozen=True)
class ElasticFeatures:
    """phi(params) = (log(G / K), delta). With ``relative=True`` the error of a linear elastic
    scene under prescribed loads is unchanged when K and G scale together (u scales as 1 / K in
    both models), so it depends on the moduli only through G / K: two features, not three;
    ``with_delta=False`` (delta held, ``bp.Held``): log(G / K) alone."""

    with_delta: bool = True

    def __call__(self, params: dict) -> torch.Tensor:
        K, G = (torch.as_tensor(params[k], dtype=torch.float64) for k in ("K", "G"))
        if not self.with_delta:
            return torch.log(G / K).reshape(1)
        return torch.stack([torch.log(G / K), torch.as_tensor(params["delta"], dtype=torch.float64)])


def feature_matrix(features: Callable, draws: Sequence[dict]) -> torch.Tensor:
    """(draws, q) features of every draw, checked finite and of one length."""
    rows = [torch.as_tensor(features(p), dtype=torch.float64).reshape(-1) for p in draws]
    if len({len(r) for r in rows}) != 1:
        raise ValueError("the features returned vectors of different lengths across the draws")
    phi = torch.stack(rows)
    if not bool(torch.isfinite(phi).all()):
        raise ValueError("the features are NaN/inf at some draw: map the parameters to finite values")
    return phi


@dataclass(frozen=True)
class LinearTrend:
    """mu + B (phi(params) - centre); intercept (n,), slope (n, q)."""

    features: Callable
    intercept: torch.Tensor
    slope: torch.Tensor
    centre: torch.Tensor

    def __call__(self, params: dict) -> torch.Tensor:
        return self.intercept + self.slope @ (self.features(params) - self.centre)


def fit_linear(features: Callable, draws: Sequence[dict], E: torch.Tensor) -> tuple:
    phi = feature_matrix(features, draws)
    centre = phi.mean(0)
    X = torch.cat([torch.ones(len(draws), 1, dtype=torch.float64), phi - centre], 1)
    coef = torch.linalg.lstsq(X, E).solution  # (1 + q, n): row 0 mu, rows 1: B^T
    trend = LinearTrend(features, coef[0], coef[1:].T.contiguous(), centre)
    return trend, E - X @ coef, len(draws) - X.shape[1]


def _monomials(x: torch.Tensor, degree: int = 2) -> torch.Tensor:
    """(..., m): every monomial of total degree <= ``degree`` in the last axis of ``x``."""
    q = x.shape[-1]
    columns = [torch.ones(x.shape[:-1], dtype=x.dtype)]
    for d in range(1, degree + 1):
        columns += [math.prod(x[..., i] for i in combo) for combo in itertools.combinations_with_replacement(range(q), d)]
    return torch.stack(columns, -1)


def _kernel(x: torch.Tensor, nodes: torch.Tensor) -> torch.Tensor:
    """-r^5 between each row of x (..., q) and each node (N, q), via r^2 so that its first and
    second derivatives are finite at r = 0."""
    r2 = (x[..., None, :] - nodes).square().sum(-1)
    return -r2.pow(2.5)


@dataclass(frozen=True)
class SmoothTrend:
    """sum_i a_i phi(|x - x_i|) + p(x) in x = (phi(params) - centre) / scale; nodes (N, q),
    weights (N, n), coef (m, n) of the monomials of degree <= 2."""

    features: Callable
    centre: torch.Tensor
    scale: torch.Tensor
    nodes: torch.Tensor
    weights: torch.Tensor
    coef: torch.Tensor

    def __call__(self, params: dict) -> torch.Tensor:
        x = (self.features(params) - self.centre) / self.scale
        return _kernel(x, self.nodes) @ self.weights + _monomials(x) @ self.coef


def fit_smooth(features: Callable, draws: Sequence[dict], E: torch.Tensor) -> tuple:
    phi = feature_matrix(features, draws)
    centre, scale = phi.mean(0), phi.std(0)
    if not bool((scale > 0).all()):
        raise ValueError("a feature takes one value over every draw: drop it from the features, or draw it")
    x = (phi - centre) / scale
    P = _monomials(x)
    n, m = P.shape
    A = torch.cat([torch.cat([_kernel(x, x), P], 1), torch.cat([P.T, torch.zeros(m, m, dtype=P.dtype)], 1)])
    if n < m + 2 or torch.linalg.matrix_rank(P) < m:
        raise ValueError(f"the smooth trend in {phi.shape[1]} features needs draws that determine a quadratic "
                         f"({m} coefficients) and more: give at least {m + 2} distinct, spread draws (dozens "
                         "per feature are typical)")
    inverse = torch.linalg.inv(A)
    solution = inverse[:, :n] @ E
    leave_one_out = solution[:n] / inverse.diagonal()[:n, None]
    return SmoothTrend(features, centre, scale, x, solution[:n], solution[n:]), leave_one_out, n
