"""A measured displacement field (DIC subsets, FE nodes) mapped onto particles in one call:
the particles, the observation operator at the measured points, the data and the masks.

**Index order.** A gridded field is given by coordinate vectors ``x`` (nx,), ``y`` (ny,) and
component arrays in one of two layouts, named as numpy.meshgrid names them:

* ``order="xy"``: arrays of shape (ny, nx), ``a[iy, ix]`` at (x[ix], y[iy]): rows are y, as
  ``numpy.meshgrid(x, y)`` and images give them;
* ``order="ij"``: arrays of shape (nx, ny), ``a[ix, iy]``: ``numpy.meshgrid(x, y, indexing="ij")``.

An ``xarray.DataArray`` with dims named "x" and "y" carries its order. Without ``order`` the
layout is read from a non-square shape; a square grid (nx = ny) without it is refused, since
its shape cannot tell a transposed field. Points are listed x fastest, as ``bp.grid_points``:
point k lies at (x[k % nx], y[k // nx]).

**Particles.** With ``particles=None`` every node of the measured lattice is a particle
(node-centred: the cell of volume h^2 t around each measured point, so the body reaches h/2
beyond the outer points) and each point observes its particle exactly (H a selection). This is
the default because the measurement fixes the spacing (Delorme 2018 §4.1: "the nodal spacing h
is more or less prescribed by the measuring equipment"), because the data then carry no
interpolation error and because the VFM needs a measured value on every particle. A node whose
correlation failed stays a particle (missing data, not missing material); ``body`` removes the
nodes that are not material (holes, notches). With ``particles=`` (e.g. ``bp.grid_2d`` of the
specimen at a coarser h, or points not on a regular lattice such as VIC-3D's metric
coordinates) the observation interpolates at the measured points: bilinear on a lattice
(``GridObservation``), barycentric otherwise, points the body cannot interpolate masked.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.spatial import cKDTree

from bayespd.discretize import Particles
from bayespd.observe import GridObservation, LinearObservation, edge_mask, locate, model_data
from bayespd.validate import numbers, finite, in_range, positive

LATTICE_TOL = 1e-3  # points within this fraction of h of a lattice node lie on it


@dataclass(frozen=True)
class Field:
    """A measured field on particles: ``observation`` (H at the n measured points), ``y`` (n, dim)
    measured displacements (NaN where missing), ``valid`` (n, dim) True where measured and
    observable, ``edge`` (n, dim) True at least ``edge`` width inside the body, ``sigma`` (n,)
    the measurement's own std. dev. estimate (NaN where absent) and ``shape`` (ny, nx) of a
    gridded input (None for scattered points)."""

    particles: Particles
    observation: LinearObservation
    y: np.ndarray
    valid: np.ndarray
    edge: np.ndarray
    sigma: np.ndarray
    shape: tuple | None = None

    @property
    def points(self) -> np.ndarray:
        return self.observation.points

    @property
    def mask(self) -> np.ndarray:
        """The entries to fit: valid and away from the edges."""
        return self.valid & self.edge

    def on_particles(self) -> np.ndarray:
        """The measured displacements per particle (particles.n, dim), NaN where not measured: the
        VFM's input (``vfm_defaults.estimate(scene, u)``). Needs each point to observe one particle,
        as the particles at the nodes (``particles=None``) do."""
        index = self.observation.index.numpy()
        if index.shape[1] != 1:
            raise ValueError("the measured points interpolate the particles (particles= was given), so no particle "
                             "has a measured value of its own: read the field with particles=None (a particle at "
                             "every measured point)")
        u = np.full((self.particles.n, self.particles.dim), np.nan)
        rows = self.valid.any(axis=1)
        u[index[rows, 0]] = self.y[rows]
        return u

    def data(self) -> dict:
        """``{"y", "mask"}`` for a Pyro model (``bp.model_data(y, mask)``)."""
        return model_data(self.y, self.mask)

    def grid(self, values, order: str = "xy") -> np.ndarray:
        """Per-point ``values`` (n, ...) of a gridded field as an array (ny, nx, ...) for
        ``order="xy"`` or (nx, ny, ...) for ``"ij"``."""
        if self.shape is None:
            raise ValueError("this field was given as scattered points: it has no grid layout")
        grid = np.asarray(values).reshape(*self.shape, *np.shape(values)[1:])
        return grid if _order(order) == "xy" else grid.swapaxes(0, 1)


def _order(order: str) -> str:
    if order not in ("xy", "ij"):
        raise ValueError(f"order must be 'xy' (a[iy, ix], rows are y) or 'ij' (a[ix, iy]), got {order!r}")
    return order


def _layout(name: str, a, order, nx: int, ny: int) -> np.ndarray:
    """The array ``a`` of a grid (nx, ny) as (ny, nx), by ``order`` or by named dims."""
    dims = getattr(a, "dims", None)
    if dims is not None and set(dims) == {"x", "y"}:
        named = "xy" if tuple(dims) == ("y", "x") else "ij"
        if order is not None and _order(order) != named:
            raise ValueError(f"{name} has dims {tuple(dims)} (order {named!r}) but order={order!r}: drop order")
        order = named
    a = numbers(a, name)
    if order is None:
        if nx == ny:
            raise ValueError(f"{name} is a square {nx} x {ny} grid, so its shape cannot tell its index order: "
                             "pass order='xy' (a[iy, ix], rows are y, as numpy.meshgrid(x, y) and images) or "
                             "order='ij' (a[ix, iy])")
        order = "xy" if a.shape == (ny, nx) else "ij"
    expected = (ny, nx) if _order(order) == "xy" else (nx, ny)
    if a.shape != expected:
        raise ValueError(f"{name} has shape {a.shape} but order={order!r} with nx={nx}, ny={ny} needs {expected}"
                         + (": the array is transposed, pass the other order" if a.shape == expected[::-1] else ""))
    return a if order == "xy" else a.T


def _lattice(points: np.ndarray):
    """(origin, h, nodes) of points on a square lattice: nodes (n, dim) integer indices."""
    if len(points) < 2:
        raise ValueError("one measured point gives no lattice spacing: pass particles= to observe it")
    distance, _ = cKDTree(points).query(points, k=2)
    rough = float(np.median(distance[:, 1]))
    if not rough > 0:
        raise ValueError("two measured points coincide: drop the repeats")
    origin = points.min(axis=0)
    nodes = np.rint((points - origin) / rough).astype(int)
    spans = nodes.max(axis=0)
    h = np.array([(points[:, a] - origin[a]) @ nodes[:, a] / max(nodes[:, a] @ nodes[:, a], 1)
                  if spans[a] else rough for a in range(points.shape[1])])
    off = np.abs((points - origin) / h - nodes).max()
    if off > LATTICE_TOL or np.ptp(h) > LATTICE_TOL * h.min():
        raise ValueError(f"the measured points are not on a square lattice (spacings {h.tolist()}, a point "
                         f"{off:.2g} h off its node): pass particles= (e.g. bp.grid_2d of the specimen) to "
                         "interpolate the model at the measured points")
    if len(np.unique(nodes, axis=0)) < len(nodes):
        raise ValueError("two measured points fall on one lattice node: drop the repeats")
    return origin, float(h.mean()), nodes


def _at_nodes(points: np.ndarray, body, thickness: float):
    """Particles at the nodes of the points' lattice (those ``body`` keeps) and the
    observation selecting each point's particle (weight 0 and masked off the body)."""
    origin, h, nodes = _lattice(points)
    shape = nodes.max(axis=0) + 1
    grid = np.stack(np.meshgrid(*[np.arange(c) for c in shape], indexing="xy"), axis=-1).reshape(-1, len(shape))
    x = origin + h * grid
    keep = np.ones(len(x), dtype=bool) if body is None else np.asarray(body(x), dtype=bool)
    if keep.shape != (len(x),) or not keep.any():
        raise ValueError("body must be a predicate x (M, dim) -> M booleans keeping at least one lattice node")
    cell = h ** points.shape[1] * (thickness if points.shape[1] == 2 else 1.0)
    particles = Particles(x[keep], np.full(int(keep.sum()), cell), h, thickness)
    table = np.full(len(x), -1)
    table[keep] = np.arange(int(keep.sum()))
    index = table[np.ravel_multi_index(nodes.T[::-1], shape[::-1])]
    on = index >= 0
    observation = LinearObservation(origin + h * nodes, np.maximum(index, 0)[:, None], on[:, None].astype(float),
                                    np.repeat(on[:, None], points.shape[1], axis=1))
    return particles, observation


def _interpolated(particles: Particles, points: np.ndarray) -> LinearObservation:
    """Bilinear on a lattice, barycentric otherwise; points outside the body masked."""
    try:
        return GridObservation(particles, points)
    except ValueError as error:
        if "regular grid" not in str(error):
            raise
    vertices, weights, outside = locate(particles, points)
    weights[outside] = 0.0
    return LinearObservation(points, vertices, weights, np.repeat(~outside[:, None], particles.dim, axis=1))


def from_point_field(points, displacement, *, sigma=None, valid=None, particles: Particles | None = None,
                     body=None, thickness: float = 1.0, edge: float = 0.0) -> Field:
    """A field measured at ``points`` (n, dim), ``displacement`` (n, dim) (NaN in a component:
    the point is missing), as a
    :class:`Field` (see the module docstring for where the particles go). ``sigma`` (n,): the
    measurement's std. dev. (negative or NaN: a failed point, as DICe and VIC write it);
    ``valid`` (n,) or (n, dim): the user's own mask; ``edge``: drop points closer than this
    to an edge of the body (Delorme 2018 Table 4); ``body``: a predicate x -> bool of the
    lattice nodes that are material (``particles=None`` only)."""
    points = finite("points", numbers(points, "points"), "drop the rows without a position")
    if points.ndim != 2 or points.shape[1] not in (2, 3) or len(points) == 0:
        raise ValueError(f"points must be a non-empty (n, 2) or (n, 3) array, got shape {points.shape}")
    n, dim = points.shape
    y = numbers(displacement, "displacement")
    if y.shape != (n, dim):
        raise ValueError(f"displacement must be (n, dim) = {(n, dim)} like points, got {y.shape}")
    positive("thickness", thickness)
    in_range("edge", edge, 0.0, np.inf, "pass the band to drop along the edges, >= 0", closed=(True, False))
    given = sigma
    sigma = np.full(n, np.nan) if sigma is None else numbers(sigma, "sigma").reshape(-1)
    if sigma.shape != (n,):
        raise ValueError(f"sigma must have one value per point ({n}), got {sigma.shape}")
    ok = np.ones((n, dim), dtype=bool) if valid is None else np.asarray(valid)
    if ok.dtype != bool or ok.shape not in ((n,), (n, dim)):
        raise ValueError(f"valid must be boolean of shape ({n},) or ({n}, {dim}), got {ok.dtype} {ok.shape}")
    if particles is None:
        particles, observation = _at_nodes(points, body, thickness)
    else:
        if body is not None:
            raise ValueError("body selects lattice nodes as particles: with particles= given, cut the body "
                             "out of the particles (particles.where(...)) instead")
        if particles.dim != dim:
            raise ValueError(f"particles are {particles.dim}D but the points are {dim}D")
        observation = _interpolated(particles, points)
    measured = np.isfinite(y).all(axis=1, keepdims=True) & (True if given is None else (sigma >= 0)[:, None])
    valid = measured & (ok if ok.ndim == 2 else ok[:, None]) & observation.mask
    band = edge_mask(particles, observation.points, edge) if edge > 0 else np.ones((n, dim), dtype=bool)
    return Field(particles, observation, np.where(valid, y, np.nan), valid, band, sigma)


def from_grid_field(x, y, u, v, *, order: str | None = None, sigma=None, valid=None, **mapping) -> Field:
    """A 2D field on the grid of coordinate vectors ``x`` (nx,), ``y`` (ny,) with components
    ``u``, ``v`` (and ``sigma``, ``valid`` when given) laid out by ``order`` (module docstring;
    DataArrays with dims "x", "y" need none), as a :class:`Field` of nx * ny points listed x
    fastest; ``mapping``: the keywords of :func:`from_point_field` (particles, body, thickness, edge)."""
    x = finite("x", numbers(x, "x"), "pass the grid's x coordinates").reshape(-1)
    y = finite("y", numbers(y, "y"), "pass the grid's y coordinates").reshape(-1)
    nx, ny = len(x), len(y)
    if nx < 2 or ny < 2:
        raise ValueError(f"the grid needs at least 2 coordinates along x and y, got nx={nx}, ny={ny}")
    u, v = _layout("u", u, order, nx, ny), _layout("v", v, order, nx, ny)
    points = np.stack(np.meshgrid(x, y, indexing="xy"), axis=-1).reshape(-1, 2)
    sigma = None if sigma is None else _layout("sigma", sigma, order, nx, ny).reshape(-1)
    if valid is not None:
        if np.asarray(valid).dtype != bool:
            raise ValueError(f"valid must be a boolean array, got {np.asarray(valid).dtype}")
        valid = _layout("valid", valid, order, nx, ny).astype(bool).reshape(-1)
    field = from_point_field(points, np.stack([u.reshape(-1), v.reshape(-1)], axis=1), sigma=sigma,
                             valid=valid, **mapping)
    return replace(field, shape=(ny, nx))
