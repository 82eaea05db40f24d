"""Refuse bad input before any sampling, with messages that name the fix."""

import inspect
import math

import numpy as np
import torch
from torch.distributions import constraints


def as_tensors(data) -> dict:
    """``data`` with its numpy arrays, lists and tuples as torch tensors (floats in the default dtype), so a
    model gets what Pyro takes; arrays of strings or objects are refused."""
    if not isinstance(data, dict):
        raise TypeError(f"data must be a dict of the model's keyword arguments, not {type(data).__name__}")
    out = dict(data)
    for k, v in data.items():
        if isinstance(v, (list, tuple)):
            try:
                v = np.asarray(v)
            except ValueError as error:  # ragged
                raise TypeError(f"data[{k!r}] is a ragged {type(v).__name__}: pass an array or tensor") from error
        if isinstance(v, np.ndarray):
            if v.dtype.kind not in "biuf":
                raise TypeError(f"data[{k!r}] is an array of {v.dtype}: pass numbers (or booleans for a mask)")
            out[k] = torch.as_tensor(v, dtype=torch.get_default_dtype() if v.dtype.kind == "f" else None)
    return out


def check_arguments(model, data: dict) -> None:
    """Every key of ``data`` is an argument the model takes (when its signature is known)."""
    try:
        signature = inspect.signature(model)
    except (TypeError, ValueError):  # no signature: its own errors speak
        return
    try:
        signature.bind_partial(**data)
    except TypeError as error:
        raise TypeError(f"data keys {sorted(data)} do not fit the model's arguments {signature} ({error}): "
                        "pass only the model's keyword arguments") from None


def check_continuous(priors: dict) -> None:
    """Every latent site (``{name: distribution}``) is continuous: the samplers and optimisers
    move on a continuous space."""
    for name, prior in priors.items():
        if getattr(getattr(prior, "support", None), "is_discrete", False):  # a plate's subsample has none
            raise ValueError(f"{name} has a discrete prior ({type(prior).__name__}): NUTS, HMC, SVI and "
                             "Laplace need continuous latent variables; give it a continuous prior "
                             "(e.g. LogNormal, or Uniform over its range) or enumerate it out")


def check_data(data: dict, observed: str) -> None:
    """The observed tensor exists and is finite wherever the mask (``data["mask"]``) keeps it;
    masked entries must be finite too (a NaN times a zero weight still poisons gradients)."""
    if observed not in data:
        raise ValueError(f"data has no {observed!r} entry (keys {sorted(data)}): pass the "
                         "observations under that name or set observed=")
    y = torch.as_tensor(data[observed])
    bad = ~torch.isfinite(y)
    if not bad.any():
        return
    mask = data.get("mask")
    keep = torch.ones_like(bad) if mask is None else torch.as_tensor(mask, dtype=torch.bool).expand_as(bad)
    outside = bad & keep
    if outside.any():
        first = tuple(int(i) for i in torch.nonzero(outside)[0])
        raise ValueError(f"{observed} has {int(outside.sum())} NaN/inf entries outside the mask "
                         f"(first at index {first}): mark missing data in the mask, e.g. "
                         "data = bayespd.model_data(y, mask), which also zeroes them")
    raise ValueError(f"{observed} has {int(bad.sum())} NaN/inf entries under the mask: their "
                     "weight is 0 but NaN * 0 is NaN in the gradients; set them to 0, e.g. "
                     "data = bayespd.model_data(y, mask)")


def check_observed_shape(trace, data: dict, observed: str, scene=None) -> None:
    """The observations have the shape the model (and the scene's observation) predicts."""
    sites = [k for k, s in trace.nodes.items() if s["type"] == "sample"]
    if observed not in sites:
        raise ValueError(f"the model has no sample site {observed!r} (sites {sites}): "
                         "set observed= to the name of the likelihood site")
    shape = tuple(torch.as_tensor(data[observed]).shape)
    if scene is not None and scene.observation is not None:
        expected = (scene.observation.n, scene.particles.dim)
        if shape != expected:
            raise ValueError(f"{observed} has shape {shape} but the scene observes {expected[0]} "
                             f"points x {expected[1]} components {expected}: build the scene's "
                             "Observation at the data's points (one row per point)")
    fn = trace.nodes[observed]["fn"]
    predicted = tuple(fn.batch_shape + fn.event_shape)
    if shape != predicted:
        raise ValueError(f"{observed} has shape {shape} but the model predicts {predicted}: "
                         "the data do not match the scene's observation points")


def _bounds(support):
    while isinstance(support, constraints.independent):
        support = support.base_constraint
    low = getattr(support, "lower_bound", -math.inf)
    high = getattr(support, "upper_bound", math.inf)
    return float(torch.as_tensor(low).min()), float(torch.as_tensor(high).max())


def trace_priors(trace) -> dict:
    """``{site: distribution}`` of the latent (unobserved) sample sites of ``trace``."""
    return {k: s["fn"] for k, s in trace.nodes.items() if s["type"] == "sample" and not s["is_observed"]}


def check_priors(priors: dict, scene) -> None:
    """Prior supports (``{name: distribution}``) inside the physical range of ``scene``: moduli
    (``material.moduli_names``) positive, the horizon in [h, delta_max]. Names that are no
    parameter of the scene are skipped."""
    h, delta_max = scene.particles.h, scene.material.bonds.delta_max
    for name, prior in priors.items():
        if name not in scene.param_names:
            continue
        low, high = _bounds(prior.support)
        if name in scene.material.moduli_names and low < 0:
            raise ValueError(f"the prior of {name} has support [{low:g}, {high:g}], which "
                             f"includes negative moduli: use a positive prior, e.g. "
                             f"LogNormal(log(nominal), 0.5)")
        if name == "delta" and (low < h * (1 - 1e-12) or high > delta_max * (1 + 1e-12)):
            raise ValueError(f"the prior of delta has support [{low:g}, {high:g}] but the scene "
                             f"allows h = {h:g} <= delta <= delta_max = {delta_max:g}: use e.g. "
                             f"ScaledBeta({h:g}, {delta_max:g}), or build the scene with a larger "
                             "delta_max")
