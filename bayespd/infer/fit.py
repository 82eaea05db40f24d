"""Fit a Pyro model by NUTS or full-rank Gaussian SVI; results as an ArviZ-style DataTree."""

import json
import time
from collections import defaultdict
from datetime import datetime, timezone

import numpy as np
import pyro
import torch
import xarray as xr
from pyro import poutine
from pyro.infer import MCMC, NUTS, SVI, Trace_ELBO
from pyro.infer.autoguide import AutoMultivariateNormal
from pyro.infer.autoguide.initialization import InitMessenger, init_to_median, init_to_value
from pyro.ops.integrator import register_exception_handler
from pyro.poutine.util import site_is_subsample
from pyro.optim import ClippedAdam
from torch.distributions import biject_to
from tqdm.auto import tqdm

from bayespd.materials import NonFiniteParameterError
from bayespd.sparse import NotPositiveDefiniteError

from .datatree import build_tree


class _RecordingNUTS(NUTS):
    """NUTS that records per-draw statistics and counts potential-energy evaluations.

    After warmup, every ``sample`` appends to ``self.stats``: ``lp`` (minus the potential
    energy, i.e. the log joint density on the unconstrained space, log-Jacobians included),
    ``energy`` (Hamiltonian at the start of the trajectory), ``step_size``, ``tree_depth``
    (number of trajectory doublings; at most ``2**tree_depth - 1`` leapfrog steps),
    ``n_steps`` (leapfrog steps), ``diverging`` and ``acceptance_rate`` (mean Metropolis
    acceptance probability over the trajectory, the quantity step-size adaptation targets).
    """

    def __init__(self, model, seed_covariance=None, **kwargs):
        super().__init__(model, **kwargs)
        self.seed_covariance = seed_covariance
        self.stats = defaultdict(list)
        self.num_grad_evals = 0

    def _initialize_model_properties(self, model_args, model_kwargs):
        super()._initialize_model_properties(model_args, model_kwargs)
        potential_fn = self.potential_fn

        def counted(z):
            self.num_grad_evals += 1
            return potential_fn(z)

        self.potential_fn = counted

    def _initialize_adapter(self):
        """Start from ``seed_covariance`` (unconstrained space, sites in sorted order) as the
        inverse mass matrix, then find a step size for it; adaptation continues as usual."""
        super()._initialize_adapter()
        if self.seed_covariance is not None:
            names = tuple(sorted(self.initial_params))
            self.mass_matrix_adapter.inverse_mass_matrix = {names: self.seed_covariance}
            self._adapter.reset_step_size_adaptation(self._initial_params)

    def _sample_r(self, name):
        r, r_unscaled = super()._sample_r(name)
        self._energy = float(self._kinetic_energy(r_unscaled) + self._potential_energy_last)
        return r, r_unscaled

    def _build_tree(self, z, r, z_grads, log_slice, direction, tree_depth, energy_current):
        self._depth = max(self._depth, tree_depth + 1)
        return super()._build_tree(z, r, z_grads, log_slice, direction, tree_depth, energy_current)

    def _build_basetree(self, *args):
        tree = super()._build_basetree(*args)
        self._n_steps += 1
        self._sum_accept += float(tree.sum_accept_probs)
        self._diverging |= bool(tree.diverging)
        return tree

    def sample(self, params):
        self._depth, self._n_steps, self._sum_accept, self._diverging = 0, 0, 0.0, False
        z = super().sample(params)
        if self._t > self._warmup_steps:
            s = self.stats
            s["lp"].append(-float(self._potential_energy_last))
            s["energy"].append(self._energy)
            s["step_size"].append(float(self.step_size))
            s["tree_depth"].append(self._depth)
            s["n_steps"].append(self._n_steps)
            s["diverging"].append(self._diverging)
            s["acceptance_rate"].append(self._sum_accept / max(self._n_steps, 1))
        return z


def _max_plate_nesting(model, data, init):
    """As Pyro guesses it, but running the model at the initial values, not at prior draws
    (which may make the model raise)."""
    with poutine.block():
        trace = poutine.trace(InitMessenger(init)(model)).get_trace(**data)
    dims = [frame.dim for site in trace.nodes.values() if site["type"] == "sample"
            for frame in site["cond_indep_stack"] if frame.vectorized]
    return -min(dims) if dims else 0


def unconstrained_covariance(model, data, tree) -> torch.Tensor:
    """Covariance of a fit's posterior draws on Pyro's unconstrained space, latent sites in
    sorted order: a seed for NUTS's dense mass matrix (e.g. from a quick SVI fit)."""
    with poutine.block():
        trace = poutine.trace(model).get_trace(**data)
    columns = []
    for name in sorted(n for n, s in trace.nodes.items() if s["type"] == "sample"
                       and not s["is_observed"] and not site_is_subsample(s)):
        draws = torch.as_tensor(tree["posterior"][name].values).reshape(-1, trace.nodes[name]["value"].numel())
        columns.append(biject_to(trace.nodes[name]["fn"].support).inv(draws))
    return torch.cov(torch.cat(columns, dim=1).T)


def _run_nuts(model, data, num_samples, num_warmup, num_chains, seed, init, progress, dense_mass,
              seed_covariance):
    register_exception_handler(
        "bayespd_numerical_trouble",
        lambda e: isinstance(e, (NotPositiveDefiniteError, NonFiniteParameterError)),
        warn_on_overwrite=False,
    )
    samples, stats, grad_evals = [], [], 0
    plates = _max_plate_nesting(model, data, init)
    for chain in range(num_chains):
        pyro.set_rng_seed(seed + chain)
        kernel = _RecordingNUTS(model, init_strategy=init, max_plate_nesting=plates,
                                full_mass=dense_mass or seed_covariance is not None,
                                seed_covariance=seed_covariance)
        mcmc = MCMC(kernel, num_samples=num_samples, warmup_steps=num_warmup,
                    disable_progbar=not progress)
        mcmc.run(**data)
        samples.append(mcmc.get_samples())
        stats.append(kernel.stats)
        grad_evals += kernel.num_grad_evals
    posterior = {k: torch.stack([s[k] for s in samples]) for k in samples[0]}
    sample_stats = {k: np.array([s[k] for s in stats]) for k in stats[0]}
    return posterior, sample_stats, grad_evals


def _run_svi(model, data, num_samples, seed, steps, lr, init, progress):
    pyro.set_rng_seed(seed)
    with pyro.get_param_store().scope():
        guide = AutoMultivariateNormal(model, init_loc_fn=init)
        optim = ClippedAdam({"lr": lr, "lrd": 0.1 ** (1 / steps)})  # lr / 10 at the end
        svi = SVI(model, guide, optim, Trace_ELBO())
        losses = [svi.step(**data) for _ in tqdm(range(steps), "SVI", disable=not progress)]
        with torch.no_grad():
            draws = [guide(**data) for _ in range(num_samples)]
    posterior = {k: torch.stack([d[k] for d in draws])[None] for k in draws[0]}
    return posterior, xr.Dataset({"svi_loss": ("svi_step", np.array(losses))})


def _replay(model, data, posterior, observed, progress):
    """Run the model once per draw, conditioned on it. Returns the pointwise log-likelihood
    of the data (mask and scale applied, masked entries 0), one replicated data set per draw
    and the ``pyro.deterministic`` sites, each shaped ``(chain, draw, ...)``."""
    loglik, predictive, deterministic = [], [], defaultdict(list)
    num_chains, num_draws = next(iter(posterior.values())).shape[:2]
    with torch.no_grad():
        for c, d in tqdm(np.ndindex(num_chains, num_draws), "predictive",
                         total=num_chains * num_draws, disable=not progress):
            draw = {k: v[c, d] for k, v in posterior.items()}
            trace = poutine.trace(poutine.condition(model, data=draw)).get_trace(**data)
            trace.compute_log_prob(lambda name, site: name == observed)
            site = trace.nodes[observed]
            loglik.append(site["log_prob"])
            predictive.append(site["fn"].sample())
            for name, s in trace.nodes.items():
                if s["type"] == "sample" and s["infer"].get("_deterministic"):
                    deterministic[name].append(s["value"])

    def stack(values):
        return torch.stack(values).reshape(num_chains, num_draws, *values[0].shape)

    return stack(loglik), stack(predictive), {k: stack(v) for k, v in deterministic.items()}


def _numpy(arrays):
    return {k: v.detach().cpu().numpy() for k, v in arrays.items()}


def fit(model, data: dict, method="nuts", *, num_samples=500, num_warmup=500, num_chains=2,
        seed=0, svi_steps=2000, svi_lr=0.02, init_values=None, progress=True, observed="y",
        dims=None, coords=None, dense_mass=False, mass_matrix_from=None):
    """Sample the posterior of ``model(**data)`` and return an ArviZ-style ``xarray.DataTree``.

    ``data[observed]`` is the observed tensor, scored by the sample site of the same name.

    * ``"nuts"``: Pyro NUTS. The ``num_chains`` chains run one after another in this
      process (Pyro's multi-process mode would use ``cpu_count() - 1`` workers, a single one
      on a 2-core machine), chain ``c`` seeded with ``seed + c``. Chains start at
      ``init_values`` (other sites at the prior median), else at the prior median. A
      ``NotPositiveDefiniteError`` raised by the model inside a trajectory counts as a
      divergence (the proposal is rejected) instead of crashing. ``dense_mass=True`` adapts
      a full mass matrix (for correlated posteriors, e.g. bulk modulus against horizon);
      ``mass_matrix_from=<DataTree>`` seeds it with the covariance of that fit's draws on
      the unconstrained space (e.g. a quick SVI fit), which saves most of the early warmup.
      ``sample_stats``: ``lp``, ``energy``, ``step_size``, ``tree_depth``, ``n_steps``,
      ``diverging``, ``acceptance_rate`` per draw (see ``_RecordingNUTS``).
    * ``"svi"``: ``AutoMultivariateNormal`` guide (loc at ``init_values`` / prior median),
      ``Trace_ELBO``, ``svi_steps`` steps of ``ClippedAdam`` whose learning rate decays
      geometrically from ``svi_lr`` to ``svi_lr / 10`` (a constant rate leaves the
      single-sample gradient noise in the result); then ``num_samples`` guide draws as one
      chain. ``sample_stats`` holds only ``svi_loss`` (ELBO loss) over dim ``svi_step``.

    Both then run the model once per draw for ``log_likelihood`` (pointwise, of the observed
    site, with its mask and scale applied: masked entries are 0, so each draw's sum is the
    site's log-likelihood), ``posterior_predictive`` (one replicated data set per draw)
    and ``pyro.deterministic`` sites (added to ``posterior``).
    Root attributes: ``method``, ``wall_time_s`` (sampling / optimisation only),
    ``predictive_wall_time_s``, ``num_grad_evals`` (NUTS: potential-energy evaluations
    including warmup; SVI: steps), ``settings`` (JSON), ``created_at``, library versions.
    """
    if method not in ("nuts", "svi"):
        raise ValueError(f"method must be 'nuts' or 'svi', not {method!r}")
    init = init_to_median
    if init_values:
        dtype = torch.get_default_dtype()
        values = {k: torch.as_tensor(v, dtype=dtype) for k, v in init_values.items()}
        init = init_to_value(values=values, fallback=init_to_median)
    start = time.perf_counter()
    if method == "nuts":
        posterior, stats, grad_evals = _run_nuts(
            model, data, num_samples, num_warmup, num_chains, seed, init, progress, dense_mass,
            None if mass_matrix_from is None else unconstrained_covariance(model, data, mass_matrix_from))
        settings = {"num_warmup": num_warmup, "num_chains": num_chains, "dense_mass": dense_mass}
    else:
        posterior, stats = _run_svi(
            model, data, num_samples, seed, svi_steps, svi_lr, init, progress)
        grad_evals = svi_steps
        settings = {"svi_steps": svi_steps, "svi_lr": svi_lr}
    wall_time = time.perf_counter() - start

    start = time.perf_counter()
    pyro.set_rng_seed(seed)
    loglik, predictive, deterministic = _replay(model, data, posterior, observed, progress)
    groups = {
        "posterior": _numpy({**posterior, **deterministic}),
        "sample_stats": stats,
        "log_likelihood": _numpy({observed: loglik}),
        "posterior_predictive": _numpy({observed: predictive}),
        "observed_data": _numpy({observed: data[observed]}),
    }
    settings.update(num_samples=num_samples, seed=seed, observed=observed,
                    init_values=sorted(init_values or {}))
    attrs = {
        "method": method,
        "wall_time_s": wall_time,
        "predictive_wall_time_s": time.perf_counter() - start,
        "num_grad_evals": grad_evals,
        "settings": json.dumps(settings),
        "created_at": datetime.now(timezone.utc).isoformat(),
        "inference_library": "pyro",
        "inference_library_version": pyro.__version__,
        "torch_version": str(torch.__version__),  # TorchVersion would not write to NetCDF
    }
    return build_tree(groups, attrs, dims, coords)
