"""Elastic moduli, horizon and noise of a peridynamic plate from displacement observations.

    K, G, delta, sigma  ~ models/priors.py elastic_priors (LogNormal(log nominal, 0.5),
                          ScaledBeta(h, delta_max, 2, 2), HalfNormal(noise_scale))
    y     ~ Normal(H u(K, G, delta), sigma)    (masked points allowed)

The scene may be a ``bayespd.reduced.ReducedScene``: the same model at the cost of an r x r
solve, with its error estimate reported per draw in ``sample_stats`` by ``fit``.

Any prior can be replaced through ``priors={"K": dist.LogNormal(...), ...}``.

With ``discrepancy=`` (a ``bp.Discrepancy`` from ``bp.estimate_discrepancy``: the
approximation error of this scene against a finer reference, Kaipio & Somersalo 2007) the
observed entries are jointly Gaussian instead:

    vec(y) ~ N(vec(H u + s mu(params)), s^2 W W^T + diag(s^2 d + sigma^2))   (s = 1, or rms(H u) if relative)

over the entries the mask keeps (the exact marginal of the full law); replicated data are drawn
from the full law, shape (points, dim). The pointwise log-likelihood is then one value per draw.
"""
from __future__ import annotations

import pyro
import pyro.distributions as dist
import torch
from torch.distributions import constraints

import bayespd as bp
from bayespd.models.priors import choose, elastic_priors


def default_priors(scene, nominal: dict, noise_scale: float) -> dict:
    """Weakly informative priors on physical scales (moduli, horizon, observation noise)."""
    return elastic_priors(scene, nominal, noise_scale)


class FieldGaussian(dist.TorchDistribution):
    """N(vec(loc), W W^T + diag(d)) over a (points, dim) field as one event; ``log_prob`` is
    the marginal density of the entries ``mask`` keeps (rows of W and d selected)."""

    arg_constraints = {}
    support = constraints.independent(constraints.real, 2)
    has_rsample = True

    def __init__(self, loc, factor, diag, mask=None):
        self.full = dist.LowRankMultivariateNormal(loc.reshape(-1), factor, diag)
        self.keep = None if mask is None else torch.as_tensor(mask, dtype=torch.bool).expand(loc.shape).reshape(-1)
        if self.keep is not None and not bool(self.keep.any()):
            raise ValueError("the mask keeps no observation: mark at least one entry True")
        self.kept = self.full if self.keep is None else dist.LowRankMultivariateNormal(
            loc.reshape(-1)[self.keep], factor[self.keep], diag[self.keep])
        super().__init__(torch.Size(), loc.shape, validate_args=False)

    def rsample(self, sample_shape=torch.Size()):
        return self.full.rsample(sample_shape).reshape(torch.Size(sample_shape) + self.event_shape)

    def log_prob(self, value):
        flat = value.reshape(value.shape[:value.dim() - 2] + (-1,))
        return self.kept.log_prob(flat if self.keep is None else flat[..., self.keep])


class ElasticPlate:
    """The Pyro model ``model(y=None, mask=None)`` for observations y of shape (points, dim);
    a module-level class, so it pickles and its NUTS chains can run in worker processes."""

    def __init__(self, scene, priors: dict, discrepancy=None):
        if discrepancy is not None:
            if not isinstance(discrepancy, bp.Discrepancy):
                raise TypeError(f"discrepancy must be a bayespd.Discrepancy (from bayespd.estimate_discrepancy), "
                                f"not {type(discrepancy).__name__}")
            if scene.observation is None:
                raise ValueError("a discrepancy term needs a scene with an observation (the points it was estimated at)")
            discrepancy.check_points(scene.observation.points)
        self.scene, self.priors, self.discrepancy = scene, priors, discrepancy

    def diagnostics(self, draws: dict) -> dict:
        """Per-draw figures of the scene (a reduced scene's error estimate), for ``fit``."""
        report = getattr(self.scene, "diagnostics", None)
        return report(draws) if report else {}

    def __call__(self, y=None, mask=None):
        scene, chosen = self.scene, self.priors
        params = {k: pyro.sample(k, chosen[k]) for k in scene.param_names}
        sigma = pyro.sample("sigma", chosen["sigma"])
        mean = scene.predict(params)
        if self.discrepancy is not None:
            loc, factor, diag = self.discrepancy.gaussian(mean, params)
            pyro.sample("y", FieldGaussian(loc, factor, diag + sigma**2, mask), obs=y)
            return
        likelihood = dist.Normal(mean, sigma)
        if mask is not None:
            likelihood = likelihood.mask(mask)
        with pyro.plate("point", mean.shape[0], dim=-2), pyro.plate("component", mean.shape[1], dim=-1):
            pyro.sample("y", likelihood, obs=y)


def elastic_plate(scene, nominal: dict, noise_scale: float, priors: dict | None = None,
                  discrepancy=None) -> ElasticPlate:
    """The model with the default priors, any of them replaced by ``priors``, and the
    approximation-error term ``discrepancy`` (a ``bp.Discrepancy``) when given."""
    return ElasticPlate(scene, choose(default_priors(scene, nominal, noise_scale), priors, scene), discrepancy)
