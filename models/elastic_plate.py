"""Elastic moduli, horizon and noise of a peridynamic plate from displacement observations.

    K, G, delta, sigma  ~ models/priors.py elastic_priors (LogNormal(log nominal, 0.5),
                          ScaledBeta(h, delta_max, 2, 2), HalfNormal(noise_scale))
    y     ~ Normal(H u(K, G, delta), sigma)    (masked points allowed)

The scene may be a ``bayespd.reduced.ReducedScene``: the same model at the cost of an r x r
solve, with its error estimate reported per draw in ``sample_stats`` by ``fit``.

Any prior can be replaced through ``priors={"K": dist.LogNormal(...), ...}``.
"""
from __future__ import annotations

import pyro
import pyro.distributions as dist

from bayespd.models.priors import choose, elastic_priors


def default_priors(scene, nominal: dict, noise_scale: float) -> dict:
    """Weakly informative priors on physical scales (moduli, horizon, observation noise)."""
    return elastic_priors(scene, nominal, noise_scale)


class ElasticPlate:
    """The Pyro model ``model(y=None, mask=None)`` for observations y of shape (points, dim);
    a module-level class, so it pickles and its NUTS chains can run in worker processes."""

    def __init__(self, scene, priors: dict):
        self.scene, self.priors = scene, priors

    def diagnostics(self, draws: dict) -> dict:
        """Per-draw figures of the scene (a reduced scene's error estimate), for ``fit``."""
        report = getattr(self.scene, "diagnostics", None)
        return report(draws) if report else {}

    def __call__(self, y=None, mask=None):
        scene, chosen = self.scene, self.priors
        params = {k: pyro.sample(k, chosen[k]) for k in scene.param_names}
        sigma = pyro.sample("sigma", chosen["sigma"])
        mean = scene.predict(params)
        likelihood = dist.Normal(mean, sigma)
        if mask is not None:
            likelihood = likelihood.mask(mask)
        with pyro.plate("point", mean.shape[0], dim=-2), pyro.plate("component", mean.shape[1], dim=-1):
            pyro.sample("y", likelihood, obs=y)


def elastic_plate(scene, nominal: dict, noise_scale: float, priors: dict | None = None) -> ElasticPlate:
    """The model with the default priors, any of them replaced by ``priors``."""
    return ElasticPlate(scene, choose(default_priors(scene, nominal, noise_scale), priors, scene))
