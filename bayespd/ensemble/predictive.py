"""Posterior-predictive crack ensembles (Dodwell 2019 §3: "a distribution of crack paths").

``ensemble(tree, scene, n, store=DIR)`` draws pairs (posterior draw, Brownian seed), runs the
stochastic fracture model of Dodwell 2019 eq 4 for each (``scene.realise``) and
aggregates the results (``stats.aggregate``). Two ensembles are run:

* ``posterior``: realisation i takes draw d_i of the fitted tree's ``posterior`` group and
  Brownian seed b_i; its spread is the total (epistemic + aleatoric) predictive spread;
* ``mean``: realisation i takes the posterior mean and the same seed b_i; its spread is the
  aleatoric (Brownian) part alone.

(d_i, b_i) depend only on (seed, i) (``numpy.random.SeedSequence([seed, i])``), so any single
realisation can be re-run exactly (``rerun``), a larger n extends a smaller one,
and results do not depend on where, in which order or in which company realisations run.
A task runs BATCH realisations in lock-step (``scene.realise_batch``: they share the
half solves of one factor, bit for bit as if alone); each result is written to the store as
its batch arrives, so a crash loses the batches in flight, and a re-run skips finished
realisations. No Pyro here.

Devices: ``device=`` runs each realisation (the scene's build and the run) under
``torch.device(device)``, so the tensors the driver creates live there; nothing in the
ensemble code names a device, and results come back as host numpy arrays. The fracture
driver's sparse factorisations are scipy / CHOLMOD on the host, so a CUDA device moves the
torch bond arithmetic only; tested on CPU (no GPU was available to test CUDA).
"""
from __future__ import annotations

import hashlib
from functools import partial

import numpy as np

from bayespd.linalg.sparse import ConvergenceError, NotPositiveDefiniteError
from bayespd.solvers.dynamics import NumericalInstabilityError
from bayespd.validate import device as check_device

from .execution import check_workers, run_tasks
from .scene import BATCH, FractureScene, realise, realise_batch
from .stats import aggregate
from .store import EnsembleStore

KINDS = ("posterior", "mean")
# what a realisation's own numbers cause: recorded as its (permanent) outcome
NUMERICAL_ERRORS = (NumericalInstabilityError, NotPositiveDefiniteError, ConvergenceError)


def posterior_draws(tree, names) -> dict:
    """``{name: (chain * draw,)}`` float64 draws of the scalar parameters ``names``."""
    if "posterior" not in tree.children:
        raise ValueError("the tree has no 'posterior' group: pass the result of bayespd.infer.fit "
                         "(or bayespd.infer.load of its NetCDF file)")
    post = tree["posterior"]
    missing = [k for k in names if k not in post]
    if missing:
        raise ValueError(f"the posterior has no variable(s) {missing} (it has {sorted(post.data_vars)}): "
                         "fit a model with these sample sites, or give the scene other params")
    out = {}
    for k in names:
        v = post[k]
        if set(v.dims) != {"chain", "draw"}:
            raise ValueError(f"posterior variable {k!r} has dims {v.dims}: the scene needs scalar "
                             "parameters (dims chain, draw)")
        out[k] = np.asarray(v.transpose("chain", "draw").values, dtype=np.float64).reshape(-1)
    return out


def realisation_inputs(draws: dict, seed: int, i: int, kind: str = "posterior"):
    """(params, draw index, Brownian seed) of realisation ``i``: draw index uniform over the
    posterior draws (-1 for the ``mean`` ensemble, which takes the posterior mean), seed a
    uint32; both from ``SeedSequence([seed, i])`` alone."""
    if kind not in KINDS:
        raise ValueError(f"kind must be one of {KINDS}, not {kind!r}")
    choose, noise = np.random.SeedSequence([int(seed), int(i)]).spawn(2)
    brownian = int(noise.generate_state(1, np.uint32)[0])
    if kind == "mean":
        return {k: float(v.mean()) for k, v in draws.items()}, -1, brownian
    d = int(np.random.default_rng(choose).integers(len(next(iter(draws.values())))))
    return {k: float(v[d]) for k, v in draws.items()}, d, brownian


def rerun(tree, scene: FractureScene, i: int, kind: str = "posterior", seed: int = 0, device=None) -> dict:
    """Realisation ``i`` of an ensemble run again, bit for bit (``scene.realise``)."""
    check_device("device", device)
    params, _, brownian = realisation_inputs(posterior_draws(tree, scene.params), seed, i, kind)
    return realise(scene, params, brownian, device)


def _plan(scene: FractureScene, draws: dict, seed: int) -> dict:
    """What the stored realisations depend on (n does not: a larger n extends a smaller one)."""
    digest = hashlib.sha256()
    for k in sorted(draws):
        digest.update(k.encode() + draws[k].tobytes())
    build = scene.build
    described = (f"{build.func.__module__}.{build.func.__qualname__} {build.args!r} {sorted(build.keywords.items())!r}"
                 if isinstance(build, partial) else f"{build.__module__}.{getattr(build, '__qualname__', build)}")
    return {"seed": int(seed), "posterior_sha256": digest.hexdigest(), "build": described,
            "params": list(scene.params), "load_factors": scene.load_factors.tolist(), "dt": scene.dt,
            "hold": scene.hold, "max_steps": scene.max_steps, "path_threshold": scene.path_threshold,
            "particles": len(scene.x), "operator": f"{scene.tangent}:{scene.max_rank}",
            "zone_sha256": None if scene.zone is None else hashlib.sha256(scene.zone.tobytes()).hexdigest()}


def _task(scene, items, device):
    """A batch of realisations in a worker (``realise_batch``); a numerical blow-up
    (``NUMERICAL_ERRORS``: it would happen again) becomes an error record (kept, and counted in
    the results: never hidden); any other error (out of memory, a bad device, a bug) is raised,
    so a re-run tries that realisation again."""
    out = []
    for result in realise_batch(scene, items, device):
        if isinstance(result, NUMERICAL_ERRORS):
            result = {"error": f"{type(result).__name__}: {result}"}
        elif isinstance(result, BaseException):
            raise result
        out.append(result)
    return out


def _tasks(keys: list, workers: int) -> list:
    """``keys`` cut into tasks of at most BATCH realisations, as even as they can be, and as
    many as a multiple of ``workers`` allows: the last round of tasks keeps every worker
    busy (25 tasks of 8 on 2 workers left one idle for a task's length)."""
    check_workers(workers)
    if not keys:
        return []
    count = -(-len(keys) // BATCH)
    count = min(len(keys), -(-count // workers) * workers)
    bounds = [len(keys) * t // count for t in range(count + 1)]
    return [tuple(keys[a:b]) for a, b in zip(bounds, bounds[1:])]


def _prepare(tree, scene, n, n_mean, seed, store):
    n_mean = n if n_mean is None else n_mean
    for name, value in (("n", n), ("n_mean", n_mean)):
        if not (isinstance(value, (int, np.integer)) and value >= 0):
            raise ValueError(f"{name} must be a non-negative integer, got {value!r}")
    if n < 2 or n_mean == 1:
        raise ValueError("ask for at least 2 realisations per ensemble (n_mean may be 0): "
                         "a spread needs two")
    if not isinstance(scene, FractureScene):
        raise ValueError("scene must be a FractureScene (see bayespd.ensemble.scene)")
    draws = posterior_draws(tree, scene.params)
    st = EnsembleStore(store, _plan(scene, draws, seed))
    inputs = {(kind, i): realisation_inputs(draws, seed, i, kind)
              for kind, count in zip(KINDS, (n, n_mean)) for i in range(count)}
    return st, inputs


def pending(tree, scene: FractureScene, n: int, *, store, n_mean: int | None = None, seed: int = 0) -> list:
    """The (kind, i) realisations of this plan that ``store`` does not hold yet."""
    st, inputs = _prepare(tree, scene, n, n_mean, seed, store)
    return [key for key in inputs if not st.done(*key)]


def ensemble(tree, scene: FractureScene, n: int, *, store, n_mean: int | None = None, seed: int = 0,
             scheduler=None, workers: int = 2, device=None, progress: bool = True):
    """Run (or resume) the two ensembles and return the aggregated ``xarray.Dataset`` (also
    written atomically to ``store/ensemble.nc``). ``n`` posterior realisations, ``n_mean``
    (default n) at the posterior mean; ``store``: the directory of realisation files;
    ``scheduler``: None (local: ``workers`` processes, 1 = in this process), a
    ``distributed.Client`` or a scheduler address; ``workers`` also sets the tasks' count
    to a multiple of it (``_tasks``: pass a Dask cluster's worker count for the same
    balance); ``device``: the torch device of each realisation's tensors (default CPU), checked
    before any work."""
    check_device("device", device)
    st, inputs = _prepare(tree, scene, n, n_mean, seed, store)
    todo = {key: (params, brownian) for key, (params, _, brownian) in inputs.items() if not st.done(*key)}
    batches = {keys: ([todo[key] for key in keys], device) for keys in _tasks(list(todo), workers)}

    def write(keys, results):
        for key, result in zip(keys, results):
            st.write(*key, result)

    run_tasks(_task, batches, write, shared=scene, scheduler=scheduler, workers=workers,
              progress=progress, label=f"batches of {BATCH} realisations")
    ds = aggregate([(kind, i, st.read(kind, i), *inputs[kind, i]) for kind, i in inputs], scene, seed)
    st.save_dataset(ds)
    return ds
