"""Observation operators: displacements interpolated linearly at points inside the body."""
from __future__ import annotations

import numpy as np
import torch
from scipy.spatial import Delaunay

from bayespd.discretize import Particles


class Observation:
    """u at ``points`` by linear (barycentric) interpolation on a Delaunay triangulation of
    the particles. A point that coincides with a particle observes that particle exactly.

    Points outside the body, or in a hole or notch (inside a simplex with an edge longer than
    1.9 h), are refused.
    """

    def __init__(self, particles: Particles, points):
        points = np.atleast_2d(np.asarray(points, dtype=float))
        if points.shape[1] != particles.dim:
            raise ValueError(f"points must have {particles.dim} coordinates")
        if not np.all(np.isfinite(points)):
            raise ValueError("observation points contain NaN or inf")
        tri = Delaunay(particles.x)
        simplex = tri.find_simplex(points, tol=1e-10)
        vertices = tri.simplices[np.maximum(simplex, 0)]
        corners = particles.x[vertices]
        edges = np.linalg.norm(corners[:, :, None] - corners[:, None, :], axis=-1).max(axis=(1, 2))
        outside = (simplex < 0) | (edges > 1.9 * particles.h)
        if outside.any():
            k = int(np.flatnonzero(outside)[0])
            raise ValueError(f"{int(outside.sum())} observation point(s) lie outside the body, "
                             f"e.g. {points[k].tolist()}: drop them or mask them out")
        T = tri.transform[simplex]
        b = np.einsum("pij,pj->pi", T[:, :-1], points - T[:, -1])
        weights = np.concatenate([b, 1 - b.sum(1, keepdims=True)], axis=1)
        self.points = points
        self._index = torch.as_tensor(vertices)
        self._weights = torch.as_tensor(weights)

    @property
    def n(self) -> int:
        return len(self.points)

    def __call__(self, u: torch.Tensor) -> torch.Tensor:
        """Observed displacements (n_points, dim) of a field u (N, dim)."""
        return (self._weights[..., None] * u[self._index]).sum(1)
