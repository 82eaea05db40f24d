"""Brownian forcing of Dodwell 2019 eq 4 read as a model-discrepancy term (see
``bayespd.infer.likelihoods`` for the derivations).

Stationary frames (``stationary``): F independent frames of the elastic body at equilibrium
under the Langevin forcing, observed with noise,

    K, G, delta, sigma  as models/elastic_plate.py   (LogNormal(log nominal, 0.5), ScaledBeta(h, delta_max), HalfNormal)
    eta   ~ LogNormal(log eta_nominal, 1)             (a factor of e either way at one sd)
    y_f   ~ N(H A^-1 p, eta H A^-1 H^T + sigma^2 I),  f = 1..F   (A = K_ff + eps I).

Trajectory (``trajectory``): a path U_0..U_T of the free dofs observed exactly,

    K, G, delta ~ as above;  eta ~ LogNormal(log eta_nominal, 1)
    sigma_c     ~ LogNormal(log sigma_c_nominal, 1)     (noise amplitude, C = sigma_c^2 R)
    length      ~ LogNormal(log length_nominal, 0.5)   (correlation length; Karhunen-Loeve noise only)
    U_{n+1} | U_n ~ N(U_n + (dt / eta) C (p - A U_n), 2 dt C)   (Euler-Maruyama).

Any prior can be replaced through ``priors={"eta": dist.LogNormal(...), ...}``.
"""
from __future__ import annotations

import math

import pyro
import pyro.distributions as dist
import torch

from bayespd.infer import NoiseCovariance, StationaryMarginal, euler_maruyama_transition
from bayespd.models.elastic_plate import default_priors


def _choose(defaults: dict, priors: dict | None) -> dict:
    unknown = set(priors or {}) - set(defaults)
    if unknown:
        raise ValueError(f"no such parameter(s) {sorted(unknown)}: priors can be given for {sorted(defaults)}")
    return {**defaults, **(priors or {})}


def stationary(scene, nominal: dict, eta_nominal: float, noise_scale: float, priors: dict | None = None):
    """A Pyro model ``model(y)`` for y of shape (frames, n_obs): the observed entries of each
    frame (``frames_data`` flattens (frames, points, dim) data), site ``y``."""
    chosen = _choose({**default_priors(scene, nominal, noise_scale),
                      "eta": dist.LogNormal(math.log(eta_nominal), 1.0)}, priors)
    marginal = StationaryMarginal(scene)

    def model(y):
        params = {k: pyro.sample(k, chosen[k]) for k in scene.param_names}
        eta = pyro.sample("eta", chosen["eta"])
        sigma = pyro.sample("sigma", chosen["sigma"])
        with pyro.plate("frame", y.shape[0]):
            pyro.sample("y", marginal(params, eta, sigma), obs=y)

    model.marginal = marginal
    return model


def frames_data(scene, y) -> dict:
    """``{"y": (frames, n_obs)}`` from observations (frames, points, dim) of ``scene``, keeping
    the entries its observation mask marks (the stationary model's data)."""
    mask = scene.observation.mask.reshape(-1)
    if y.shape[1:] != scene.observation.mask.shape:
        raise ValueError(f"y must be (frames, {scene.observation.n}, {scene.particles.dim}), got {tuple(y.shape)}")
    return {"y": y.reshape(y.shape[0], -1)[:, mask]}


def trajectory(scene, nominal: dict, eta_nominal: float, sigma_c_nominal: float, dt: float,
               noise: dict | None = None, priors: dict | None = None):
    """A Pyro model ``model(y, u0)`` for a path of the free dofs: ``y`` = U_1..U_T (T, n_free),
    ``u0`` = U_0. ``noise=None`` is white C = sigma_c^2 I; ``noise={"rank": r, "nugget": g,
    "length_nominal": l}`` is the Karhunen-Loeve C = sigma_c^2 (Phi_r Lambda_r Phi_r^T + g I) (x) I
    of a squared-exponential kernel with unknown length (keep the particle set small: the
    kernel's eigenpairs come from a dense eigendecomposition per evaluation)."""
    defaults = {k: v for k, v in default_priors(scene, nominal, 1.0).items() if k != "sigma"}
    defaults["eta"] = dist.LogNormal(math.log(eta_nominal), 1.0)
    defaults["sigma_c"] = dist.LogNormal(math.log(sigma_c_nominal), 1.0)
    if noise is not None:
        defaults["length"] = dist.LogNormal(math.log(noise["length_nominal"]), 0.5)
    chosen = _choose(defaults, priors)
    n = len(scene.constraints.free_dofs)

    def covariance(sigma_c):
        if noise is None:
            return NoiseCovariance.white(sigma_c, n)
        length = pyro.sample("length", chosen["length"])
        return NoiseCovariance.karhunen_loeve(scene.particles.x, sigma_c, length, noise["rank"],
                                              noise["nugget"], scene.constraints.free_dofs, scene.particles.dim)

    def model(y, u0):
        params = {k: pyro.sample(k, chosen[k]) for k in scene.param_names}
        eta = pyro.sample("eta", chosen["eta"])
        C = covariance(pyro.sample("sigma_c", chosen["sigma_c"]))
        previous = torch.cat([u0[None], y[:-1]])  # U_0..U_{T-1}
        with pyro.plate("step", y.shape[0]):
            pyro.sample("y", euler_maruyama_transition(scene, params, eta, C, dt, previous), obs=y)

    return model

