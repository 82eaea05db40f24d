"""Elastic moduli, horizon and noise of a peridynamic plate from displacement observations.

    K, G ~ LogNormal(log nominal, 0.5)         (a factor of ~1.6 either way at one sd)
    delta ~ ScaledBeta(h, delta_max, 2, 2)     (the horizon lies between h and the bond search radius)
    sigma ~ HalfNormal(noise_scale)
    y     ~ Normal(H u(K, G, delta), sigma)    (masked points allowed)

Any prior can be replaced through ``priors={"K": dist.LogNormal(...), ...}``.
"""
from __future__ import annotations

import math

import pyro
import pyro.distributions as dist

from bayespd.infer import ScaledBeta


def default_priors(scene, nominal: dict, noise_scale: float) -> dict:
    """Weakly informative priors on physical scales (moduli, horizon, observation noise)."""
    h, delta_max = scene.particles.h, scene.material.bonds.delta_max
    priors = {k: dist.LogNormal(math.log(nominal[k]), 0.5) for k in scene.material.param_names}
    priors["delta"] = ScaledBeta(h, delta_max, 2.0, 2.0)
    priors["sigma"] = dist.HalfNormal(noise_scale)
    return priors


def elastic_plate(scene, nominal: dict, noise_scale: float, priors: dict | None = None):
    """A Pyro model ``model(y=None, mask=None)`` for observations y of shape (points, dim)."""
    chosen = default_priors(scene, nominal, noise_scale)
    unknown = set(priors or {}) - set(chosen)
    if unknown:
        raise ValueError(f"no such parameter(s) {sorted(unknown)}: priors can be given for {sorted(chosen)}")
    chosen.update(priors or {})

    def model(y=None, mask=None):
        params = {k: pyro.sample(k, chosen[k]) for k in scene.param_names}
        sigma = pyro.sample("sigma", chosen["sigma"])
        mean = scene.observe(scene.solve(params))
        likelihood = dist.Normal(mean, sigma)
        if mask is not None:
            likelihood = likelihood.mask(mask)
        with pyro.plate("point", mean.shape[0], dim=-2), pyro.plate("component", mean.shape[1], dim=-1):
            pyro.sample("y", likelihood, obs=y)

    return model
