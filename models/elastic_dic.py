"""K, G, delta and sigma of a peridynamic body from a DIC displacement field with missing data.

A DIC field is a regular grid of points (``bp.grid_points``) observed through
``bp.GridObservation`` (bilinear interpolation from the particle lattice). Data are missing
where the correlation failed (NaN) or where the user masks them (e.g. a band near an edge);
grid points the lattice cannot interpolate (holes, notches, outside) are masked by the
observation itself. The model is ``models/elastic_plate.py`` on the union of those masks:

    K, G, delta, sigma  ~ models/priors.py elastic_priors (overridable by ``priors=``)
    y[p, c] ~ Normal(H u(K, G, delta), sigma)   for every kept entry (p, c)

Use ``dic_data(scene, y, mask)`` to build the data: NaN is accepted only where ``mask`` is
False, since an unmarked NaN is usually a bug in the DIC export.
"""
from __future__ import annotations

import numpy as np
import torch

import bayespd as bp
from bayespd.models.elastic_plate import elastic_plate


def _grid_scene(scene):
    if not isinstance(scene.observation, bp.GridObservation):
        raise ValueError("elastic_dic needs a scene observed through bp.GridObservation(particles, "
                         f"points) (a DIC grid), not {type(scene.observation).__name__}: use "
                         "models.elastic_plate for scattered observations")
    return scene.observation


def dic_data(scene, y, mask=None) -> dict:
    """``{"y", "mask"}`` for the model: ``y`` (points, dim) on the scene's DIC grid, ``mask``
    (points, dim) True where observed (default: everywhere), combined with the grid's own mask;
    masked entries of y are set to 0. NaN/inf where ``mask`` is True raises ValueError."""
    obs = _grid_scene(scene)
    y = np.asarray(y, dtype=float)
    expected = (obs.n, scene.particles.dim)
    if y.shape != expected:
        raise ValueError(f"the DIC field has shape {y.shape} but the scene's grid has {expected[0]} "
                         f"points x {expected[1]} components {expected}: build the "
                         "GridObservation at the DIC points (one row per point, x fastest)")
    keep = np.ones(expected, dtype=bool) if mask is None else np.asarray(mask)
    if keep.dtype != bool or keep.shape != expected:
        raise ValueError(f"mask must be boolean of shape {expected}, got {keep.dtype} {keep.shape}")
    bad = ~np.isfinite(y) & keep
    if bad.any():
        first = tuple(int(i) for i in np.argwhere(bad)[0])
        raise ValueError(f"the DIC field has {int(bad.sum())} NaN/inf entries outside the mask "
                         f"(first at {first}): mark missing data False in mask, e.g. "
                         "mask=bp.finite_mask(y) & band")
    keep = keep & obs.mask
    return {"y": torch.as_tensor(np.where(keep, y, 0.0)), "mask": torch.as_tensor(keep)}


def elastic_dic(scene, nominal: dict, noise_scale: float, priors: dict | None = None, discrepancy=None):
    """A Pyro model ``model(y=None, mask=None)`` for a DIC field y (points, dim) on the scene's
    grid (see ``dic_data``); the grid's own mask is always applied. ``discrepancy`` (a
    ``bp.Discrepancy`` estimated at the grid's points) adds the approximation-error term, its
    Gaussian marginalised over the masked entries."""
    grid_mask = torch.as_tensor(_grid_scene(scene).mask)
    inner = elastic_plate(scene, nominal, noise_scale, priors, discrepancy)

    def model(y=None, mask=None):
        inner(y, grid_mask if mask is None else grid_mask & torch.as_tensor(mask, dtype=torch.bool))

    return model
