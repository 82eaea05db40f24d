"""``fit``: one entry point for every inference method; results as an ArviZ-style DataTree.

**Methods.** ``METHODS`` maps a name to a method class (``bayespd.infer.method.Method``): a
frozen dataclass whose fields are its settings and whose ``run(model, data, init, search)``
returns ``Draws``. Built in: ``"nuts"`` / ``"hmc"`` (``NUTS``, ``HMC``), ``"svi"`` (``SVI``)
and ``"laplace"`` (``Laplace``). To add one, subclass ``Method`` (its ``name``, its fields,
its ``run``) and ``register`` it; ``fit(model, data, "<name>", ...)`` then runs it (an object
of it runs unregistered too: ``fit(model, data, Prior(...))``), with the checks, start, replay
and DataTree every method gets::

    @dataclass(frozen=True)
    class Prior(Method):
        name = "prior"
        def run(self, model, data, init, search): ...

    register(Prior)
"""

import json
import time
from dataclasses import replace
from datetime import datetime, timezone

import numpy as np
import xarray as xr
import pyro
import torch
from pyro.infer.autoguide.initialization import init_to_median, init_to_value

from bayespd.validate import finite

from .checks import (as_tensors, check_arguments, check_continuous, check_data, check_observed_shape, check_priors,
                     trace_priors)
from .datatree import SAMPLE_DIMS, _dataset, build_tree
from .laplace import Laplace
from .method import Method
from .replay import replay, thinned
from .samplers import HMC, NUTS
from .search import Search
from .space import init_trace
from .svi import SVI

METHODS = {m.name: m for m in (NUTS, HMC, SVI, Laplace)}


def register(method: type[Method]) -> type[Method]:
    """Add ``method`` (a ``Method`` subclass) to ``METHODS`` under its ``name``; returns it."""
    if not (isinstance(method, type) and issubclass(method, Method) and isinstance(getattr(method, "name", None), str)):
        raise TypeError(f"register takes a Method subclass with a name, not {method!r}")
    if METHODS.get(method.name, method) is not method:
        raise ValueError(f"a method named {method.name!r} is registered already ({METHODS[method.name].__name__})")
    METHODS[method.name] = method
    return method


def settings_of(method, keywords: dict) -> Method:
    """The settings object of a fit: ``method`` (a name in ``METHODS``) built from ``keywords``,
    or ``method`` (a settings object) with ``keywords`` replacing its fields."""
    if isinstance(method, str):
        if method not in METHODS:
            raise ValueError(f"method must be one of {tuple(METHODS)} or a settings object such as "
                             f"bayespd.infer.NUTS(...), not {method!r}")
        cls = METHODS[method]
    elif isinstance(method, Method):
        cls = type(method)
    else:
        raise TypeError(f"method must be a name in {tuple(METHODS)} or a Method object, not {type(method).__name__}")
    foreign = sorted(set(keywords) - set(cls.settings()))
    if foreign:
        raise TypeError(f"{', '.join(foreign)}: not a setting of method {cls.name!r} ({cls.__name__}); "
                        f"its settings are {', '.join(cls.settings())}")
    return cls(**keywords) if isinstance(method, str) else replace(method, **keywords)


def _initial(init_values):
    if not init_values:
        return init_to_median
    dtype = torch.get_default_dtype()
    values = {k: finite(f"init_values[{k!r}]", torch.as_tensor(v, dtype=dtype), "start from finite values")
              for k, v in init_values.items()}
    return init_to_value(values=values, fallback=init_to_median)


def fit(model, data: dict, method="nuts", **settings):
    """Posterior of ``model(**data)`` as an ArviZ-style ``xarray.DataTree``.

    ``method`` is a name in ``METHODS`` whose settings are the keywords
    (``fit(model, data, "nuts", num_samples=300)``), or a settings object such as
    ``NUTS(num_samples=300)``, which keywords then override (``fit(model, data, nuts, seed=1)``:
    one object reused across fits). A keyword that is no setting of the method raises
    ``TypeError`` naming its settings. Settings: ``Method`` (shared), ``NUTS``, ``HMC``, ``SVI``,
    ``Laplace``.

    Input is checked first (``bayespd.infer.checks``; numpy arrays in ``data`` become
    tensors): NaN data outside (or under) ``data["mask"]``, observations of the wrong shape,
    discrete priors, and, given ``scene``, priors whose support leaves the physical range. The seed fixes the start (``init_to_median`` draws from
    the prior). Every method then replays the model per draw (``predictive=True``, the
    default; ``predictive=n``: n draws evenly spaced along the chains, the groups' ``draw``
    coordinate naming them; ``predictive=False``: no replay, none of these groups):
    ``log_likelihood`` (pointwise, mask and scale applied, masked entries 0: ``az.loo``
    works), ``posterior_predictive`` and ``pyro.deterministic`` sites (added to ``posterior``,
    or to ``posterior_predictive`` when thinned). One factorisation serves every draw
    (``bayespd.infer.replay``). ``observed_data``; ``constant_data``:
    the other data tensors, the scene's particle positions and observation points, and
    ``constant_data``; given a scene, observations get dims ``(point, component)``. A model
    with a ``diagnostics(draws)`` method (draws: arrays (chain, draw, ...)) adds the arrays it
    returns to ``sample_stats`` (a reduced scene's error estimate at every draw). Root
    attributes: ``method``, ``wall_time_s`` (sampling / optimisation only),
    ``predictive_wall_time_s``, ``num_grad_evals``, ``settings`` (JSON), ``map_modes`` and
    ``mode_weights`` (when searched), ``created_at``, library versions.
    """
    s = settings_of(method, settings)
    data = as_tensors(data)
    check_arguments(model, data)
    check_data(data, s.observed)
    pyro.set_rng_seed(s.seed)  # init_to_median draws from the prior: the seed fixes the start too
    init = _initial(s.init_values)
    trace = init_trace(model, data, init)
    check_observed_shape(trace, data, s.observed, s.scene)
    check_continuous(trace_priors(trace))
    if s.scene is not None:
        check_priors(trace_priors(trace), s.scene)

    start = time.perf_counter()
    search = Search.of(s)
    posterior, stats, grad_evals, attrs = s.run(model, data, init, search)
    wall_time = time.perf_counter() - start
    attrs = dict(attrs or {})
    if search.modes is not None:
        attrs["map_modes"] = search.modes
    if search.weights is not None:
        attrs["mode_weights"] = search.weights

    start = time.perf_counter()
    pyro.set_rng_seed(s.seed)
    posterior = {k: np.asarray(v) for k, v in posterior.items()}
    replayed = _replayed(model, data, posterior, s)
    extra = getattr(model, "diagnostics", lambda draws: {})(posterior)
    if extra:  # stats: arrays (chain, draw), or a Dataset (Laplace)
        stats = (stats.assign({k: (("chain", "draw"), v) for k, v in extra.items()})
                 if isinstance(stats, xr.Dataset) else {**stats, **extra})
    dims, coords, const = _scene_layout(s.scene, data, s.observed, s.dims, s.coords, s.constant_data)
    groups = {
        "posterior": posterior,
        "sample_stats": stats,
        "observed_data": {s.observed: np.asarray(data[s.observed])},
    }
    if replayed is not None:
        draws, loglik, predictive, deterministic = replayed
        every = len(draws) == next(iter(posterior.values())).shape[1]
        if every:  # deterministic sites beside the draws they belong to
            groups["posterior"] = {**posterior, **deterministic}
        groups["log_likelihood"] = _at_draws({s.observed: loglik}, draws, dims, coords)
        groups["posterior_predictive"] = _at_draws({s.observed: predictive, **({} if every else deterministic)},
                                                   draws, dims, coords)
    if const:
        groups["constant_data"] = const
    attrs.update({
        "method": s.name,
        "wall_time_s": wall_time,
        "predictive_wall_time_s": time.perf_counter() - start,
        "num_grad_evals": grad_evals,
        "settings": json.dumps(s.record()),
        "created_at": datetime.now(timezone.utc).isoformat(),
        "inference_library": "pyro",
        "inference_library_version": pyro.__version__,
        "torch_version": str(torch.__version__),  # TorchVersion would not write to NetCDF
    })
    return build_tree(groups, attrs, dims, coords)


def _replayed(model, data, posterior, s):
    """(draw indices, log-likelihood, replicated data, deterministic sites) of the draws the
    ``predictive`` setting asks for, or None for ``predictive=False``."""
    if s.predictive is False:
        return None
    num_chains, num_draws = next(iter(posterior.values())).shape[:2]
    draws = thinned(num_draws, num_chains, s.predictive)
    return (draws, *replay(model, data, posterior, s.observed, s.progress, draws))


def _at_draws(arrays, draws, dims, coords):
    """A (chain, draw, ...) group whose ``draw`` coordinate is the replayed draws' indices."""
    return _dataset(arrays, SAMPLE_DIMS, dims, coords).assign_coords(draw=draws)


def _scene_layout(scene, data, observed, dims, coords, constant_data):
    """Default dims/coords for observations ``(point, component)`` and the scene's geometry
    as constant data; the user's ``dims`` / ``coords`` / ``constant_data`` take precedence."""
    dims, coords, const = dict(dims or {}), dict(coords or {}), {}
    for k, v in data.items():
        if k != observed and isinstance(v, (torch.Tensor, np.ndarray)):
            const[k] = np.asarray(v)
            if tuple(np.shape(v)) == tuple(np.shape(data[observed])):
                dims.setdefault(k, dims.get(observed, ["point", "component"] if scene else []))
    if scene is not None:
        dim = scene.particles.dim
        dims.setdefault(observed, ["point", "component"])
        coords.setdefault("component", ["x", "y", "z"][:dim])
        const["particle_x"] = np.asarray(scene.particles.x)
        dims.setdefault("particle_x", ["particle", "component"])
        if scene.observation is not None:
            const["observation_points"] = np.asarray(scene.observation.points)
            dims.setdefault("observation_points", ["point", "component"])
    const.update({k: np.asarray(v) for k, v in (constant_data or {}).items()})
    return dims, coords, const
