"""Particles from a finite-element mesh (any format meshio reads): one particle per cell at
its centroid, with the cell's volume (area x thickness in 2D).

Triangles and tetrahedra are affine, so centroid and volume are closed-form. Quads and
hexahedra are taken as bilinear / trilinear cells: det J is of degree <= 2 per reference
coordinate and x det J of degree <= 3, so 2-point Gauss quadrature per axis gives their
volume and centroid exactly, and neighbours share the same bilinear faces, so the volumes
tile the body exactly even when faces are warped.
"""
from __future__ import annotations

import itertools
import math
import numpy as np

from bayespd.discretize import Particles, from_points
from bayespd.validate import readable_file, reading

SUPPORTED = {2: ("triangle", "quad"), 3: ("tetra", "hexahedron")}
LOWER = {2: ("vertex", "line"), 3: ("vertex", "line", "triangle", "quad", "polygon")}  # boundary entities
CORNERS = {  # reference corners of quad and hexahedron in VTK / meshio node order
    "quad": [(0, 0), (1, 0), (1, 1), (0, 1)],
    "hexahedron": [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0), (0, 0, 1), (1, 0, 1), (1, 1, 1), (0, 1, 1)],
}


def _simplices(x: np.ndarray):
    """Centroids and volumes of simplices x (m, d+1, d): |det(edges)| / d!."""
    d = x.shape[2]
    return x.mean(axis=1), np.abs(np.linalg.det(x[:, 1:] - x[:, :1])) / math.factorial(d)


def _multilinear(x: np.ndarray, corners: np.ndarray):
    """Centroids and volumes of bilinear / trilinear cells x (m, 2^d, d) by 2^d Gauss points."""
    g = 0.5 + np.array([-0.5, 0.5]) / math.sqrt(3.0)  # weights 1/2 each on [0, 1]
    moment, volume = 0.0, 0.0
    for xi in itertools.product(g, repeat=corners.shape[1]):
        factors = np.where(corners, xi, 1 - np.asarray(xi))  # (2^d, d): xi_i or 1 - xi_i
        shape = factors.prod(axis=1)
        dshape = np.stack([np.where(corners[:, i], 1.0, -1.0) * np.prod(np.delete(factors, i, axis=1), axis=1)
                           for i in range(corners.shape[1])], axis=1)  # dN_a / dxi_i
        det = np.linalg.det(np.einsum("mad,ai->mdi", x, dshape)) / 2 ** corners.shape[1]
        volume = volume + det
        moment = moment + det[:, None] * np.einsum("mad,a->md", x, shape)
    return moment / volume[:, None], np.abs(volume)


def from_mesh(path, thickness: float = 1.0, h: float | None = None) -> Particles:
    """Particles at the cells of the mesh in ``path`` (read with meshio: .msh, .vtu, .inp, ...).

    A mesh whose z coordinates are all equal is 2D (triangles, quads; volume = area x
    ``thickness``), otherwise 3D (tetrahedra, hexahedra); lower-dimensional cells (boundary
    lines and faces) are ignored. ``h`` defaults as in :func:`bayespd.from_points`.
    """
    try:
        import meshio
    except ImportError as error:
        raise ImportError("from_mesh reads meshes with meshio: pip install bayespd[mesh]") from error
    path = readable_file(path, "mesh file")
    with reading(path, "a mesh", "pass a complete mesh file in a format meshio reads (.msh, .vtu, .inp, ...)"):
        mesh = meshio.read(path)
    points = mesh.points
    flat = points.shape[1] == 2 or np.ptp(points[:, 2]) == 0
    dim = 2 if flat else 3
    points = points[:, :dim]
    kinds = sorted({block.type for block in mesh.cells})
    unsupported = [k for k in kinds if k not in SUPPORTED[dim] and not k.startswith(LOWER[dim])]
    if unsupported or not set(kinds) & set(SUPPORTED[dim]):
        raise ValueError(f"{path.name} is a {dim}D mesh with cells {kinds}: from_mesh reads triangle and quad "
                         "cells of a flat (z constant) mesh and tetra and hexahedron cells of a 3D mesh; "
                         "re-mesh or convert the other cells")
    centroids, volumes = [], []
    for block in mesh.cells:
        if block.type in SUPPORTED[dim]:
            if block.data.size and not 0 <= block.data.min() <= block.data.max() < len(points):
                raise ValueError(f"{path}: a {block.type} cell refers to a node outside 0..{len(points) - 1} "
                                 "(a damaged file?): re-export the mesh")
            x = points[block.data]
            c, v = _multilinear(x, np.array(CORNERS[block.type])) if block.type in CORNERS else _simplices(x)
            centroids.append(c)
            volumes.append(v)
    volume = np.concatenate(volumes) * (thickness if dim == 2 else 1.0)
    return from_points(np.concatenate(centroids), volume, h, thickness if dim == 2 else 1.0)
