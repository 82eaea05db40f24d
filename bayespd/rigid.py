"""A rigid-body nuisance at the observation points, marginalised exactly or estimated.

Measured fields (DIC, FE exports) carry an unknown rigid motion: the specimen slides and turns
in the grips, the DIC reference is arbitrary. With R (m, k) the rigid modes at the m kept
observation entries (translations, and the infinitesimal rotations x -> e x (x - c) about the
centroid c of the kept points) the data are

    y = H u(params) + R r + eps,   eps ~ N(0, sigma^2 I_m),   r in R^k unknown.

A flat prior on r integrates out in closed form. With R = Q [T; 0] (Householder QR, Q = [Q1 Q2]
orthogonal, range(Q1) = range(R)):

    p(y | params, sigma) = int N(y; H u + R r, sigma^2 I) dr
                         = |T|^-1 N(Q2^T y; Q2^T H u, sigma^2 I_{m-k})             (1)

|T| = |R^T R|^(1/2) does not depend on params or sigma, so the likelihood is the Gaussian of
the m - k rotated residual entries Q2^T (y - H u): the projection onto the orthogonal
complement of the rigid modes, with m - k (not m) entries counting in sigma's normalisation.
:class:`RigidNuisance` is an observation operator returning Q^T H u in the (points, dim) layout,
its ``mask`` dropping the k entries that hold Q1^T (the rigid coordinates): any model scoring
``Normal(scene.predict(params), sigma).mask(mask)`` against ``nuisance.data(y)`` then evaluates
(1) exactly. The least-squares estimate r = T^-1 Q1^T (y - H u) (``estimate``) is the mode of
the same posterior, for deterministic fits.
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import torch

from bayespd.observe import LinearObservation, model_data


def rigid_modes(points: np.ndarray, centre, rotation: bool = True) -> np.ndarray:
    """The rigid modes at ``points`` (n, dim) as (n, dim, k): the dim translations, then
    (``rotation``) the infinitesimal rotations about ``centre`` (one in 2D, three in 3D)."""
    n, dim = points.shape
    modes = [np.broadcast_to(np.eye(dim)[a], (n, dim)) for a in range(dim)]
    if rotation:
        r = points - centre
        axes = [2] if dim == 2 else [0, 1, 2]
        r3 = np.concatenate([r, np.zeros((n, 3 - dim))], axis=1)
        modes += [np.cross(np.eye(3)[a], r3)[:, :dim] for a in axes]
    return np.stack(modes, axis=-1)


def _householder(R: np.ndarray):
    """Householder vectors v_j (k, m), zero above j, with Q^T = H_k ... H_1, H_j = I - 2 v_j v_j^T,
    and the triangle T (k, k) of R = Q [T; 0]."""
    A = R.copy()
    m, k = A.shape
    V = np.zeros((k, m))
    for j in range(k):
        x = A[j:, j]
        v = x.copy()
        v[0] += np.copysign(np.linalg.norm(x), x[0])
        norm = np.linalg.norm(v)
        if norm > 0:
            v /= norm
            A[j:] -= 2.0 * np.outer(v, v @ A[j:])
        V[j, j:] = v
    return V, np.triu(A[:k])


class RigidNuisance:
    """The observation ``observation`` with a rigid-body nuisance marginalised exactly (eq 1
    of the module docstring): ``__call__(u)`` gives Q^T H u on the entries ``mask`` of the
    inner observation keeps (data masks included: give the data's mask, e.g. ``field.mask``),
    in the (points, dim) layout, zero elsewhere; ``mask`` is that mask minus the k rigid
    coordinates. Score data through ``data(y)``; ``rotation=False`` lets only translations float.

    A scene takes it as its observation (``bp.Scene(..., observation=RigidNuisance(obs, mask))``),
    so ``models.elastic_plate`` and the other Gaussian models marginalise the nuisance unchanged.
    """

    def __init__(self, observation: LinearObservation, mask=None, rotation: bool = True):
        self.inner = observation
        self.points = observation.points
        keep = observation.mask if mask is None else np.asarray(mask)
        if keep.dtype != bool or keep.shape != self.points.shape:
            raise ValueError(f"mask must be boolean of shape {self.points.shape} (points, dim), got "
                             f"{keep.dtype} {keep.shape}: pass the data's mask, e.g. field.mask")
        keep = keep & observation.mask
        flat = np.flatnonzero(keep.reshape(-1))
        self.rotation, self.centre = rotation, self.points[keep.any(axis=1)].mean(axis=0) if keep.any() else 0.0
        R = rigid_modes(self.points, self.centre, rotation)
        R = R.reshape(-1, R.shape[-1])[flat]
        k = R.shape[1]
        if len(flat) <= k:
            raise ValueError(f"the mask keeps {len(flat)} observed entries; a rigid nuisance of {k} modes needs "
                             f"more than {k}: keep more points or pass rotation=False")
        V, T = _householder(R)
        scale = np.linalg.norm(R, axis=0)
        if np.any(np.abs(np.diag(T)) <= 1e-10 * scale):
            raise ValueError("the kept observation entries cannot tell the rigid modes apart (all points on one "
                             "line, or one component only): keep points spread in both directions and both "
                             "components, or pass rotation=False")
        self.k, self.T, self._flat = k, T, torch.as_tensor(flat)
        self._V = torch.as_tensor(V)
        self.mask = keep.copy()
        self.mask.reshape(-1)[flat[:k]] = False

    @property
    def n(self) -> int:
        return len(self.points)

    def _rotate(self, flat: torch.Tensor) -> torch.Tensor:
        """Q^T applied to the kept entries (m,)."""
        for v in self._V:
            flat = flat - 2.0 * v * (v @ flat)
        return flat

    def _layout(self, z: torch.Tensor) -> torch.Tensor:
        return torch.zeros(self.points.size, dtype=z.dtype).index_put((self._flat,), z).reshape(self.points.shape)

    def __call__(self, u: torch.Tensor) -> torch.Tensor:
        """Q^T H u in the (points, dim) layout (zero on the entries the mask drops)."""
        return self._layout(self._rotate(self.inner(u).reshape(-1)[self._flat]))

    def data(self, y) -> dict:
        """``{"y", "mask"}`` for a Gaussian model: Q^T y on the kept entries (NaN is allowed
        only where the mask drops an entry)."""
        y = np.asarray(y, dtype=float)
        if y.shape != self.points.shape:
            raise ValueError(f"y must have the shape of the observation {self.points.shape}, got {y.shape}")
        kept = y.reshape(-1)[self._flat.numpy()]
        if not np.all(np.isfinite(kept)):
            raise ValueError("y has NaN or inf on entries the mask keeps: build the nuisance with the data's "
                             "mask (e.g. RigidNuisance(obs, field.mask))")
        return model_data(self._layout(self._rotate(torch.as_tensor(kept))).numpy(), self.mask)

    def estimate(self, y, prediction=None) -> np.ndarray:
        """The least-squares rigid coordinates r (k,) of y - prediction (both (points, dim);
        prediction defaults to 0): r = T^-1 Q1^T (y - H u), the translations first."""
        y = np.asarray(y, dtype=float) - (0.0 if prediction is None else np.asarray(prediction, dtype=float))
        z = self._rotate(torch.as_tensor(y.reshape(-1)[self._flat.numpy()])).numpy()
        return np.linalg.solve(self.T, z[:self.k])

    def motion(self, r) -> np.ndarray:
        """The rigid field R r (points, dim) at the observation points (zero off the kept entries)."""
        R = rigid_modes(self.points, self.centre, self.rotation)
        keep = np.zeros(self.points.size, dtype=bool)
        keep[self._flat.numpy()] = True
        return np.where(keep.reshape(self.points.shape), R @ np.asarray(r, dtype=float), 0.0)

    def matrix(self, n_particles: int) -> sp.csr_matrix:
        """Q^T H (rows in the (points, dim) layout, zero off the kept entries), for
        ``Scene.observation_matrix``; dense in the kept rows of the observed particles' dofs."""
        H = self.inner.matrix(n_particles)[self._flat.numpy()]
        for v in self._V.numpy():
            H = H - sp.csr_matrix(2.0 * v[:, None]) @ sp.csr_matrix(v[None, :] @ H)
        rows = sp.csr_matrix((np.ones(len(self._flat)), (self._flat.numpy(), np.arange(len(self._flat)))),
                             shape=(self.points.size, len(self._flat)))
        return (rows @ H).tocsr()
