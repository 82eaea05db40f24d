"""The MCMC fit methods: ``NUTS`` and ``HMC`` (chains run by ``bayespd.infer.mcmc``)."""

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from pyro.infer.autoguide.initialization import init_to_median

from bayespd.validate import count

from . import laplace as _laplace
from .laplace import NotPositiveDefiniteHessian
from .mcmc import SETTINGS, ChainSpec, check_settings, run_chains
from .method import Draws, Method
from .mixture import allocate, cell_log_masses, cells, merged, mode_weights, stratified
from .space import Unconstrained


def unconstrained_covariance(model, data, tree) -> torch.Tensor:
    """Covariance of a fit's posterior draws on Pyro's unconstrained space, latent sites in
    sorted order: a seed for the dense mass matrix (e.g. from a quick SVI fit)."""
    space = Unconstrained(model, data, init_to_median)
    post = tree["posterior"]
    draws = {k: torch.as_tensor(post[k].values).reshape(-1, *space.shapes[k]) for k in space.names}
    return torch.atleast_2d(torch.cov(space.unconstrain(draws).T))  # one latent value: cov is 0-d


@dataclass(frozen=True)
class Sampler(Method):
    """``num_chains`` chains of ``num_warmup`` + ``num_samples`` (``bayespd.infer.mcmc``: seeds,
    ``chains="auto" | "sequential" | "processes"``, ``checkpoint=<dir>`` every
    ``checkpoint_every`` draws). ``dense_mass=True`` adapts a full mass matrix;
    ``mass_matrix_from`` seeds it with the covariance of a previous fit's draws (a DataTree, e.g.
    a quick SVI fit) or of the Laplace approximation (``"laplace"``), which ``adapt_mass=False``
    keeps through warmup (only the step size adapts towards ``target_accept``). A model that
    raises ``NotPositiveDefiniteError`` or ``ParameterRangeError`` in a trajectory gets a
    divergence; a chain that diverges on every draw raises ``ChainDivergedError``.
    ``sample_stats``: ``lp``, ``energy``, ``step_size``, ``n_steps``, ``diverging``,
    ``acceptance_rate`` per draw. With ``modes="weighted"``, ``num_chains`` chains from each
    mode (seeds ``seed + j num_chains``), the pooled draws split into one cell per mode and
    mixed by the cells' modified-harmonic-mean masses.
    """

    recorded = (*Method.recorded, "num_warmup", "num_chains", "dense_mass", "adapt_mass", "mass_matrix_from")

    num_warmup: int = 500
    num_chains: int = 4
    chains: str = "auto"
    dense_mass: bool = False
    mass_matrix_from: object = None
    adapt_mass: bool = True
    target_accept: float = 0.8
    checkpoint: str | Path | None = None
    checkpoint_every: int = 50

    def __post_init__(self):
        super().__post_init__()
        count("num_chains", self.num_chains, 1, "run at least one chain (4 to check convergence)")
        count("num_warmup", self.num_warmup, 0, "use 0 to skip warm-up (e.g. with a seeded mass matrix)")
        check_settings(**{k: getattr(self, k) for k in SETTINGS if hasattr(self, k)})
        if not self.adapt_mass and self.mass_matrix_from is None:
            raise ValueError("adapt_mass=False keeps a seeded mass matrix: give mass_matrix_from "
                             "('laplace' or a DataTree), or leave adaptation on")
        if isinstance(self.mass_matrix_from, str) and self.mass_matrix_from != "laplace":
            raise ValueError(f"mass_matrix_from must be a DataTree or 'laplace', not {self.mass_matrix_from!r}")

    def record(self) -> dict:
        source = self.mass_matrix_from
        return {**super().record(), "mass_matrix_from": source if source is None or isinstance(source, str) else "tree"}

    @property
    def seeds_from_laplace(self) -> bool:
        """``mass_matrix_from="laplace"`` (not ``==``: a DataTree compares elementwise, and truthy)."""
        return isinstance(self.mass_matrix_from, str)

    def kernel_options(self) -> dict:
        """Keyword arguments of the Pyro kernel."""
        return {"full_mass": bool(self.dense_mass or self.mass_matrix_from is not None),
                "adapt_mass_matrix": bool(self.adapt_mass)}

    def run(self, model, data, init, search):
        covariance = (None if self.mass_matrix_from is None or isinstance(self.mass_matrix_from, str)
                      else unconstrained_covariance(model, data, self.mass_matrix_from))
        if search.weighted:
            return self._at_every_mode(model, data, init, covariance, search)
        if self.seeds_from_laplace:
            space, gaussian, info = _laplace.laplace(model, data, init, self.observed, "exact", self.progress,
                                                     search.starts, self.seed)
            search.modes, covariance = info["map_modes"], gaussian.covariance
            if self.init == "map":
                init = _laplace.init_at(space, gaussian.mean)
        elif self.init == "map":
            init = search.map_init(model, data, init)
        return Draws(*self._chains(model, data, init, covariance, folder=self.checkpoint))

    def _chains(self, model, data, start, covariance, offset=0, folder=None):
        spec = ChainSpec(model, data, self.name, self.num_warmup, self.num_samples, self.seed + offset, start,
                         self.kernel_options(), covariance, self.progress,
                         None if folder is None else Path(folder), self.checkpoint_every)
        return run_chains(spec, self.num_chains, self.chains)

    def _at_every_mode(self, model, data, init, tree_covariance, search):
        """Chains at every mode worth fitting; their pooled draws split into the modes' cells and
        mixed by the cells' modified-harmonic-mean masses (``bayespd.infer.mixture``)."""
        space, fitted, laplace_masses, evaluations = search.modes_to_fit(model, data, init, self.observed, "exact")
        positive = [(z, h) for (z, _, _, h), m in zip(fitted, laplace_masses) if m is not None]
        if not positive:
            raise NotPositiveDefiniteHessian(
                "no mode found has a positive definite Hessian, so the modes' cells are not defined: "
                "use modes='best', or more map_starts")
        precisions = [h if m is not None else min(positive, key=lambda p: float((p[0] - z).norm()))[1]
                      for (z, _, _, h), m in zip(fitted, laplace_masses)]  # on a kink: the nearest one's
        runs = []
        for j, ((z, *_), h) in enumerate(zip(fitted, precisions)):
            covariance = (_laplace.Gaussian(z, h, space.labels).covariance if self.seeds_from_laplace
                          else tree_covariance)
            folder = None if self.checkpoint is None else Path(self.checkpoint) / f"mode{j}"
            runs.append(self._chains(model, data, _laplace.init_at(space, z), covariance, j * self.num_chains, folder))
            evaluations += runs[-1][2]
        pooled = {k: np.concatenate([r[0][k] for r in runs]).reshape(-1, *runs[0][0][k].shape[2:])
                  for k in runs[0][0]}
        stats = {k: np.concatenate([r[1][k] for r in runs]).reshape(-1) for k in runs[0][1]}
        z_draws = space.unconstrain({k: torch.as_tensor(v) for k, v in pooled.items()}).numpy()
        groups = np.repeat(np.arange(len(fitted)), len(stats["lp"]) // len(fitted))
        labels, joined = merged(cells(z_draws, [m[0].numpy() for m in fitted], [h.numpy() for h in precisions]),
                                groups, len(fitted))
        masses = cell_log_masses(z_draws, stats["lp"], labels, len(fitted))
        counts = allocate(mode_weights(masses), self.num_samples)
        search.record_weights(space, fitted, laplace_masses, masses, counts, cell=joined)
        return Draws(stratified(pooled, labels, counts, self.num_chains),
                     stratified(stats, labels, counts, self.num_chains), evaluations)


@dataclass(frozen=True)
class NUTS(Sampler):
    """The No-U-Turn sampler: trees of at most ``max_tree_depth`` doublings (``sample_stats``
    also ``tree_depth``)."""

    name = "nuts"
    recorded = (*Sampler.recorded, "target_accept", "max_tree_depth")

    max_tree_depth: int = 10

    def kernel_options(self):
        return {"target_accept_prob": self.target_accept, "max_tree_depth": self.max_tree_depth,
                **super().kernel_options()}


@dataclass(frozen=True)
class HMC(Sampler):
    """Static HMC: trajectories of length ``trajectory_length`` (default 2 pi), i.e.
    ``trajectory_length / step_size`` leapfrog steps."""

    name = "hmc"
    recorded = (*Sampler.recorded, "trajectory_length")

    trajectory_length: float | None = None

    def kernel_options(self):
        return {"trajectory_length": self.trajectory_length, "target_accept_prob": self.target_accept,
                **super().kernel_options()}
