"""Gaussian Markov random fields over the particle graph (no Pyro here).

A field x (one value per particle) has precision

    Q(ell, s) = tau (I + ell^2 A),        A = c D^T W D  (~ -Laplacian in the interior),

D the signed incidence matrix of the graph's pairs (i, j), W = diag(1 / |xi|^2) and
c = 2 dim / n_max, n_max the largest number of neighbours of a particle: for a smooth z,
sum_pairs (z_j - z_i)^2 / |xi|^2 ~ (n / (2 dim)) sum_i |grad z|^2 on a lattice neighbourhood
(sum of e e^T over a symmetric family = (n / dim) I), so A approximates -Laplacian with
free (Neumann) edges. Q is the precision of the SPDE (1 - ell^2 Laplacian) x = white noise
(Lindgren, Rue & Lindstrom 2011, alpha = 1): ``ell`` is a correlation length in the units of
the positions, and tau is set so that the mean marginal variance (1/N) tr Q^-1 equals s^2:
``s`` is the root-mean-square amplitude of the field.

Log-determinant: exact, from the eigenvalues lambda_k of A computed once (dense symmetric
eigendecomposition, O(N^3) once, fine for N up to a few thousand):
log det Q = N log tau + sum_k log(1 + ell^2 lambda_k) and (1/N) tr (I + ell^2 A)^-1 =
mean_k 1 / (1 + ell^2 lambda_k), both O(N) per evaluation and differentiable in ell and s.
The quadratic form uses the sparse Q (torch sparse, the graph's pattern).

Tikhonov link (Turner 2015 eq 12 with a general L): at fixed (ell, s) the negative log density
is psi/2 ||L (x - m)||^2 + const with psi = tau and L = [I; ell sqrt(c) W^1/2 D]
(``square_root``), L^T L = I + ell^2 A: the MAP of a model with this prior is the Tikhonov
solution with that psi and L.
"""
from __future__ import annotations

import math

import numpy as np
import scipy.sparse as sp
import torch


def _pairs(particles, bonds, radius):
    i, j, length = np.asarray(bonds.i), np.asarray(bonds.j), np.asarray(bonds.length)
    if radius is not None:
        keep = length <= radius * (1 + 1e-9)
        i, j, length = i[keep], j[keep], length[keep]
    if len(i) == 0:
        raise ValueError("the graph has no pairs: use a larger radius (at least h)")
    return i, j, length


class GMRF:
    """Precision Q(ell, s) of the module docstring over the pairs (i, j) of ``bonds``
    (a ``bp.Bonds``: the scene's bond graph) no longer than ``radius`` (default: all)."""

    def __init__(self, particles, bonds, radius: float | None = None):
        i, j, length = _pairs(particles, bonds, radius)
        n = particles.n
        rows = np.repeat(np.arange(len(i)), 2)
        D = sp.csr_matrix((np.tile([-1.0, 1.0], len(i)), (rows, np.stack([i, j], 1).reshape(-1))),
                          shape=(len(i), n))
        degree = np.bincount(i, minlength=n) + np.bincount(j, minlength=n)
        if np.any(degree == 0):
            raise ValueError(f"{int(np.sum(degree == 0))} particle(s) have no pair in the graph: "
                             "a GMRF over it would leave them unconnected; use a larger radius")
        self.c = 2.0 * particles.dim / degree.max()
        self._root = sp.diags(np.sqrt(self.c) / length) @ D  # A = root^T root
        A = (self._root.T @ self._root).tocsr()
        self.n, self.pairs = n, len(i)
        values, vectors = np.linalg.eigh(A.toarray())
        self.eigenvalues = torch.as_tensor(np.clip(values, 0.0, None))  # A is PSD; 0 = constants
        self._vectors = torch.as_tensor(vectors)
        coo = A.tocoo()
        eye = sp.identity(n, format="coo")
        self._index = torch.as_tensor(np.stack([np.r_[coo.row, eye.row], np.r_[coo.col, eye.col]]))
        self._a_values = torch.as_tensor(np.r_[coo.data, np.zeros(n)])
        self._i_values = torch.as_tensor(np.r_[np.zeros(coo.nnz), np.ones(n)])
        self.laplacian = A
        self._A = torch.sparse_coo_tensor(self._index, self._a_values, (n, n), check_invariants=True).coalesce()

    def mean_variance(self, ell) -> torch.Tensor:
        """(1/N) tr (I + ell^2 A)^-1, exact (eigenvalues of A)."""
        return (1.0 / (1.0 + torch.as_tensor(ell) ** 2 * self.eigenvalues)).mean()

    def tau(self, ell, s) -> torch.Tensor:
        """Scale of Q such that the mean marginal variance is s^2."""
        return self.mean_variance(ell) / torch.as_tensor(s) ** 2

    def precision(self, ell, s) -> torch.Tensor:
        """Q(ell, s) as a sparse (N, N) torch tensor, differentiable in ell and s."""
        ell, tau = torch.as_tensor(ell), self.tau(ell, s)
        values = tau * (self._i_values + ell**2 * self._a_values)
        return torch.sparse_coo_tensor(self._index, values, (self.n, self.n), check_invariants=True).coalesce()

    def log_det(self, ell, s) -> torch.Tensor:
        """log det Q(ell, s), exact."""
        ell = torch.as_tensor(ell)
        return self.n * torch.log(self.tau(ell, s)) + torch.log1p(ell**2 * self.eigenvalues).sum()

    def log_prob(self, x, mean, ell, s) -> torch.Tensor:
        """log N(x; mean, Q(ell, s)^-1) over the last axis of x (leading batch dims allowed)."""
        d = torch.as_tensor(x) - torch.as_tensor(mean)
        ell = torch.as_tensor(ell)
        flat = d.reshape(-1, self.n)
        quad = (flat**2).sum(-1) + ell**2 * (flat * torch.sparse.mm(self._A, flat.T).T).sum(-1)
        quad = self.tau(ell, s) * quad.reshape(d.shape[:-1])
        return 0.5 * (self.log_det(ell, s) - quad - self.n * math.log(2 * math.pi))

    def colour(self, w, ell, s) -> torch.Tensor:
        """Q(ell, s)^-1/2 w (symmetric root, from the eigenvectors of A): white noise w (..., N)
        becomes a zero-mean field with precision Q; differentiable in w, ell and s."""
        scale = 1.0 / torch.sqrt(self.tau(ell, s) * (1.0 + torch.as_tensor(ell) ** 2 * self.eigenvalues))
        return ((w @ self._vectors) * scale) @ self._vectors.T

    def sample(self, mean, ell, s, shape=(), generator=None) -> torch.Tensor:
        """Exact draws mean + Q^-1/2 eps."""
        return torch.as_tensor(mean) + self.colour(torch.randn(*shape, self.n, generator=generator), ell, s)

    def square_root(self, ell) -> sp.csr_matrix:
        """L = [I; ell sqrt(c) W^1/2 D] with L^T L = I + ell^2 A = Q / tau (scipy sparse): with
        psi = tau(ell, s), Tikhonov's psi/2 ||L (z - z_ref)||^2 is the GMRF's quadratic form."""
        return sp.vstack([sp.identity(self.n), float(ell) * self._root]).tocsr()
