"""Laplace approximation on Pyro's unconstrained space.

The MAP ``z*`` minimises the potential U(z) = -log p(y, z) (log-Jacobians of the constraint
transforms included) by L-BFGS, then Newton steps polish it. The posterior is approximated by
N(z*, H^-1), H the Hessian of U at z*, and its draws are pushed through the constraint
transforms. Two Hessians:

* ``"exact"``: ``torch.autograd.functional.hessian`` of U; the PD solve is twice
  differentiable (its backward is the same adjoint Function), costing about two solves per
  parameter.
* ``"gauss-newton"`` (large problems, no second derivatives of the solve): the Hessian of the
  prior part (exact; it involves no solve) plus the Fisher information of a Normal likelihood
  y ~ N(m(z), s(z)), ``J_m^T diag(w / s^2) J_m + J_s^T diag(2 w / s^2) J_s`` (w: mask and
  scale of the observed site). The Jacobians J of the mean m and scale s are built column by
  column from reverse mode alone: g(v) = J^T v is linear in a dummy v, so J e_k = d(g_k)/dv
  (one backward-of-backward per parameter, i.e. about two solves). It drops the residual-
  weighted second derivatives of m, exact for a linear mean and accurate when residuals are
  small.
"""

from dataclasses import dataclass
from functools import partial

import numpy as np
import torch
import xarray as xr
from pyro import poutine
from pyro.distributions import Independent, MaskedDistribution
from pyro.distributions.torch_distribution import ExpandedDistribution
from pyro.infer.autoguide.initialization import init_to_value

from .method import Draws, Method
from .mixture import allocate, mode_weights, one_chain
from .mode import distinct_modes, modes_json
from .space import Unconstrained

HESSIANS = ("exact", "gauss-newton")


class NotPositiveDefiniteHessian(ValueError):
    """The Hessian of the negative log joint at the mode is not positive definite (or is
    singular to working precision: smallest eigenvalue <= 1e-12 x largest)."""


@dataclass
class Gaussian:
    """N(mean, precision^-1) on the unconstrained space; ``labels`` name the coordinates."""

    mean: torch.Tensor
    precision: torch.Tensor
    labels: list

    def __post_init__(self):
        self.precision = (self.precision + self.precision.T) / 2
        values, vectors = torch.linalg.eigh(self.precision)
        chol, info = torch.linalg.cholesky_ex(self.precision)
        if info or values[0] <= 1e-12 * values[-1]:  # singular to working precision
            worst = self.labels[int(vectors[:, 0].abs().argmax())]
            raise NotPositiveDefiniteHessian(
                f"the Hessian of the negative log joint at the mode is not positive definite "
                f"(smallest eigenvalue {float(values[0]):.3g}, mostly along {worst!r}): the mode "
                "is a saddle or a ridge, or the optimiser stopped early. Tighten the prior of "
                f"{worst!r} (or fix it with pyro.poutine.condition), start elsewhere with "
                "init_values, or use method='nuts' / 'svi', which need no Hessian")
        self._chol = chol

    @property
    def covariance(self) -> torch.Tensor:
        return torch.cholesky_inverse(self._chol)

    def sample(self, n: int, generator=None) -> torch.Tensor:
        """(n, dim) draws: mean + L^-T eps with precision = L L^T."""
        eps = torch.randn(n, self.mean.numel(), generator=generator, dtype=self.mean.dtype)
        return self.mean + torch.linalg.solve_triangular(self._chol.T, eps.T, upper=True).T


def exact_hessian(space, z) -> torch.Tensor:
    return torch.autograd.functional.hessian(space.potential, z.detach())


def _jacobian(y, z):
    """(y.numel(), z.numel()) Jacobian by reverse mode only (see the module docstring)."""
    y = y.reshape(-1)
    if not y.requires_grad:
        return y.new_zeros(y.numel(), z.numel())
    v = torch.zeros_like(y, requires_grad=True)
    (g,) = torch.autograd.grad(y, z, v, create_graph=True)
    columns = []
    for k in range(z.numel()):
        col = torch.autograd.grad(g[k], v, retain_graph=True, allow_unused=True)[0] if g[k].requires_grad else None
        columns.append(torch.zeros_like(y) if col is None else col)
    return torch.stack(columns, dim=1).detach()


def _normal_parts(site):
    """Mean, scale and weight (mask x scale), each shaped like the observed value."""
    fn, weight = site["fn"], torch.ones_like(site["value"]) * site["scale"]
    while isinstance(fn, (MaskedDistribution, Independent, ExpandedDistribution)):
        if isinstance(fn, MaskedDistribution):
            weight = weight * fn._mask
        fn = fn.base_dist
    if not isinstance(fn, torch.distributions.Normal):
        raise ValueError(f"hessian='gauss-newton' needs a Normal likelihood at site "
                         f"{site['name']!r}, not {type(fn).__name__}: use hessian='exact'")
    shape = site["value"].shape
    return fn.loc.expand(shape), fn.scale.expand(shape), weight.expand(shape)


def gauss_newton_hessian(model, data, observed, space, z) -> torch.Tensor:
    """Exact prior Hessian plus the Fisher information of the Normal likelihood at z."""
    prior = Unconstrained(poutine.block(model, hide=[observed]), data, init_at(space, z))
    h = exact_hessian(prior, z)
    z = z.detach().requires_grad_()
    trace = poutine.trace(poutine.condition(model, data=space.constrain(z))).get_trace(**data)
    loc, scale, weight = _normal_parts(trace.nodes[observed])
    precision = (weight / scale**2).detach().reshape(-1, 1)
    j_loc, j_scale = _jacobian(loc, z), _jacobian(scale, z)
    return h + j_loc.T @ (precision * j_loc) + j_scale.T @ (2 * precision * j_scale)


def init_at(space, z):
    """Pyro init strategy at the unconstrained point z."""
    return init_to_value(values={k: v.detach() for k, v in space.constrain(z.detach()).items()})


def modes(model, data, init, observed="y", hessian="exact", progress=True, starts=1, seed=0, warn=True):
    """The distinct modes of ``starts`` MAP searches (``distinct_modes``; ``warn`` of close
    ones) with their Hessians: (space, modes lowest first, gradient evaluations)."""
    if hessian not in HESSIANS:
        raise ValueError(f"hessian must be one of {HESSIANS}, not {hessian!r}")
    space = Unconstrained(model, data, init)
    hessian_fn = (partial(exact_hessian, space) if hessian == "exact"
                  else partial(gauss_newton_hessian, model, data, observed, space))
    found, evaluations = distinct_modes(space, model, data, init, starts, seed, hessian_fn, progress, warn)
    return space, found, evaluations


def laplace(model, data, init, observed="y", hessian="exact", progress=True, starts=1, seed=0):
    """Laplace approximation of ``model(**data)`` at the lowest of the ``modes``:
    (space, Gaussian, info dict)."""
    space, found, evaluations = modes(model, data, init, observed, hessian, progress, starts, seed)
    z, u, g, h = found[0]
    info = {"map_potential": u, "map_grad_norm": float(g.norm()), "map_modes": modes_json(space, found),
            "gradient_evaluations": evaluations, "hessian": hessian}
    return space, Gaussian(z, h, space.labels), info


def draws(space, gaussian, num_samples, seed):
    """``{site: (1, num_samples, ...)}`` constrained draws from the Laplace Gaussian."""
    z = gaussian.sample(num_samples, torch.Generator().manual_seed(seed))
    return {k: v[None].detach() for k, v in space.constrain(z).items()}


def stats(gaussian) -> dict:
    """Mode and covariance on the unconstrained space, as ``sample_stats`` arrays."""
    labels = np.array(gaussian.labels)
    cov = gaussian.covariance.numpy()
    return xr.Dataset(
        {"mode_unconstrained": ("unconstrained", gaussian.mean.numpy()),
         "covariance_unconstrained": (("unconstrained", "unconstrained_b"), cov)},
        coords={"unconstrained": labels, "unconstrained_b": labels})


@dataclass(frozen=True)
class Laplace(Method):
    """The Laplace approximation at the MAP (the lowest of ``map_starts`` searches) with
    ``hessian="exact" | "gauss-newton"``; ``num_samples`` draws of the Gaussian pushed through
    the constraint transforms, as one chain. ``sample_stats``: the mode and covariance on the
    unconstrained space. With ``modes="weighted"``, the Gaussians at every mode with a
    positive definite Hessian, mixed by their Laplace masses."""

    name = "laplace"
    searches_map = True
    recorded = (*Method.recorded, "hessian")

    hessian: str = "exact"

    def run(self, model, data, init, search):
        if search.weighted:
            return self._at_every_mode(model, data, init, search)
        space, gaussian, info = laplace(model, data, init, self.observed, self.hessian, self.progress,
                                        self.map_starts, self.seed)
        search.modes = info["map_modes"]
        return Draws(draws(space, gaussian, self.num_samples, self.seed), stats(gaussian),
                     info["gradient_evaluations"],
                     {"map_potential": info["map_potential"], "map_grad_norm": info["map_grad_norm"]})

    def _at_every_mode(self, model, data, init, search):
        """Laplace approximations at every mode with a positive definite Hessian, mixed by their
        Laplace masses."""
        space, fitted, masses, evaluations = search.modes_to_fit(model, data, init, self.observed, self.hessian)
        pairs = [(m, w) for m, w in zip(fitted, masses) if w is not None] or [(fitted[0], None)]
        gaussians = [Gaussian(z, h, space.labels)  # none positive definite: raises, naming the fix
                     for (z, _, _, h), _ in pairs]
        fitted, masses = [m for m, _ in pairs], [w for _, w in pairs]
        counts = allocate(mode_weights(masses), self.num_samples)
        per_mode = [draws(space, g, int(c), self.seed + j) for j, (g, c) in enumerate(zip(gaussians, counts))]
        search.record_weights(space, fitted, masses, masses, counts)
        return Draws(one_chain(per_mode, counts), stats(gaussians[0]), evaluations)
