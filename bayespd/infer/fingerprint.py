"""What determines a chain's draws, as a dict of short hashes: a checkpoint written for one run
is refused by another (``bayespd.infer.mcmc``).

**Data**: every keyword of the model, exactly (dtype, shape, bytes of tensors and arrays).

**Model, prior and start**: one trace of the model at its initial values (the chain's init
strategy, the torch / numpy / python RNGs seeded with the run's seed and restored afterwards):
per sample site its distribution's class, shapes, parameters, plates, scale and mask, and at
latent sites the initial value. A likelihood's parameters there are the forward model's
output (e.g. ``H u(K)``), so a changed scene, material or prior shows up, and so does a
changed init strategy or ``init_values``. Tensors of the trace are hashed at float32
precision: the forward model is rerun, and a last-bit difference of a multithreaded solve
must not refuse a checkpoint. (Pickled model bytes are no alternative: closures do not
pickle, and a model object's caches and counters change its bytes without changing it.)
"""

import hashlib
import random

import numpy as np
import torch
from pyro.poutine.util import site_is_subsample

from .space import init_trace


def _digest(*parts) -> str:
    h = hashlib.sha256()
    for p in parts:
        h.update(p if isinstance(p, bytes) else repr(p).encode())
    return h.hexdigest()[:16]


def _bytes(value, exact: bool) -> tuple:
    """(dtype, shape, bytes) of a tensor or an array; floats at float32 precision unless ``exact``."""
    a = value.detach().cpu().numpy() if isinstance(value, torch.Tensor) else np.asarray(value)
    b = a.astype(np.float32) if not exact and a.dtype.kind == "f" else a
    return str(a.dtype), a.shape, np.ascontiguousarray(b).tobytes()


def data_hash(value) -> str:
    """Exact hash of one data value: tensors and arrays by content, containers by their items,
    plain values by ``repr``, any other object by its type only (an address is no content)."""
    if isinstance(value, (torch.Tensor, np.ndarray)):
        return _digest(*_bytes(value, exact=True))
    if isinstance(value, dict):
        return _digest(*((k, data_hash(v)) for k, v in sorted(value.items(), key=lambda kv: repr(kv[0]))))
    if isinstance(value, (list, tuple)):
        return _digest(type(value).__name__, *(data_hash(v) for v in value))
    if value is None or isinstance(value, (bool, int, float, complex, str, bytes)):
        return _digest(value)
    return _digest(type(value).__qualname__)


def _distribution(fn) -> tuple:
    """A distribution's class, shapes, parameters and (wrappers) base distribution."""
    params = []
    for name in sorted(getattr(fn, "arg_constraints", {})):
        value = getattr(fn, name, None)
        params.append((name, _bytes(value, exact=False) if isinstance(value, torch.Tensor) else value))
    base = getattr(fn, "base_dist", None)
    mask = getattr(fn, "_mask", None)  # pyro's MaskedDistribution
    return (type(fn).__name__, tuple(fn.batch_shape), tuple(fn.event_shape), params,
            None if base is None else _distribution(base),
            _bytes(mask, exact=True) if isinstance(mask, torch.Tensor) else mask)


def _site(site) -> str:
    scale, mask = site["scale"], site["mask"]
    return _digest(
        "observed" if site["is_observed"] else "latent", _distribution(site["fn"]),
        [(f.name, f.size, f.dim) for f in site["cond_indep_stack"]],
        _bytes(scale, exact=False) if isinstance(scale, torch.Tensor) else scale,
        _bytes(mask, exact=True) if isinstance(mask, torch.Tensor) else mask,
        None if site["is_observed"] else _bytes(site["value"], exact=False))


def _seeded_trace(model, data, init, seed):
    """The model's trace at its initial values, the RNGs seeded with ``seed`` and then restored."""
    states = torch.get_rng_state(), np.random.get_state(), random.getstate()
    try:
        torch.manual_seed(seed)
        np.random.seed(seed % 2**32)
        random.seed(seed)
        with torch.no_grad():
            return init_trace(model, data, init)
    finally:
        torch.set_rng_state(states[0])
        np.random.set_state(states[1])
        random.setstate(states[2])


def run_fingerprint(model, data, init, seed, seed_covariance=None) -> dict:
    """``{"data 'y'": hash, "site 'K'": hash, ..., "mass matrix seed": hash}`` of a run."""
    trace = _seeded_trace(model, data, init, seed)
    sites = {f"site {name!r}": _site(s) for name, s in trace.nodes.items()
             if s["type"] == "sample" and not site_is_subsample(s)}
    return {**{f"data {k!r}": data_hash(v) for k, v in sorted(data.items())}, **sites,
            "mass matrix seed": None if seed_covariance is None else _digest(*_bytes(seed_covariance, exact=False))}
