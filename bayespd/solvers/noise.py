"""Noise covariances C for the Langevin forcing sqrt(2C) dB (Dodwell 2019 eq 4), in the form

    C = diag(d) + G G^T,   C^{1/2} xi := sqrt(d) xi_1 + G xi_2   (xi ~ N(0, I_{n_xi})),

so that Cov(C^{1/2} xi) = C. ``white_noise`` is C = sigma^2 I (G absent); ``karhunen_loeve``
is C = sigma^2 (R_r + nugget I) with R_r the rank-r truncated Karhunen-Loeve expansion of a
squared-exponential kernel on the particles, G = sigma Phi Lambda^{1/2} (x) I_dim: the same
spatial correlation for every displacement component, never a dense N x N factorisation.
"""
from __future__ import annotations

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import torch
from scipy.spatial import cKDTree

from bayespd.linalg.assembly import to_numpy
from bayespd.linalg.factors import shifted_factor


class Covariance:
    """C = diag(d) + G G^T on n dofs; ``d`` (n,) all positive or all zero, ``G`` (n, m) or None."""

    def __init__(self, diagonal, factor=None):
        self.d = np.asarray(to_numpy(diagonal), dtype=np.float64).reshape(-1)
        if not (np.all(self.d > 0) or np.all(self.d == 0)):
            raise ValueError("the diagonal of C must be all positive or all zero")
        self.n = len(self.d)
        self.G = None if factor is None else np.asarray(to_numpy(factor), dtype=np.float64)
        if self.G is not None and self.G.shape[0] != self.n:
            raise ValueError(f"the factor G must have {self.n} rows")
        self._diag = bool(self.d[0] > 0)
        if not self._diag and self.G is None:
            raise ValueError("C = 0: give a positive diagonal or a factor")
        self.m = 0 if self.G is None else self.G.shape[1]
        self.n_xi = (self.n if self._diag else 0) + self.m

    def sample(self, xi: torch.Tensor) -> torch.Tensor:
        """C^{1/2} xi for xi of shape (n_xi, *batch)."""
        x = to_numpy(xi)
        out = np.zeros((self.n, *x.shape[1:]))
        if self._diag:
            out += _col(np.sqrt(self.d), x) * x[: self.n]
        if self.G is not None:
            out += self.G @ x[self.n_xi - self.m:]
        return torch.from_numpy(out).to(xi.dtype)

    def adjoint(self, v: torch.Tensor) -> torch.Tensor:
        """(C^{1/2})^T v, of shape (n_xi, *batch)."""
        x = to_numpy(v)
        parts = [_col(np.sqrt(self.d), x) * x] if self._diag else []
        if self.G is not None:
            parts.append(self.G.T @ x)
        return torch.from_numpy(np.concatenate(parts)).to(v.dtype)

    def matvec(self, v: torch.Tensor) -> torch.Tensor:
        """C v."""
        x = to_numpy(v)
        out = _col(self.d, x) * x
        if self.G is not None:
            out = out + self.G @ (self.G.T @ x)
        return torch.from_numpy(out).to(v.dtype)

    def dense(self) -> np.ndarray:
        """C as a dense matrix (for tests on small problems)."""
        C = np.diag(self.d)
        return C if self.G is None else C + self.G @ self.G.T

    def implicit_solver(self, A, b: float):
        """x = (I + b C A)^-1 r for a sparse SPD A: with B = I + b diag(d) A,
        B^-1 r = (diag(d)^-1 + b A)^-1 (r / d) (one sparse Cholesky), and the low-rank part by
        Woodbury, (B + b G G^T A)^-1 = B^-1 - W S^-1 G^T A B^-1 with W = b B^-1 G and
        S = I_m + G^T A W (m extra solves once, then one m x m LU). A: a scipy sparse matrix
        or a ``woodbury.LocallyUpdated`` (then its factor is updated, not made afresh)."""
        if self._diag:
            factor = shifted_factor(A, 1 / self.d, b)

            def base(r):
                return factor.solve(_col(1 / self.d, r) * r)
        else:
            def base(r):
                return r
        if self.G is None:
            return lambda r: torch.from_numpy(np.asarray(base(to_numpy(r)))).to(r.dtype)
        W = np.asarray(base(b * self.G))
        GA = np.asarray((A @ self.G).T)  # G^T A (A symmetric)
        lu = sla.lu_factor(np.eye(self.m) + GA @ W)

        def solve(r):
            y = np.asarray(base(to_numpy(r)))
            return torch.from_numpy(y - W @ sla.lu_solve(lu, GA @ y)).to(r.dtype)

        return solve


def _col(w: np.ndarray, x: np.ndarray) -> np.ndarray:
    """w (n,) shaped to broadcast against x (n, *batch)."""
    return w.reshape(-1, *([1] * (x.ndim - 1)))


def white_noise(sigma, n: int) -> Covariance:
    """C = sigma^2 I on n dofs (sigma a scalar or one value per dof)."""
    s = np.broadcast_to(np.asarray(to_numpy(sigma), dtype=np.float64), (n,))
    if not (np.all(np.isfinite(s)) and np.all(s > 0)):
        raise ValueError("sigma must be finite and positive")
    return Covariance(s**2)


class KLCovariance(Covariance):
    """A truncated Karhunen-Loeve covariance (see ``karhunen_loeve``): ``eigenvalues``
    (r,) and ``modes`` Phi (N, r) of the kernel matrix R, and ``fraction`` =
    sum(eigenvalues) / trace(R) = sum(eigenvalues) / N, the share of the kernel's variance kept."""


def karhunen_loeve(x, sigma, length: float, rank: int | None = None, fraction: float = 0.95,
                   nugget: float = 0.0, cutoff: float = 4.0, dim: int | None = None,
                   dofs=None) -> KLCovariance:
    """C = sigma^2 (Phi Lambda Phi^T + nugget I) (x) I_dim on particles ``x`` (N, space dim).

    R_ij = exp(-|x_i - x_j|^2 / (2 length^2)) is assembled sparse, cut off at
    ``cutoff * length`` (dropped entries are below exp(-cutoff^2 / 2) = 3.4e-4 at 4), and its
    leading eigenpairs come from Lanczos (``eigsh``): ``rank`` of them, or the fewest
    (doubling from 16) whose sum reaches ``fraction`` of trace(R) = N. The trace error of the
    truncation is (1 - fraction) N and its 2-norm error lambda_{r+1}. ``sigma``: scalar or
    one value per particle (C = S R S). ``nugget`` > 0 makes C positive definite, so the
    invariant law of the Langevin dynamics does not depend on C; without it every step moves
    U within U_0 + range(C) (r * dim directions). ``dofs`` restricts C to
    those indices of the N*dim node-major dofs (e.g. the free dofs).
    """
    x = np.asarray(x, dtype=np.float64)
    N = len(x)
    dim = dim or x.shape[1]
    if not length > 0 or not nugget >= 0 or not 0 < fraction <= 1:
        raise ValueError("need length > 0, nugget >= 0 and 0 < fraction <= 1")
    pairs = cKDTree(x).query_pairs(cutoff * length, output_type="ndarray")
    r2 = np.sum((x[pairs[:, 0]] - x[pairs[:, 1]]) ** 2, axis=1)
    k = np.exp(-r2 / (2 * length**2))
    R = sp.coo_matrix((np.concatenate([k, k, np.ones(N)]),
                       (np.concatenate([pairs[:, 0], pairs[:, 1], np.arange(N)]),
                        np.concatenate([pairs[:, 1], pairs[:, 0], np.arange(N)]))), shape=(N, N)).tocsr()
    v0 = np.random.default_rng(0).standard_normal(N)
    r = rank or min(16, N - 1)
    while True:
        if not 0 < r < N:
            raise ValueError(f"rank must lie in [1, {N - 1}] (eigsh needs rank < N)")
        lam, phi = spla.eigsh(R, k=r, which="LA", v0=v0)
        keep = lam > 0
        lam, phi = lam[keep][::-1], phi[:, keep][:, ::-1]
        if rank or lam.sum() >= fraction * N or r == N - 1:
            break
        r = min(2 * r, N - 1)
    s = np.broadcast_to(np.asarray(to_numpy(sigma), dtype=np.float64), (N,))
    if not (np.all(np.isfinite(s)) and np.all(s > 0)):
        raise ValueError("sigma must be finite and positive")
    G = np.kron(s[:, None] * phi * np.sqrt(lam), np.eye(dim))
    d = np.repeat(s**2 * nugget, dim)
    if dofs is not None:
        G, d = G[np.asarray(dofs)], d[np.asarray(dofs)]
    cov = KLCovariance(d, G)
    cov.eigenvalues, cov.modes, cov.fraction = lam, phi, float(lam.sum() / N)
    return cov
