"""A heterogeneous modulus field log mu(x) as a Gaussian Markov random field (Turner 2015 §4.2).

    m      ~ Normal(log nominal, 0.5)              (the field's level, log scale)
    s      ~ LogNormal(log 0.1, 1)                 (rms amplitude of log mu: ~10 %, a factor e either way)
    ell    ~ LogNormal(log length, 0.7)            (correlation length; default length = extent / 4)
    sigma  ~ HalfNormal(noise_scale)
    log mu ~ N(m, Q(ell, s)^-1)                    (Q = tau (I + ell^2 A) on the bond graph, bayespd.gmrf)
    y      ~ Normal(H u(mu(x), fixed), sigma)      (masked entries allowed)

Two parametrisations of the same model. ``whitened=True`` (default): site ``<field>_white``
w ~ N(0, I) and log mu = m + Q^-1/2 w (deterministic ``log_<field>``). ``whitened=False``:
site ``log_<field>`` with the GMRF density itself (exact log-determinant). Use the centred
form only with the hyper-parameters fixed (e.g. by ``pyro.poutine.condition``): with m and s
free its joint density is unbounded (log mu -> m, s -> 0), so it has no MAP and Laplace fails,
and NUTS meets the same funnel; the whitened form has neither problem.

``field`` names the scene parameter that varies (default "G", Turner 2015's mu); the others
(e.g. K of eq 26 and delta) are given in ``fixed``. Every particle carries one value of the
field: the gradient of the log-likelihood with respect to all of them costs one adjoint
solve (``bp.Scene.solve`` is an adjoint-differentiable solve). Sites: ``log_<field>`` (N,),
``<field>_mean``, ``amplitude``, ``length``, ``sigma``; ``<field>`` (N,) is deterministic.

At fixed (m, s, ell, sigma) the MAP of ``log_<field>`` is the Tikhonov solution of Turner 2015
eq 12 with psi = tau(ell, s), L = gmrf.square_root(ell), centred at m (``tikhonov_settings``).
"""
from __future__ import annotations

import math

import numpy as np
import pyro
import pyro.distributions as dist
import torch
from pyro.distributions import constraints

from bayespd import GMRF
from bayespd.models.observations import check_shape
from bayespd.models.priors import choose, fixed_params, positive, positive_support


class GMRFDistribution(dist.TorchDistribution):
    """N(mean, Q(ell, s)^-1) over one value per particle (event shape (N,)); exact log density
    (log-determinant from the graph Laplacian's eigenvalues) and exact draws."""

    arg_constraints = {}
    support = constraints.real_vector

    def __init__(self, gmrf: GMRF, mean, ell, s, validate_args=None):
        self.gmrf, self.mean_level, self.ell, self.s = gmrf, mean, ell, s
        super().__init__(torch.Size(), torch.Size([gmrf.n]), validate_args=validate_args)

    def log_prob(self, value):
        return self.gmrf.log_prob(value, self.mean_level, self.ell, self.s)

    def sample(self, sample_shape=torch.Size()):
        with torch.no_grad():
            return self.gmrf.sample(self.mean_level, self.ell, self.s, tuple(sample_shape))

    @property
    def mean(self):
        return torch.as_tensor(self.mean_level).expand(self.gmrf.n)


def default_priors(scene, nominal: float, noise_scale: float, length: float | None, field: str) -> dict:
    extent = float(np.ptp(scene.particles.x, axis=0).max())
    length = positive("length", extent / 4 if length is None else length)
    return {f"{field}_mean": dist.Normal(math.log(positive(f"the nominal {field}", nominal)), 0.5),
            "amplitude": dist.LogNormal(math.log(0.1), 1.0),
            "length": dist.LogNormal(math.log(length), 0.7),
            "sigma": dist.HalfNormal(positive("noise_scale", noise_scale))}


def _check_field(scene, field: str) -> None:
    if field not in scene.material.moduli_names:
        raise ValueError(f"field must be one of the material's moduli {list(scene.material.moduli_names)}, not {field!r}")


def heterogeneous_field(scene, nominal: float, noise_scale: float, fixed: dict, *, field: str = "G",
                        length: float | None = None, radius: float | None = None, whitened: bool = True,
                        priors: dict | None = None):
    """A Pyro model ``model(y=None, mask=None)`` for observations y (points, dim) of ``scene``.
    ``nominal``: a typical value of the field; ``radius``: the GMRF graph keeps the bonds no
    longer than it (default 1.5 h, the 8 nearest neighbours on a square grid)."""
    _check_field(scene, field)
    fixed = fixed_params(scene, fixed, (field,))
    chosen = choose(default_priors(scene, nominal, noise_scale, length, field), priors)
    positive_support(chosen, ("amplitude", "length", "sigma"))
    gmrf = GMRF(scene.particles, scene.material.bonds, 1.5 * scene.particles.h if radius is None else radius)
    shape = (scene.observation.n, scene.particles.dim)

    def model(y=None, mask=None):
        if y is not None:
            y = check_shape(y, shape, "y", "observe the scene's observation points (one row per point)")
        level = pyro.sample(f"{field}_mean", chosen[f"{field}_mean"])
        s = pyro.sample("amplitude", chosen["amplitude"])
        ell = pyro.sample("length", chosen["length"])
        sigma = pyro.sample("sigma", chosen["sigma"])
        if whitened:
            w = pyro.sample(f"{field}_white", dist.Normal(torch.zeros(gmrf.n), 1.0).to_event(1))
            log_field = pyro.deterministic(f"log_{field}", level + gmrf.colour(w, ell, s))
        else:
            log_field = pyro.sample(f"log_{field}", GMRFDistribution(gmrf, level, ell, s))
        value = pyro.deterministic(field, torch.exp(log_field))
        mean = scene.observe(scene.solve({**fixed, field: value}))
        likelihood = dist.Normal(mean, sigma)
        if mask is not None:
            likelihood = likelihood.mask(torch.as_tensor(mask, dtype=torch.bool))
        with pyro.plate("point", shape[0], dim=-2), pyro.plate("component", shape[1], dim=-1):
            pyro.sample("y", likelihood, obs=y)

    model.gmrf = gmrf
    return model


def tikhonov_settings(model, level: float, length: float, amplitude: float, field: str = "G") -> dict:
    """Keyword arguments of ``bayespd.inverse.tikhonov`` whose minimiser is this model's MAP at
    fixed hyper-parameters (level m on the log scale, length, amplitude): psi, L and ref."""
    gmrf = model.gmrf
    return {"psi": float(gmrf.tau(length, amplitude)), "L": gmrf.square_root(length),
            "ref": {field: np.full(gmrf.n, math.exp(level))}}
