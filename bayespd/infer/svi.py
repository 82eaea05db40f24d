"""Stochastic variational inference with Pyro autoguides on the unconstrained space.

Guides: ``"normal"`` (mean field, ``AutoNormal``), ``"mvn"`` (full-rank Gaussian,
``AutoMultivariateNormal``), ``"lowrank"`` (``AutoLowRankMultivariateNormal``, covariance
W W^T + D of rank ``svi_rank``, default about sqrt(dim)) and ``"flow"`` (two inverse
autoregressive flows followed by an affine map centred at the initial location, so the flow
starts where the Gaussian guides start). Every guide starts at the initial values (prior median
or ``init_values``).
"""

import math
from dataclasses import dataclass

import numpy as np
import pyro
import pyro.infer
import torch
import xarray as xr
from pyro import poutine
from pyro.distributions.transforms import ComposeTransformModule, affine_autoregressive
from pyro.infer import Trace_ELBO
from pyro.infer.autoguide import (AutoContinuous, AutoLowRankMultivariateNormal,
                                  AutoMultivariateNormal, AutoNormal, AutoNormalizingFlow)
from pyro.optim import ClippedAdam
from scipy.special import logsumexp
from torch.distributions.transforms import AffineTransform
from tqdm.auto import tqdm

from . import laplace as _laplace
from bayespd.materials.checks import ParameterRangeError
from bayespd.validate import count, positive

from .method import Draws, Method
from .whitened import AutoWhitenedMVN
from .mixture import allocate, mode_weights, one_chain

GUIDES = ("normal", "mvn", "lowrank", "flow")


class AutoFlow(AutoNormalizingFlow):
    """N(0, I) through ``num_flows`` IAFs, then ``x -> init_loc + init_scale * x``."""

    def __init__(self, model, init_loc_fn, num_flows=2, init_scale=0.1):
        AutoContinuous.__init__(self, model, init_loc_fn=init_loc_fn)
        self._init_transform_fn, self.transform = self._flow, None
        self._prototype_tensor = torch.tensor(0.0)
        self.num_flows, self.init_scale = num_flows, init_scale

    def _flow(self, dim):
        if dim < 2:
            raise ValueError("the 'flow' guide needs at least two latent dimensions: "
                             "use guide='mvn' (exact for a Gaussian posterior)")
        flows = [affine_autoregressive(dim) for _ in range(self.num_flows)]
        return ComposeTransformModule([*flows, AffineTransform(self._init_loc(), self.init_scale)])


def make_guide(model, guide, init, rank=None, start=None):
    """The guide ``guide`` started at ``init``; ``start`` = (space, Laplace Gaussian) whitens the
    ``"mvn"`` guide by that Gaussian (``AutoWhitenedMVN``)."""
    if guide == "normal":
        return AutoNormal(model, init_loc_fn=init)
    if guide == "mvn":
        return AutoMultivariateNormal(model, init_loc_fn=init) if start is None else AutoWhitenedMVN(model, init, *start)
    if guide == "lowrank":
        return AutoLowRankMultivariateNormal(model, init_loc_fn=init, rank=rank)
    if guide == "flow":
        return AutoFlow(model, init)
    raise ValueError(f"guide must be one of {GUIDES}, not {guide!r}")


def run_svi(model, data, guide, num_samples, seed, steps, lr, init, progress, rank=None,
            particles=1, evidence=False, start=None):
    """Fit ``guide`` by ``steps`` of ClippedAdam (learning rate decaying geometrically from
    ``lr`` to ``lr / 10``: a constant rate leaves the single-sample gradient noise in the
    result) on the ELBO with ``particles`` samples per step; return ``num_samples`` guide
    draws as one chain ``{site: (1, num_samples, ...)}`` and the loss trace, and with
    ``evidence`` also ``log_evidence`` from ``num_samples`` further guide draws; ``start``: see
    ``make_guide``."""
    pyro.set_rng_seed(seed)
    with pyro.get_param_store().scope():
        q = make_guide(model, guide, init, rank, start)
        optim = ClippedAdam({"lr": lr, "lrd": 0.1 ** (1 / steps)})
        svi = pyro.infer.SVI(model, q, optim, Trace_ELBO(num_particles=particles))
        losses = []
        with tqdm(range(steps), f"SVI ({guide})", disable=not progress) as bar:
            for i in bar:
                losses.append(_step(svi, data, i, steps, lr))
                if i % 50 == 0:
                    bar.set_postfix(loss=f"{losses[-1]:.4g}")
        with torch.no_grad():
            draws = [q(**data) for _ in range(num_samples)]
            log_z = log_evidence(model, q, data, num_samples) if evidence else None
    posterior = {k: torch.stack([d[k] for d in draws])[None] for k in draws[0]}
    stats = xr.Dataset({"svi_loss": ("svi_step", np.array(losses))})
    return (posterior, stats) if not evidence else (posterior, stats, log_z)


def _step(svi, data, i: int, steps: int, lr: float) -> float:
    """One SVI step's loss. After the first step, a non-finite loss or guide parameter, or an
    invalid draw (the model's ``ParameterRangeError``: a modulus overflowed; torch refusing a
    guide distribution's parameters), is the optimiser diverging: a ``ValueError`` naming
    ``svi_lr`` and the fix."""
    try:
        loss = svi.step(**data)
    except (ValueError, RuntimeError) as error:
        if i == 0 or not (_invalid_draw(error) or not _params_finite()):
            raise
        raise _diverged(i, steps, lr, f"the guide gave an invalid draw ({str(error).splitlines()[0]})") from error
    if i == 0 and not math.isfinite(loss):
        raise ValueError(f"the first SVI loss is {loss}: the model's log density is not finite at the "
                         "initial values; check the priors, init_values and the data")
    if not (math.isfinite(loss) and _params_finite()):
        raise _diverged(i, steps, lr, "the ELBO or the guide's parameters became NaN or inf")
    return loss


def _invalid_draw(error: Exception) -> bool:
    """A model's parameter out of range, or a distribution's parameters refused by torch."""
    return isinstance(error, ParameterRangeError) or str(error).startswith("Expected parameter")


def _diverged(i: int, steps: int, lr: float, what: str) -> ValueError:
    return ValueError(f"SVI diverged at step {i + 1} of {steps} with svi_lr={lr:g}: {what}; "
                      f"lower svi_lr (e.g. {lr / 10:g})")


def _params_finite() -> bool:
    """Whether every parameter in Pyro's param store is finite."""
    store = pyro.get_param_store()
    return all(bool(torch.isfinite(store[k]).all()) for k in store.keys())


def log_evidence(model, guide, data, n: int) -> float:
    """Importance-sampling estimate of log p(y) with ``guide`` as proposal:
    log mean_i exp(log p(y, theta_i) - log q(theta_i)) over n guide draws."""
    log_w = []
    for _ in range(n):
        g = poutine.trace(guide).get_trace(**data)
        m = poutine.trace(poutine.replay(model, trace=g)).get_trace(**data)
        log_w.append(float(m.log_prob_sum() - g.log_prob_sum()))
    return float(logsumexp(log_w) - math.log(n))


@dataclass(frozen=True)
class SVI(Method):
    """Stochastic variational inference: ``guide`` in ``GUIDES``, fitted by ``svi_steps`` of
    decaying-rate ClippedAdam from ``svi_lr`` with ``svi_particles`` ELBO samples per step
    (``svi_rank``: the ``"lowrank"`` guide's rank); ``num_samples`` guide draws as one chain.
    ``sample_stats``: ``svi_loss``. With ``init="map"`` the ``"mvn"`` guide starts at the
    Laplace Gaussian there, in coordinates it whitens (``whitened.py``): the learning rate is
    then in posterior standard deviations, however narrow the posterior. With ``modes="weighted"``, a guide fitted from each mode,
    mixed by their importance-sampling evidence (``log_evidence``)."""

    name = "svi"
    recorded = (*Method.recorded, "guide", "svi_steps", "svi_lr", "svi_rank", "svi_particles")

    guide: str = "mvn"
    svi_steps: int = 2000
    svi_lr: float = 0.02
    svi_rank: int | None = None
    svi_particles: int = 1

    def __post_init__(self):
        super().__post_init__()
        if self.guide not in GUIDES:
            raise ValueError(f"guide must be one of {GUIDES}, not {self.guide!r}")
        count("svi_steps", self.svi_steps, 1, "take at least one optimisation step (typically 1000s)")
        count("svi_particles", self.svi_particles, 1, "use at least one ELBO sample per step")
        positive("svi_lr", self.svi_lr, "pass a learning rate such as 0.02")
        if self.svi_rank is not None:
            count("svi_rank", self.svi_rank, 1, "or None for about sqrt(dim)")

    def _fit(self, model, data, init, seed, evidence=False, start=None):
        return run_svi(model, data, self.guide, self.num_samples, seed, self.svi_steps, self.svi_lr, init,
                       self.progress, self.svi_rank, self.svi_particles, evidence=evidence, start=start)

    def run(self, model, data, init, search):
        if search.weighted:
            return self._at_every_mode(model, data, init, search)
        start, evaluations = None, 0
        if self.init == "map" and self.guide == "mvn":  # started at the Laplace Gaussian, whitened by it
            init, space, gaussian, evaluations = search.laplace_start(model, data, init, self.observed)
            start = None if gaussian is None else (space, gaussian)
        elif self.init == "map":
            init = search.map_init(model, data, init)
        return Draws(*self._fit(model, data, init, self.seed, start=start),
                     evaluations + self.svi_steps * self.svi_particles)

    def _at_every_mode(self, model, data, init, search):
        """A guide fitted from every mode worth fitting, mixed by their evidence estimates."""
        space, fitted, laplace_masses, evaluations = search.modes_to_fit(model, data, init, self.observed, "exact")
        fits = [self._fit(model, data, _laplace.init_at(space, z), self.seed + j, evidence=True)
                for j, (z, *_) in enumerate(fitted)]
        masses = [f[2] for f in fits]
        counts = allocate(mode_weights(masses), self.num_samples)
        search.record_weights(space, fitted, laplace_masses, masses, counts)
        stats = xr.concat([f[1] for f in fits], dim="svi_mode")
        return Draws(one_chain([f[0] for f in fits], counts), stats,
                     evaluations + self.svi_steps * self.svi_particles * len(fitted))
