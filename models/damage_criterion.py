"""Critical stretch s0 of the smoothed damage law (You 2023 eq 3.10) from crack openings
observed during a quasi-static test.

    s0    ~ LogNormal(log nominal, 0.5)            (a factor ~1.6 either way at one sd)
    sigma ~ HalfNormal(noise_scale)
    y[k, j] ~ Normal(h_j(u_k(s0)), sigma)          openings at station j, load factor lam_k

u_k(s0) is the equilibrium at lam_k of ``models/smooth_fracture.SmoothFracture`` (bond-based,
small strain, history-dependent smoothed step of width eta, gradient in s0 by the implicit
function theorem; one dense solve per step). ``observation`` maps u (N, dim) to the openings
(``models.load_from_aperture.aperture_observation``), its mask keeps the opening component.
The forward model has exact first derivatives only: fit with NUTS, SVI or
``fit(..., "laplace", hessian="gauss-newton")``.
"""
from __future__ import annotations

import math

import numpy as np
import pyro
import pyro.distributions as dist
import torch

from bayespd.models.observations import check_shape
from bayespd.models.priors import choose, positive, positive_support


def damage_criterion(fracture, load_factors, observation, nominal: float, noise_scale: float,
                     priors: dict | None = None):
    """A Pyro model ``model(y=None, mask=None)`` for openings y (steps, stations, dim) at
    ``load_factors`` (increasing, > 0). Sites ``s0``, ``sigma``."""
    lams = np.asarray(load_factors, dtype=float)
    if lams.ndim != 1 or len(lams) == 0 or np.any(lams <= 0) or np.any(np.diff(lams) <= 0):
        raise ValueError("load_factors must be a non-empty increasing sequence of positive values")
    chosen = choose({"s0": dist.LogNormal(math.log(positive("the nominal s0", nominal)), 0.5),
                     "sigma": dist.HalfNormal(positive("noise_scale", noise_scale))}, priors)
    positive_support(chosen, ("s0", "sigma"))
    shape = (len(lams), observation.n, fracture.particles.dim)
    keep = torch.as_tensor(observation.mask).expand(shape)

    def model(y=None, mask=None):
        if y is not None:
            y = check_shape(y, shape, "y", "one (stations, dim) frame of openings per load factor")
        s0 = pyro.sample("s0", chosen["s0"])
        sigma = pyro.sample("sigma", chosen["sigma"])
        opening = fracture.run(s0, lams, observation)
        used = keep if mask is None else keep & torch.as_tensor(mask, dtype=torch.bool)
        with pyro.plate("step", shape[0], dim=-3), pyro.plate("station", shape[1], dim=-2), \
                pyro.plate("component", shape[2], dim=-1):
            pyro.sample("y", dist.Normal(opening, sigma).mask(used), obs=y)

    return model
