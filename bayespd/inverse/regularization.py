"""Regularisation operators L for the Tikhonov term psi/2 ||L (z - z_ref)||^2 (Turner 2015 eq 12).

``None`` / ``"identity"``: L = I (Turner 2015's choice, which penalises the parameters
themselves). ``"gradient"``: a graph gradient over neighbour pairs in grid units,
(L z)_b = (z_j - z_i) h / |xi_b| for every pair closer than ``radius`` (default 1.5 h: the 8
nearest neighbours on a square grid), which penalises roughness of a per-particle field and
leaves its mean free; the h makes it dimensionless, so psi means the same for any length unit.
A user may also pass any matrix (scipy sparse, numpy or torch) with one column per unknown.
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import torch
from scipy.spatial import cKDTree

from bayespd.discretize import Particles


def graph_gradient(particles: Particles, radius: float | None = None) -> torch.Tensor:
    """Sparse (n_pairs, N) operator (z_j - z_i) h / |xi| over the pairs closer than ``radius``."""
    radius = 1.5 * particles.h if radius is None else float(radius)
    pairs = cKDTree(particles.x).query_pairs(radius * (1 + 1e-9), output_type="ndarray")
    if len(pairs) == 0:
        raise ValueError(f"no particle pairs closer than radius={radius:g}: use radius >= h")
    i, j = pairs[:, 0], pairs[:, 1]
    inv = particles.h / np.linalg.norm(particles.x[j] - particles.x[i], axis=1)
    rows = np.repeat(np.arange(len(pairs)), 2)
    cols = np.stack([i, j], axis=1).reshape(-1)
    vals = np.stack([-inv, inv], axis=1).reshape(-1)
    return _torch_sparse(sp.coo_matrix((vals, (rows, cols)), shape=(len(pairs), particles.n)))


def _torch_sparse(A) -> torch.Tensor:
    A = sp.coo_matrix(A)
    index = torch.as_tensor(np.stack([A.row, A.col]).astype(np.int64))
    return torch.sparse_coo_tensor(index, torch.as_tensor(A.data, dtype=torch.float64), A.shape,
                                   check_invariants=True).coalesce()


def regularization_operator(spec, name: str, size: int, particles: Particles) -> torch.Tensor | None:
    """L for the unknown ``name`` with ``size`` entries (1: scalar); None means the identity."""
    if spec is None or (isinstance(spec, str) and spec == "identity"):
        return None
    if isinstance(spec, str):
        if spec != "gradient":
            raise ValueError(f"unknown regularisation {spec!r} for {name}: use 'identity', "
                             "'gradient' or a matrix with one column per unknown")
        if size != particles.n:
            raise ValueError(f"a graph gradient regularises a per-particle field, but {name} "
                             f"has {size} value(s), not {particles.n}: use 'identity' for scalars")
        return graph_gradient(particles)
    if isinstance(spec, torch.Tensor):
        L = spec.to(torch.float64)
    else:
        L = _torch_sparse(spec) if sp.issparse(spec) else torch.as_tensor(np.asarray(spec, dtype=float))
    if L.dim() != 2 or L.shape[1] != size:
        raise ValueError(f"the regularisation matrix for {name} must have {size} column(s) "
                         f"(one per unknown), got shape {tuple(L.shape)}")
    return L
