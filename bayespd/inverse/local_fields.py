"""Default virtual fields for the local virtual work (``vfm_local``): a harmonic load field and
bilinear hats, kept off the supports, the loads and the boundaries the grid cuts (holes).

Where the weak form is exact and where not (measured, docs/results.md "VFM"): on a grid the
particles' cells tile a body whose edges are grid lines exactly, so the weak form is
second-order accurate up to a straight edge; a curved boundary (a hole) is a staircase of cells
and the data near supports and loads (patch corners, where the FE field is singular) are poorly
differentiated. Virtual strains are therefore kept ``margin`` away from constrained and loaded
particles and from *rough* boundary particles (:func:`rough_boundary`):

* the load field u*_0 = s d (d the unit total load) with s the discrete harmonic function on the
  grid's 4-neighbour graph that is 0 within ``margin`` of every constrained particle, 1 within
  ``margin`` of every loaded one and constant (free) on each connected zone within ``margin``
  of a rough boundary: W*_ext = |F|, its strain is spread as evenly as the geometry allows
  (least Dirichlet energy) and vanishes where the data cannot be trusted;
* hats prod_a max(0, 1 - |x_a - c_a| / size) e_k on a grid of nodes ``size`` apart, each kept
  when no constrained, loaded or rough particle lies within ``margin`` of its support: a basis
  of piecewise-bilinear fields in which ``vfm_noise``'s weighted least squares finds the
  noise-optimal combination (Avril, Grédiac & Pierron 2004's piecewise virtual fields).

Particles without data (gaps in a DIC field) are avoided like a rough boundary.
"""
from __future__ import annotations

import itertools

import numpy as np
import scipy.sparse as sp
import scipy.sparse.csgraph as csgraph
import scipy.sparse.linalg as spla
from scipy.spatial import cKDTree

from bayespd.inverse.vfm_local import neighbours
from bayespd.validate import positive


def rough_boundary(particles) -> np.ndarray:
    """(N,) True where a particle misses a grid neighbour (of the 3^dim - 1) in a pattern that is
    not a union of whole sides of its stencil, i.e. where the body's boundary is not a grid line
    (a hole's staircase), so the cells do not tile the body there."""
    dim = particles.dim
    at = neighbours(particles)
    offsets = [o for o in itertools.product((-1, 0, 1), repeat=dim) if any(o)]
    missing = np.stack([at(o) < 0 for o in offsets], 1)  # (N, 3^dim - 1)
    sides = [np.array([o[a] == s for o in offsets]) for a in range(dim) for s in (-1, 1)]
    straight = {tuple(np.any([sides[k] for k in ks], axis=0)) if ks else (False,) * len(offsets)
                for r in range(len(sides) + 1) for ks in itertools.combinations(range(len(sides)), r)}
    return np.array([tuple(row) not in straight for row in missing])


def _busy(scene, unmeasured=None):
    """(constrained, loaded, avoided) particle masks; avoided: rough boundary or ``unmeasured``."""
    loaded = np.abs(scene.force.numpy()).sum(1) > 0
    fixed = scene.constraints.fixed_particles
    if not fixed.any() or not loaded.any() or not np.any(scene.force.numpy().sum(0)):
        raise ValueError("the default VFM fields need a scene with Dirichlet particles and a "
                         "non-zero total load: pass fields= for displacement-controlled scenes")
    avoided = rough_boundary(scene.particles)
    if unmeasured is not None:
        avoided = avoided | (np.asarray(unmeasured, bool) & ~fixed)
    return fixed, loaded, avoided


def _at_particles(x_particles, values, h):
    """A field callable that returns ``values`` (N, dim) at the particles' positions."""
    tree = cKDTree(x_particles)

    def u(x):
        dist, k = tree.query(np.asarray(x, dtype=float))
        if dist.max() > 1e-6 * h:
            raise ValueError("this virtual field is defined at the scene's particles only")
        return values[k]

    return u


def harmonic_load_field(scene, margin: float, unmeasured=None):
    """u*_0 = s d of the module docstring, as a callable at the scene's particles; particles
    marked ``unmeasured`` (N,) are avoided like a rough boundary."""
    p = scene.particles
    x, n = p.x, p.n
    fixed, loaded, rough = _busy(scene, unmeasured)
    near = [cKDTree(x[m]).query(x)[0] <= margin if m.any() else np.zeros(n, bool) for m in (fixed, loaded, rough)]
    zero, one, free_zone = near
    if np.any(zero & one):
        raise ValueError(f"margin {margin:g} joins the supports and the loads: no load field fits; pass a smaller margin=")
    free_zone &= ~(zero | one)
    at = neighbours(p)
    edges = np.concatenate([np.stack([np.arange(n), at(e)], 1) for e in np.eye(p.dim, dtype=int)])
    edges = edges[edges[:, 1] >= 0]
    # every node's unknown: its own, or one per connected rough zone
    unknown = np.full(n, -1)
    zone_graph = sp.coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n, n))
    zones = csgraph.connected_components(zone_graph.tocsr()[free_zone][:, free_zone], directed=False)[1]
    free = ~(zero | one | free_zone)
    unknown[free] = np.arange(free.sum())
    unknown[free_zone] = free.sum() + zones
    m = int(unknown.max()) + 1
    value = np.where(one, 1.0, 0.0)
    ends = np.concatenate([edges, edges[:, ::-1]])  # each edge seen from both ends (row, other)
    row, col = unknown[ends[:, 0]], unknown[ends[:, 1]]
    coupled = (row >= 0) & (row != col)  # an unknown's edge to a fixed value or another unknown
    ends, row, col = ends[coupled], row[coupled], col[coupled]
    inner = col >= 0
    L = sp.csr_matrix((np.concatenate([np.ones(len(row)), -np.ones(inner.sum())]),
                       (np.concatenate([row, row[inner]]), np.concatenate([row, col[inner]]))), shape=(m, m))
    rhs = np.bincount(row[~inner], weights=value[ends[~inner, 1]], minlength=m)
    s = value.copy()
    s[unknown >= 0] = spla.spsolve(L, rhs)[unknown[unknown >= 0]]
    total = scene.force.numpy().sum(0)
    return _at_particles(x, s[:, None] * (total / np.linalg.norm(total))[None, :], p.h)


def hat_fields(scene, size: float, margin: float, unmeasured=None) -> list:
    """The hats of the module docstring (one per kept node and component), also kept off the
    particles marked ``unmeasured``."""
    p = scene.particles
    positive("size", size, "give the hats' node spacing")
    fixed, loaded, rough = _busy(scene, unmeasured)
    avoid = cKDTree(p.x[fixed | loaded | rough])
    lo, hi = p.lower(), p.upper()
    axes = [np.arange(lo[a], hi[a] + size, size) for a in range(p.dim)]
    fields = []
    for c in itertools.product(*axes):
        c = np.asarray(c)
        support = np.all(np.abs(p.x - c) < size, axis=1)
        if support.sum() < 2 ** p.dim or avoid.query(p.x[support])[0].min() <= margin:
            continue
        fields += [_hat(c, size, k) for k in range(p.dim)]
    return fields


def _hat(centre, size, component):
    def u(x):
        out = np.zeros_like(np.asarray(x, dtype=float))
        out[:, component] = np.prod(np.maximum(0.0, 1 - np.abs(np.asarray(x) - centre) / size), axis=1)
        return out

    return u


def local_fields(scene, margin: float | None = None, size: float | None = None, unmeasured=None) -> list:
    """[harmonic load field] + hats (module docstring); defaults margin = 4 h, size = 8 h;
    ``unmeasured`` (N,): particles without data (DIC gaps), avoided like a hole's staircase."""
    h = scene.particles.h
    margin = 4 * h if margin is None else positive("margin", margin, "give a distance")
    size = 8 * h if size is None else size
    return [harmonic_load_field(scene, margin, unmeasured)] + hat_fields(scene, size, margin, unmeasured)
