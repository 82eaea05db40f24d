"""Prior plumbing shared by the models: defaults overridden by a user's ``priors=`` mapping,
and early refusal of priors whose support leaves the physical range of a scene.

    K, G  ~ LogNormal(log nominal, 0.5)       (a factor of ~1.6 either way at one sd)
    delta ~ ScaledBeta(h, delta_max, 2, 2)    (the horizon lies between h and the bond search radius)
    sigma ~ HalfNormal(noise_scale)
"""
from __future__ import annotations

import math

import pyro.distributions as dist
import torch

from bayespd import check_horizon
from bayespd.infer import ScaledBeta, check_priors


def positive(name: str, value) -> float:
    """``value`` as a float, refused unless finite and > 0 (``name`` says what it is)."""
    v = float(value)
    if not (math.isfinite(v) and v > 0):
        raise ValueError(f"{name} must be finite and positive, got {value!r}: it sets the scale "
                         "of a default prior")
    return v


def elastic_priors(scene, nominal: dict, noise_scale: float) -> dict:
    """Weakly informative priors on physical scales (moduli, horizon, observation noise)."""
    h, delta_max = scene.particles.h, scene.material.bonds.delta_max
    names = [k for k in scene.material.param_names if k != "delta"]  # delta: its own prior
    missing = set(names) - set(nominal)
    if missing:
        raise ValueError(f"nominal needs a value for every modulus {list(names)}; missing {sorted(missing)}")
    priors = {k: dist.LogNormal(math.log(positive(f"the nominal {k}", nominal[k])), 0.5) for k in names}
    priors["delta"] = ScaledBeta(h, delta_max, 2.0, 2.0)
    priors["sigma"] = dist.HalfNormal(positive("noise_scale", noise_scale))
    return priors


def choose(defaults: dict, priors: dict | None, scene=None) -> dict:
    """``defaults`` updated by ``priors``; unknown names and (given ``scene``) supports outside
    the physical range (negative moduli, delta outside [h, delta_max]) raise ValueError."""
    priors = dict(priors or {})
    unknown = set(priors) - set(defaults)
    if unknown:
        raise ValueError(f"no such parameter(s) {sorted(unknown)}: priors can be given for {sorted(defaults)}")
    for k, prior in priors.items():
        if not isinstance(prior, dist.Distribution):
            raise ValueError(f"the prior of {k} must be a Pyro distribution, got {type(prior).__name__}")
    if scene is not None:  # the check fit(..., scene=) runs on the model's priors
        check_priors(priors, scene)
    return {**defaults, **priors}


def positive_support(priors: dict, names) -> None:
    """Refuse priors for the positive quantities ``names`` (amplitudes, lengths, loads) whose
    support reaches below zero."""
    for k in names:
        low = getattr(priors[k].support, "lower_bound", None)
        if low is None or float(torch.as_tensor(low).min()) < 0:
            raise ValueError(f"the prior of {k} has support {priors[k].support}, which includes "
                             f"negative values, but {k} is positive: use e.g. LogNormal or HalfNormal")


def fixed_params(scene, fixed: dict, inferred=()) -> dict:
    """The scene parameters that a model holds known: exactly ``scene.param_names`` less
    ``inferred``, moduli finite and positive, delta in [h, delta_max]; as float64 tensors."""
    needed = set(scene.param_names) - set(inferred)
    if set(fixed) != needed:
        raise ValueError(f"fixed must give exactly {sorted(needed)} (the parameters that are not "
                         f"inferred), got {sorted(fixed)}")
    out = {k: torch.as_tensor(v, dtype=torch.float64) for k, v in fixed.items()}
    check_horizon(float(out["delta"]), scene.particles.h, scene.material.bonds.delta_max)
    for k in needed - {"delta"}:
        if not bool(torch.all(torch.isfinite(out[k]) & (out[k] > 0))):
            raise ValueError(f"the fixed {k} must be finite and positive")
    return out
