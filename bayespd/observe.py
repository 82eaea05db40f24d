"""Observation operators: displacements interpolated linearly at points inside the body."""
from __future__ import annotations

import numpy as np
import torch
from scipy.spatial import Delaunay, cKDTree

from bayespd.discretize import Particles


def locate(particles: Particles, points: np.ndarray):
    """Barycentric interpolation data (vertices, weights) of each point, and which points lie
    outside the body: off the triangulation or in a simplex with an edge longer than 1.9 h
    (a hole or a notch). A point on a particle observes that particle alone."""
    distance, nearest = cKDTree(particles.x).query(points)
    vertices = np.repeat(nearest[:, None], particles.dim + 1, axis=1)
    weights = np.zeros(vertices.shape)
    weights[:, 0] = 1.0
    outside = np.zeros(len(points), dtype=bool)
    between = np.flatnonzero(distance >= 1e-9 * particles.h)
    if len(between):
        tri = Delaunay(particles.x)
        simplex = tri.find_simplex(points[between], tol=1e-10)
        v = tri.simplices[np.maximum(simplex, 0)]
        corners = particles.x[v]
        edges = np.linalg.norm(corners[:, :, None] - corners[:, None, :], axis=-1).max(axis=(1, 2))
        outside[between] = (simplex < 0) | (edges > 1.9 * particles.h)
        T = tri.transform[simplex]
        b = np.einsum("pij,pj->pi", T[:, :-1], points[between] - T[:, -1])
        vertices[between] = v
        weights[between] = np.concatenate([b, 1 - b.sum(1, keepdims=True)], axis=1)
    return vertices, weights, outside


class Observation:
    """u at ``points`` by linear (barycentric) interpolation on a Delaunay triangulation of
    the particles. Points outside the body (see :func:`locate`) are refused.
    """

    def __init__(self, particles: Particles, points):
        points = np.atleast_2d(np.asarray(points, dtype=float))
        if points.shape[1] != particles.dim:
            raise ValueError(f"points must have {particles.dim} coordinates")
        if not np.all(np.isfinite(points)):
            raise ValueError("observation points contain NaN or inf")
        vertices, weights, outside = locate(particles, points)
        if outside.any():
            k = int(np.flatnonzero(outside)[0])
            raise ValueError(f"{int(outside.sum())} observation point(s) lie outside the body, "
                             f"e.g. {points[k].tolist()}: drop them (see observe.locate) or mask them out")
        self.points = points
        self._index = torch.as_tensor(vertices)
        self._weights = torch.as_tensor(weights)

    @property
    def n(self) -> int:
        return len(self.points)

    def __call__(self, u: torch.Tensor) -> torch.Tensor:
        """Observed displacements (n_points, dim) of a field u (N, dim)."""
        return (self._weights[..., None] * u[self._index]).sum(1)
