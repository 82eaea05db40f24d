"""Posterior of the load from observed crack apertures (Turner 2015 §5, eq 28).

The scene is the linear PD body with its crack as observed (the bonds across it removed:
``bp.precrack``), under unit loads (e.g. ``bp.Load(top, (0, 1))``) scaled by the load factor;
the apertures are linear in it (Turner 2015 §5 inverts "based on the displacement of the
material points without having to accommodate the damage model"). Eq 28's least squares is
the likelihood of Gaussian aperture errors:

    load  ~ LogNormal(log nominal, 1)               (F_y > 0; a factor e either way at one sd)
    sigma ~ HalfNormal(noise_scale)
    y_j   ~ Normal(h_j(load), sigma)               h_j = u(x_j+) - u(x_j-), the opening at station j

The moduli and the horizon are known (``fixed``). ``aperture_observation`` builds the
operator h_j from pairs of points facing each other across the crack.
"""
from __future__ import annotations

import math

import pyro
import pyro.distributions as dist
import torch

import bayespd as bp
from bayespd.models.observations import check_shape
from bayespd.models.priors import choose, fixed_params, positive, positive_support


def aperture_observation(particles, above, below, component: int = 1) -> bp.OpeningObservation:
    """Openings u(above_j) - u(below_j) at stations j; the mask keeps ``component`` (default 1:
    the y opening of a crack along x)."""
    return bp.OpeningObservation(particles, above, below, component)


def load_from_aperture(scene, nominal: float, noise_scale: float, fixed: dict, priors: dict | None = None):
    """A Pyro model ``model(y=None, mask=None)``: y (stations, dim) openings, scored where the
    scene's aperture observation (and ``mask``) keep them. Sites ``load``, ``sigma``."""
    fixed = fixed_params(scene, fixed)
    if scene.observation is None:
        raise ValueError("the scene needs an aperture observation: pass aperture_observation(...) to bp.Scene")
    chosen = choose({"load": dist.LogNormal(math.log(positive("the nominal load", nominal)), 1.0),
                     "sigma": dist.HalfNormal(positive("noise_scale", noise_scale))}, priors)
    positive_support(chosen, ("load", "sigma"))
    shape = (scene.observation.n, scene.particles.dim)
    keep = torch.as_tensor(scene.observation.mask)

    def model(y=None, mask=None):
        if y is not None:
            y = check_shape(y, shape, "y", "one row of openings per aperture station")
        load = pyro.sample("load", chosen["load"])
        sigma = pyro.sample("sigma", chosen["sigma"])
        opening = scene.observe(scene.solve({**fixed, "load": load}))
        used = keep if mask is None else keep & torch.as_tensor(mask, dtype=torch.bool)
        with pyro.plate("station", shape[0], dim=-2), pyro.plate("component", shape[1], dim=-1):
            pyro.sample("y", dist.Normal(opening, sigma).mask(used), obs=y)

    return model
