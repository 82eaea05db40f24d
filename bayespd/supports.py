"""Supports and loads from a test's description: point supports, rollers, point loads and
edge tractions, as the ``Dirichlet`` and ``Load`` a ``Scene`` takes.

**Layer or not.** A peridynamic particle feels every particle within the horizon, so a
displacement prescribed on one column acts on the body only through the bonds that reach it:
the particles within delta of the column move on their own (a nonlocal boundary layer), and on
a cell-centred grid the column sits h/2 inside the edge, so a clamp meant for the edge leaves a
u_x offset of strain x h/2 against an FE field that is zero there. To impose a displacement on an
edge (a grip, a clamp), fix a layer at least one horizon thick (``Dirichlet.layer(p, side,
depth >= delta)``, Delorme 2018 §3.1). A point support or a roller on a few particles is right
where the support only removes rigid-body motion or stands for a contact of small extent (the
rollers of a bending test): there the local field is not what is calibrated. A symmetry plane
is neither: use ``bayespd.symmetry.SymmetryPlane``.

Loads are body forces spread over particles by volume (``Load``), so their total is exact: a
point load over the particles within ``radius``, a traction t on an edge as the force t x edge
length x thickness (2D; t x face area in 3D) over a layer along it (a traction enters a
peridynamic model as a body force on its outermost layer, as in Madenci & Oterkus's book).
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from bayespd.boundary import Dirichlet, Load
from bayespd.discretize import Particles
from bayespd.validate import numbers, count, finite, positive

SIDES = {"left": (0, 0), "right": (0, 1), "bottom": (1, 0), "top": (1, 1), "front": (2, 0), "back": (2, 1)}


def _point(particles: Particles, point, name: str) -> np.ndarray:
    point = finite(name, numbers(point, name), "pass a finite position")
    if point.shape != (particles.dim,):
        raise ValueError(f"{name} must have {particles.dim} coordinates, got shape {point.shape}")
    return point


def _nearest(particles: Particles, point, name: str) -> int:
    """The particle nearest ``point``; refused when none lies within h (the point is outside)."""
    distance, k = cKDTree(particles.x).query(_point(particles, point, name))
    if distance > particles.h:
        raise ValueError(f"{name} {np.asarray(point).tolist()} is {distance:g} from the nearest particle (> h = "
                         f"{particles.h:g}): it lies outside the body; check its units and origin")
    return int(k)


def point_support(particles: Particles, point, value=(0.0, 0.0)) -> Dirichlet:
    """Fix the particle nearest ``point`` at ``value`` (one entry per component, None: free),
    e.g. to remove rigid-body motion; see the module docstring for when a layer is needed."""
    mask = np.zeros(particles.n, dtype=bool)
    mask[_nearest(particles, point, "the support point")] = True
    return Dirichlet(mask, value)


def roller(particles: Particles, mask, axis: int, value: float = 0.0) -> Dirichlet:
    """Fix component ``axis`` of the particles in ``mask`` at ``value``, the others free (a
    roller, or a symmetry condition on a line of particles lying on the plane)."""
    count("axis", axis, 0)
    if axis >= particles.dim:
        raise ValueError(f"axis must be < {particles.dim} (the component to fix), got {axis}")
    mask = np.asarray(mask)
    if mask.dtype != bool or mask.shape != (particles.n,):
        raise ValueError(f"mask must be boolean with one entry per particle ({particles.n}), got {mask.dtype} "
                         f"{mask.shape}: build it with particles.layer, .box or .region")
    finite("the roller value", value, "pass a finite displacement")
    return Dirichlet(mask, tuple(float(value) if a == axis else None for a in range(particles.dim)))


def point_load(particles: Particles, point, force, radius: float | None = None) -> Load:
    """The total ``force`` at ``point``, spread by volume over the particles within ``radius``
    (None: on the nearest particle alone, whose response then depends on h, as a point load's
    does in elasticity; a radius of about delta or the contact's half-width resolves it)."""
    if radius is None:
        mask = np.zeros(particles.n, dtype=bool)
        mask[_nearest(particles, point, "the load point")] = True
        return Load(mask, force)
    positive("radius", radius, "pass the radius to spread the load over (about delta), or None")
    mask = np.linalg.norm(particles.x - _point(particles, point, "the load point"), axis=1) <= radius
    if not mask.any():
        raise ValueError(f"no particle lies within radius={radius:g} of the load point {np.asarray(point).tolist()}: "
                         f"increase radius (h = {particles.h:g}) or check the point")
    return Load(mask, force)


def traction(particles: Particles, side: str, traction, depth: float | None = None) -> Load:
    """The traction ``traction`` (force per area, one entry per component) on the edge ``side``
    (left, right, bottom, top; front, back in 3D) of the bounding box: the total force t x the
    edge's length x thickness (the face's area in 3D), spread by volume over the layer
    ``depth`` thick along it (default h: the outermost column)."""
    if side not in SIDES or SIDES[side][0] >= particles.dim:
        raise ValueError(f"side must be one of {list(SIDES)[: 2 * particles.dim]}, got {side!r}")
    t = finite("the traction", numbers(traction, "the traction"), "pass a finite force per area")
    if t.shape != (particles.dim,):
        raise ValueError(f"the traction must have {particles.dim} components, got shape {t.shape}")
    depth = particles.h if depth is None else positive("depth", depth, "pass the layer thickness (>= h)")
    extent = particles.upper() - particles.lower()
    normal = SIDES[side][0]
    area = np.prod(np.delete(extent, normal)) * (particles.thickness if particles.dim == 2 else 1.0)
    return Load(particles.layer(side, depth), t * area)
