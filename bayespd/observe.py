"""Observation operators y = H u and masks of the observations to keep.

Every operator is linear: each observed point is a fixed weighted sum of particle
displacements. :class:`Observation` interpolates barycentrically at points inside the body,
:class:`ParticleObservation` observes particles exactly, :class:`GridObservation`
interpolates bilinearly from a particle lattice (what DIC grids need).

Masks are numpy boolean arrays shaped like the observations, ``(n_points, dim)``, True where
observed: the shape the Pyro models' ``mask`` argument takes. They combine with ``&``; pass
data and mask through :func:`model_data` before fitting.
"""
from __future__ import annotations

import itertools

import numpy as np
import scipy.sparse as sp
import torch
from scipy.spatial import Delaunay, cKDTree

from bayespd.discretize import Particles
from bayespd.validate import numbers, finite, in_range, positive


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


def _points(particles: Particles, points) -> np.ndarray:
    points = np.atleast_2d(numbers(points, "the observation points"))
    if points.ndim != 2 or points.shape[1] != particles.dim:
        raise ValueError(f"points must be (n, {particles.dim}), got shape {points.shape}")
    if len(points) == 0:
        raise ValueError("the observation has no points: give at least one (n, dim) point")
    return finite("the observation points", points, "drop them before building the operator")


class LinearObservation:
    """y_p = sum_k w_pk u[i_pk] at ``points`` (n, dim), with ``index`` i and ``weights`` w of shape
    (n, k); ``mask`` (n, dim) marks what is observed."""

    def __init__(self, points: np.ndarray, index: np.ndarray, weights: np.ndarray, mask=None):
        self.points = points
        self.mask = np.ones(points.shape, dtype=bool) if mask is None else mask
        self.index = torch.as_tensor(index)
        self.weights = torch.as_tensor(weights)

    @property
    def n(self) -> int:
        return len(self.points)

    def __call__(self, u: torch.Tensor) -> torch.Tensor:
        """Observed displacements (n_points, dim) of a field u (N, dim)."""
        return (self.weights[..., None] * u[self.index]).sum(1)

    def matrix(self, n_particles: int) -> sp.csr_matrix:
        """H as a sparse (n_points * dim, n_particles * dim) matrix on the flattened
        (point-major) observations and dofs, duplicates summed, zeros dropped."""
        dim = self.points.shape[1]
        index, weights = self.index.numpy(), self.weights.numpy()
        rows = (np.arange(self.n)[:, None, None] * dim + np.arange(dim)).repeat(index.shape[1], 1)
        cols = index[:, :, None] * dim + np.arange(dim)
        vals = np.broadcast_to(weights[:, :, None], rows.shape)
        H = sp.csr_matrix((vals.ravel(), (rows.ravel(), cols.ravel())), shape=(self.n * dim, n_particles * dim))
        H.eliminate_zeros()
        return H


class Observation(LinearObservation):
    """u at ``points`` by linear (barycentric) interpolation on a Delaunay triangulation of
    the particles; works for any particle set. Points outside the body (see :func:`locate`)
    are refused.
    """

    def __init__(self, particles: Particles, points):
        points = _points(particles, points)
        vertices, weights, outside = locate(particles, points)
        if outside.any():
            k = int(np.flatnonzero(outside)[0])
            raise ValueError(f"{int(outside.sum())} observation point(s) lie outside the body, "
                             f"e.g. {points[k].tolist()}: drop them (see observe.locate) or mask them out")
        super().__init__(points, vertices, weights)


class ParticleObservation(LinearObservation):
    """u at a subset of the particles, exactly: ``which`` is a boolean mask (N,) or indices."""

    def __init__(self, particles: Particles, which):
        which = np.asarray(which)
        if which.dtype == bool:
            if which.shape != (particles.n,):
                raise ValueError(f"a boolean mask needs one entry per particle ({particles.n}), got {which.shape}")
            which = np.flatnonzero(which)
        if which.ndim != 1 or len(which) == 0 or not np.issubdtype(which.dtype, np.integer):
            raise ValueError("give a non-empty boolean mask over the particles or a list of particle indices")
        if which.min() < 0 or which.max() >= particles.n:
            raise ValueError(f"particle indices must lie in [0, {particles.n})")
        if len(np.unique(which)) < len(which):
            raise ValueError("repeated particle indices would count those observations twice: drop the repeats")
        super().__init__(particles.x[which], which[:, None], np.ones((len(which), 1)))


class OpeningObservation(LinearObservation):
    """Crack openings u(above_p) - u(below_p) at stations p (the aperture of Turner 2015 eq 28),
    each face by barycentric interpolation. ``component`` keeps one component in the mask
    (e.g. 1: the y opening of a crack along x); None keeps all."""

    def __init__(self, particles: Particles, above, below, component: int | None = None):
        above, below = np.asarray(above, dtype=float), np.asarray(below, dtype=float)
        if above.shape != below.shape or above.ndim != 2 or len(above) == 0:
            raise ValueError(f"above and below must be matching non-empty (n, dim) point arrays, "
                             f"got shapes {above.shape} and {below.shape}")
        top, bottom = Observation(particles, above), Observation(particles, below)
        mask = np.ones(above.shape, dtype=bool)
        if component is not None:
            if not 0 <= component < particles.dim:
                raise ValueError(f"component must be in [0, {particles.dim}), got {component}")
            mask[:] = False
            mask[:, component] = True
        super().__init__((above + below) / 2, torch.cat([top.index, bottom.index], 1),
                         torch.cat([top.weights, -bottom.weights], 1), mask)


class _Lattice:
    """Particles on a regular lattice of spacing h: a table from integer lattice nodes to
    particle indices, -1 where a node has no particle (a hole, a notch, outside)."""

    def __init__(self, particles: Particles):
        self.h, self.origin = particles.h, particles.x.min(axis=0)
        s = (particles.x - self.origin) / self.h
        nodes = np.rint(s).astype(int)
        if np.abs(s - nodes).max() > 1e-6:
            raise ValueError(f"the particles do not lie on a regular grid of spacing h={self.h:g}: for an "
                             "irregular particle set use the barycentric bp.Observation(particles, points)")
        self.shape = nodes.max(axis=0) + 1
        self.table = np.full(self.shape, -1)
        self.table[tuple(nodes.T)] = np.arange(particles.n)

    def coordinates(self, points: np.ndarray) -> np.ndarray:
        """Points in lattice units, snapped to nodes within 1e-9 (so a point on a particle is exact)."""
        s = (points - self.origin) / self.h
        return np.where(np.abs(s - np.rint(s)) < 1e-9, np.rint(s), s)

    def lookup(self, nodes: np.ndarray) -> np.ndarray:
        """Particle index at integer nodes (..., dim); -1 off the lattice or at an empty node."""
        inside = np.all((nodes >= 0) & (nodes < self.shape), axis=-1)
        found = np.full(nodes.shape[:-1], -1)
        found[inside] = self.table[tuple(nodes[inside].T)]
        return found


class GridObservation(LinearObservation):
    """u at ``points`` by bilinear (trilinear in 3D) interpolation from the 2^dim particles
    around each point, for particles on a regular grid (holes and notches allowed): exact for
    fields a + b x + c y + d x y.

    A point whose interpolation needs a missing particle (in or next to a hole or notch,
    between the outer particles and the edge, outside) is kept but masked: it observes 0 and
    ``mask`` is False on its row. Combine ``mask`` with the data's masks before fitting.
    """

    def __init__(self, particles: Particles, points):
        points = _points(particles, points)
        lattice = _Lattice(particles)
        s = lattice.coordinates(points)
        base = np.floor(s).astype(int)
        t = s - base
        corners = np.array(list(itertools.product((0, 1), repeat=particles.dim)))
        index = lattice.lookup(base[:, None, :] + corners)
        weights = np.prod(np.where(corners, t[:, None, :], 1 - t[:, None, :]), axis=-1)
        valid = np.all((index >= 0) | (weights == 0), axis=1)
        if not valid.any():
            raise ValueError(f"none of the {len(points)} points can be interpolated from the particles "
                             "(each is outside the body or next to a hole or edge): check their units "
                             "and origin, or use bp.Observation")
        weights[~valid] = 0.0
        index[index < 0] = 0  # with weight 0
        super().__init__(points, index, weights, np.repeat(valid[:, None], particles.dim, axis=1))


def grid_points(origin, spacing, counts) -> np.ndarray:
    """A regular grid of points, as DIC software reports them: ``counts`` points per axis
    (x, y[, z]) from ``origin`` with ``spacing`` (scalar or per axis); x varies fastest, so
    ``values.reshape(*reversed(counts), -1)`` is an image of rows."""
    origin = finite("origin", np.asarray(origin, float), "pass the position of the first point")
    counts = np.asarray(counts)
    spacing = positive("spacing", np.asarray(spacing, float), "pass a finite positive spacing per axis")
    spacing = np.broadcast_to(spacing, origin.shape)
    if counts.shape != origin.shape or np.any(counts < 1):
        raise ValueError("grid_points needs one count (>= 1) per axis of origin")
    axes = [o + d * np.arange(c) for o, d, c in zip(origin, spacing, counts)]
    return np.stack(np.meshgrid(*axes, indexing="xy"), axis=-1).reshape(-1, len(origin))


def edge_mask(particles: Particles, points, width: float) -> np.ndarray:
    """Mask (n, dim) of the points at least ``width`` inside the body: DIC loses data near the
    free edges, and Delorme 2018 (Fig. 9, Table 4) drops bands of width k h along every edge.

    The body is the union of the particles' cells (squares or cubes of side h on a regular
    grid), so holes and notches have edges too; points outside the body are dropped.
    """
    points = _points(particles, points)
    in_range("width", width, 0.0, np.inf, "pass the band to drop along the edges, >= 0", closed=(True, False))
    lattice = _Lattice(particles)
    nearest = np.rint(lattice.coordinates(points)).astype(int)
    reach = int(np.ceil(width / lattice.h)) + 1  # farther empty cells are >= width away
    keep = np.ones(len(points), dtype=bool)
    for offset in itertools.product(range(-reach, reach + 1), repeat=particles.dim):
        node = nearest + np.array(offset)
        empty = lattice.lookup(node) < 0
        centre = lattice.origin + lattice.h * node
        gap = np.linalg.norm(np.maximum(np.abs(points - centre) - lattice.h / 2, 0.0), axis=1)
        keep &= ~(empty & (gap < max(width, 1e-9 * lattice.h)))  # width 0 still drops outside points
    return np.repeat(keep[:, None], particles.dim, axis=1)


def finite_mask(y) -> np.ndarray:
    """Mask of the finite entries of data y (n, dim): NaN or inf marks missing data."""
    return np.isfinite(np.asarray(y, dtype=float))


def model_data(y, mask=None) -> dict:
    """``{"y", "mask"}`` for a Pyro model's ``(y, mask)``: ``mask`` (n, dim) combined with
    :func:`finite_mask`, and y set to 0 where masked (a NaN would poison gradients even there)."""
    keep = finite_mask(y)
    if mask is not None:
        mask = np.asarray(mask)
        if mask.dtype != bool or mask.shape != keep.shape:
            raise ValueError(f"mask must be boolean with the shape of y {keep.shape}, got {mask.dtype} {mask.shape}")
        keep &= mask
    keep = torch.as_tensor(keep)
    y = torch.as_tensor(np.asarray(y, dtype=float))
    return {"y": torch.where(keep, y, torch.zeros(())), "mask": keep}
