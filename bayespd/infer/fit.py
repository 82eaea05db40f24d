"""``fit``: one entry point for NUTS, HMC, SVI and Laplace; results as an ArviZ-style DataTree."""

import json
import time
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import pyro
import torch
import xarray as xr
from pyro.infer.autoguide.initialization import init_to_median, init_to_value

from . import laplace as _laplace
from .laplace import NotPositiveDefiniteHessian
from .checks import check_data, check_observed_shape, check_priors
from .datatree import build_tree
from .mixture import (allocate, cell_log_masses, cells, kept, laplace_log_mass, merged, mode_weights,
                      one_chain, stratified)
from .mode import best_map, modes_json
from .mcmc import ChainSpec, run_chains
from .replay import replay
from .space import Unconstrained, init_trace
from .svi import run_svi

METHODS = ("nuts", "hmc", "svi", "laplace")
MODES = ("best", "weighted")


def unconstrained_covariance(model, data, tree) -> torch.Tensor:
    """Covariance of a fit's posterior draws on Pyro's unconstrained space, latent sites in
    sorted order: a seed for the dense mass matrix (e.g. from a quick SVI fit)."""
    space = Unconstrained(model, data, init_to_median)
    post = tree["posterior"]
    draws = {k: torch.as_tensor(post[k].values).reshape(-1, *space.shapes[k]) for k in space.names}
    return torch.cov(space.unconstrain(draws).T)


def _initial(init_values):
    if not init_values:
        return init_to_median
    dtype = torch.get_default_dtype()
    values = {k: torch.as_tensor(v, dtype=dtype) for k, v in init_values.items()}
    return init_to_value(values=values, fallback=init_to_median)


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


def fit(model, data: dict, method="nuts", *, num_samples=500, num_warmup=500, num_chains=4,
        seed=0, chains="auto", init_values=None, init="median", dense_mass=False,
        mass_matrix_from=None, adapt_mass=True, target_accept=0.8, max_tree_depth=10,
        trajectory_length=None, map_starts=1, modes="best", guide="mvn", svi_steps=2000, svi_lr=0.02,
        svi_rank=None, svi_particles=1, hessian="exact", checkpoint=None, checkpoint_every=50, scene=None,
        constant_data=None, progress=True, observed="y", dims=None, coords=None):
    """Posterior of ``model(**data)`` as an ArviZ-style ``xarray.DataTree``.

    ``data[observed]`` is scored by the sample site of the same name. Input is checked first
    (``bayespd.infer.checks``): NaN data outside (or under) ``data["mask"]``, observations of
    the wrong shape, and, given ``scene``, priors whose support leaves the physical range.
    Initial values: ``init_values`` (other sites at the prior median); ``init="map"`` starts
    at the MAP found from there (L-BFGS on the unconstrained space), or, with
    ``map_starts`` > 1, at the lowest of that many searches, the others from a Latin
    hypercube of the prior (``bayespd.infer.mode``; a warning when two modes lie within 3
    nats; the modes found go to the ``map_modes`` attribute). Laplace uses the same search.
    ``modes="weighted"`` (every method; needs ``map_starts`` > 1) fits every mode
    found whose Laplace mass is within a factor 1000 of the largest (``bayespd.infer.mixture``):
    NUTS/HMC run ``num_chains`` chains from each (seeds ``seed + j num_chains`` for the j-th
    mode; the mode's own Laplace covariance as metric under ``mass_matrix_from="laplace"``),
    split the pooled draws into one cell per mode (joined where chains cross) and mix the
    cells by their modified-harmonic-mean masses; Laplace mixes the modes' Gaussians by their
    Laplace masses, SVI the guides fitted from each mode by their importance-sampling
    evidence (``bayespd.infer.svi.log_evidence``). Every chain of the result holds each
    cell's share of ``num_samples``; the modes, masses and weights go to ``mode_weights``.

    * ``"nuts"`` / ``"hmc"``: ``num_chains`` chains of ``num_warmup`` + ``num_samples``
      (see ``bayespd.infer.mcmc`` for seeds, ``chains="auto" | "sequential" | "processes"``
      and ``checkpoint=<dir>``). ``dense_mass=True`` adapts a full mass matrix;
      ``mass_matrix_from`` seeds it with the covariance of a previous fit's draws (a DataTree,
      e.g. a quick SVI fit) or of the Laplace approximation (``"laplace"``), which
      ``adapt_mass=False`` keeps through warmup (only the step size adapts: warmup windows
      of 25-100 draws estimate a covariance worse than an exact-Hessian Laplace one). NUTS uses
      ``target_accept`` and ``max_tree_depth``; HMC integrates trajectories of length
      ``trajectory_length`` (default 2 pi), i.e. ``trajectory_length / step_size`` leapfrog steps. A model that raises ``NotPositiveDefiniteError`` or
      ``ParameterRangeError`` (a modulus over- or underflowed) in a trajectory gets a divergence (proposal rejected); a
      chain that diverges on every draw raises ``ChainDivergedError``. ``sample_stats``:
      ``lp``, ``energy``, ``step_size``, ``n_steps``, ``diverging``, ``acceptance_rate``
      (+ ``tree_depth`` for NUTS) per draw.
    * ``"svi"``: ``guide`` in ``"normal" | "mvn" | "lowrank" | "flow"`` (``bayespd.infer.svi``),
      ``svi_steps`` of decaying-rate ClippedAdam from ``svi_lr``, ``svi_particles`` ELBO samples
      per step; ``num_samples`` guide draws as one chain. ``sample_stats``: ``svi_loss``.
    * ``"laplace"``: MAP and ``hessian="exact" | "gauss-newton"`` (``bayespd.infer.laplace``);
      ``num_samples`` draws of the Gaussian pushed through the constraint transforms, as one
      chain. ``sample_stats``: the mode and covariance on the unconstrained space.

    Every method then replays the model per draw: ``log_likelihood`` (pointwise, mask and scale
    applied, masked entries 0: ``az.loo`` works), ``posterior_predictive`` (one replicated
    data set per draw) and ``pyro.deterministic`` sites (added to ``posterior``).
    ``observed_data``; ``constant_data``: the other data tensors (e.g. the mask), the
    scene's particle positions and observation points, and ``constant_data``. Given a scene,
    observations get dims ``(point, component)`` with component coords x, y(, z).
    Root attributes: ``method``, ``wall_time_s`` (sampling / optimisation only),
    ``predictive_wall_time_s``, ``num_grad_evals`` (MCMC: potential evaluations including
    warmup; SVI: steps; Laplace: gradient evaluations), ``settings`` (JSON), ``created_at``,
    library versions.
    """
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, not {method!r}")
    if init not in ("median", "map"):
        raise ValueError(f"init must be 'median' or 'map', not {init!r}")
    if map_starts != 1 and init != "map" and method != "laplace":
        raise ValueError("map_starts searches for the MAP to start from: pass init='map' too")
    if modes not in MODES:
        raise ValueError(f"modes must be one of {MODES}, not {modes!r}")
    if modes == "weighted" and (map_starts < 2 or (method != "laplace" and init != "map")):
        raise ValueError("modes='weighted' fits every mode that several MAP searches find: use it "
                         "with map_starts >= 2 (e.g. 8) and, for NUTS, HMC and SVI, init='map'")
    check_data(data, observed)
    pyro.set_rng_seed(seed)  # init_to_median draws from the prior: the seed fixes the start too
    start_init = _initial(init_values)
    trace = init_trace(model, data, start_init)
    check_observed_shape(trace, data, observed, scene)
    if scene is not None:
        check_priors(trace, scene)

    start = time.perf_counter()
    settings = {"num_samples": num_samples, "seed": seed, "observed": observed, "init": init,
                "init_values": sorted(init_values or {}), "map_starts": map_starts, "modes": modes}
    attrs = {}
    search = _Search(map_starts, seed, progress, modes == "weighted")
    if method in ("nuts", "hmc"):
        posterior, stats, grad_evals = _mcmc(
            model, data, method, num_samples, num_warmup, num_chains, seed, chains, start_init,
            init, dense_mass, mass_matrix_from, adapt_mass, target_accept, max_tree_depth,
            trajectory_length, checkpoint, checkpoint_every, observed, progress, search)
        settings.update(num_warmup=num_warmup, num_chains=num_chains, dense_mass=dense_mass,
                        adapt_mass=adapt_mass,
                        mass_matrix_from=mass_matrix_from if isinstance(mass_matrix_from, str)
                        else None if mass_matrix_from is None else "tree")
        settings.update({"nuts": {"target_accept": target_accept, "max_tree_depth": max_tree_depth},
                         "hmc": {"trajectory_length": trajectory_length}}[method])
    elif method == "svi":
        if search.weighted:
            posterior, stats, grad_evals = _weighted_svi(model, data, start_init, observed, num_samples, seed,
                                                         guide, svi_steps, svi_lr, progress, svi_rank,
                                                         svi_particles, search)
        else:
            if init == "map":
                start_init = _map_init(model, data, start_init, search)
            posterior, stats = run_svi(model, data, guide, num_samples, seed, svi_steps, svi_lr,
                                       start_init, progress, svi_rank, svi_particles)
            grad_evals = svi_steps * svi_particles
        settings.update(guide=guide, svi_steps=svi_steps, svi_lr=svi_lr, svi_rank=svi_rank,
                        svi_particles=svi_particles)
    elif search.weighted:
        posterior, stats, grad_evals = _weighted_laplace(model, data, start_init, observed, hessian,
                                                         num_samples, search)
        settings.update(hessian=hessian)
    else:
        space, gaussian, info = _laplace.laplace(model, data, start_init, observed, hessian, progress,
                                                 map_starts, seed)
        posterior = _laplace.draws(space, gaussian, num_samples, seed)
        stats, grad_evals = _laplace.stats(gaussian), info.pop("gradient_evaluations")
        settings.update(hessian=hessian)
        attrs.update(map_potential=info["map_potential"], map_grad_norm=info["map_grad_norm"])
        search.modes = info["map_modes"]
    wall_time = time.perf_counter() - start
    if search.modes is not None:
        attrs["map_modes"] = search.modes
    if search.weights is not None:
        attrs["mode_weights"] = search.weights

    start = time.perf_counter()
    pyro.set_rng_seed(seed)
    posterior = {k: np.asarray(v) for k, v in posterior.items()}
    loglik, predictive, deterministic = replay(model, data, posterior, observed, progress)
    dims, coords, const = _scene_layout(scene, data, observed, dims, coords, constant_data)
    groups = {
        "posterior": {**posterior, **deterministic},
        "sample_stats": stats,
        "log_likelihood": {observed: loglik},
        "posterior_predictive": {observed: predictive},
        "observed_data": {observed: np.asarray(data[observed])},
    }
    if const:
        groups["constant_data"] = const
    attrs.update({
        "method": method,
        "wall_time_s": wall_time,
        "predictive_wall_time_s": time.perf_counter() - start,
        "num_grad_evals": grad_evals,
        "settings": json.dumps(settings),
        "created_at": datetime.now(timezone.utc).isoformat(),
        "inference_library": "pyro",
        "inference_library_version": pyro.__version__,
        "torch_version": str(torch.__version__),  # TorchVersion would not write to NetCDF
    })
    return build_tree(groups, attrs, dims, coords)


@dataclass
class _Search:
    """How the MAP is searched for (``best_map``), and the modes the search found; with
    ``weighted``, the modes fitted and their weights (JSON)."""

    starts: int
    seed: int
    progress: bool
    weighted: bool = False
    modes: str | None = None
    weights: str | None = None


def _map_init(model, data, init, search: _Search):
    """An init strategy at the MAP."""
    space = Unconstrained(model, data, init)
    result, search.modes = best_map(space, model, data, init, search.starts, search.seed,
                                    progress=search.progress)
    return _laplace.init_at(space, result[0])


def _modes_to_fit(model, data, init, observed, hessian, search: _Search):
    """(space, the modes worth fitting (``mixture.kept``), their Laplace log masses, gradient
    evaluations of the search); records every mode found in ``search.modes``."""
    space, found, evaluations = _laplace.modes(model, data, init, observed, hessian, search.progress,
                                               search.starts, search.seed, warn=False)
    search.modes = modes_json(space, found)
    masses = [laplace_log_mass(u, h) for _, u, _, h in found]
    chosen = kept(found, masses)
    return space, [found[i] for i in chosen], [masses[i] for i in chosen], evaluations


def _record_weights(search, space, fitted, laplace_masses, masses, counts, **extra):
    weights = mode_weights(masses)
    search.weights = modes_json(space, fitted, laplace_log_mass=laplace_masses, log_mass=list(masses),
                                weight=weights.tolist(), draws=[int(c) for c in counts], **extra)


def _weighted_laplace(model, data, init, observed, hessian, num_samples, search):
    """Laplace approximations at every mode with a positive definite Hessian, mixed by their
    Laplace masses."""
    space, fitted, masses, evaluations = _modes_to_fit(model, data, init, observed, hessian, search)
    pairs = [(m, w) for m, w in zip(fitted, masses) if w is not None] or [(fitted[0], None)]
    gaussians = [_laplace.Gaussian(z, h, space.labels)  # none positive definite: raises, naming the fix
                 for (z, _, _, h), _ in pairs]
    fitted, masses = [m for m, _ in pairs], [w for _, w in pairs]
    counts = allocate(mode_weights(masses), num_samples)
    per_mode = [_laplace.draws(space, g, int(c), search.seed + j)
                for j, (g, c) in enumerate(zip(gaussians, counts))]
    _record_weights(search, space, fitted, masses, masses, counts)
    return one_chain(per_mode, counts), _laplace.stats(gaussians[0]), evaluations


def _weighted_svi(model, data, init, observed, num_samples, seed, guide, steps, lr, progress, rank,
                  particles, search):
    """A guide fitted from every mode worth fitting, mixed by their evidence estimates."""
    space, fitted, laplace_masses, evaluations = _modes_to_fit(model, data, init, observed, "exact", search)
    fits = [run_svi(model, data, guide, num_samples, seed + j, steps, lr, _laplace.init_at(space, z),
                    progress, rank, particles, evidence=True) for j, (z, *_) in enumerate(fitted)]
    masses = [f[2] for f in fits]
    counts = allocate(mode_weights(masses), num_samples)
    _record_weights(search, space, fitted, laplace_masses, masses, counts)
    stats = xr.concat([f[1] for f in fits], dim="svi_mode")
    return one_chain([f[0] for f in fits], counts), stats, evaluations + steps * particles * len(fitted)


def _mcmc(model, data, kernel, num_samples, num_warmup, num_chains, seed, chains, init_fn, init,
          dense_mass, mass_matrix_from, adapt_mass, target_accept, max_tree_depth, trajectory_length,
          checkpoint, checkpoint_every, observed, progress, search):
    if not adapt_mass and mass_matrix_from is None:
        raise ValueError("adapt_mass=False keeps a seeded mass matrix: give mass_matrix_from "
                         "('laplace' or a DataTree), or leave adaptation on")
    if isinstance(mass_matrix_from, str) and mass_matrix_from != "laplace":
        raise ValueError("mass_matrix_from must be a DataTree or 'laplace', not "
                         f"{mass_matrix_from!r}")
    options = ({"target_accept_prob": target_accept, "max_tree_depth": max_tree_depth}
               if kernel == "nuts" else {"trajectory_length": trajectory_length,
                                         "target_accept_prob": target_accept})
    options["full_mass"] = bool(dense_mass or mass_matrix_from is not None)
    options["adapt_mass_matrix"] = bool(adapt_mass)
    tree_covariance = (None if mass_matrix_from is None or isinstance(mass_matrix_from, str)
                       else unconstrained_covariance(model, data, mass_matrix_from))

    def chains_from(start, covariance, offset=0, folder=None):
        spec = ChainSpec(model, data, kernel, num_warmup, num_samples, seed + offset, start, options,
                         covariance, progress, None if folder is None else Path(folder), checkpoint_every)
        return run_chains(spec, num_chains, chains)

    if search.weighted:
        return _weighted_chains(model, data, init_fn, observed, mass_matrix_from, tree_covariance,
                                num_chains, num_samples, checkpoint, chains_from, search)
    seed_covariance = tree_covariance
    if mass_matrix_from == "laplace":
        space, gaussian, info = _laplace.laplace(model, data, init_fn, observed, "exact", progress,
                                                 search.starts, seed)
        search.modes = info["map_modes"]
        seed_covariance = gaussian.covariance
        if init == "map":
            init_fn = _laplace.init_at(space, gaussian.mean)
    if init == "map" and mass_matrix_from != "laplace":
        init_fn = _map_init(model, data, init_fn, search)
    return chains_from(init_fn, seed_covariance, folder=checkpoint)


def _weighted_chains(model, data, init_fn, observed, mass_matrix_from, tree_covariance, num_chains,
                     num_samples, checkpoint, chains_from, search):
    """Chains at every mode worth fitting; their pooled draws split into the modes' cells and
    mixed by the cells' modified-harmonic-mean masses (``bayespd.infer.mixture``)."""
    space, fitted, laplace_masses, evaluations = _modes_to_fit(model, data, init_fn, observed, "exact",
                                                               search)
    positive = [(z, h) for (z, _, _, h), m in zip(fitted, laplace_masses) if m is not None]
    if not positive:
        raise NotPositiveDefiniteHessian(
            "no mode found has a positive definite Hessian, so the modes' cells are not defined: "
            "use modes='best', or more map_starts")
    precisions = [h if m is not None else min(positive, key=lambda p: float((p[0] - z).norm()))[1]
                  for (z, _, _, h), m in zip(fitted, laplace_masses)]  # on a kink: the nearest one's
    runs = []
    for j, ((z, *_), h) in enumerate(zip(fitted, precisions)):
        covariance = (_laplace.Gaussian(z, h, space.labels).covariance if mass_matrix_from == "laplace"
                      else tree_covariance)
        folder = None if checkpoint is None else Path(checkpoint) / f"mode{j}"
        runs.append(chains_from(_laplace.init_at(space, z), covariance, j * num_chains, folder))
        evaluations += runs[-1][2]
    pooled = {k: np.concatenate([r[0][k] for r in runs]).reshape(-1, *runs[0][0][k].shape[2:])
              for k in runs[0][0]}
    stats = {k: np.concatenate([r[1][k] for r in runs]).reshape(-1) for k in runs[0][1]}
    z_draws = space.unconstrain({k: torch.as_tensor(v) for k, v in pooled.items()}).numpy()
    groups = np.repeat(np.arange(len(fitted)), len(stats["lp"]) // len(fitted))
    labels, joined = merged(cells(z_draws, [m[0].numpy() for m in fitted], [h.numpy() for h in precisions]),
                            groups, len(fitted))
    masses = cell_log_masses(z_draws, stats["lp"], labels, len(fitted))
    counts = allocate(mode_weights(masses), num_samples)
    _record_weights(search, space, fitted, laplace_masses, masses, counts, cell=joined)
    return (stratified(pooled, labels, counts, num_chains), stratified(stats, labels, counts, num_chains),
            evaluations)
