"""A model's latent sites as one flat vector on Pyro's unconstrained space.

Sites are taken in sorted name order, each flattened (the order Pyro uses for a dense mass
matrix), and mapped to their support by ``biject_to(site.support)``. ``potential(z)`` is minus
the log joint density on that space, log-Jacobians included (Pyro's ``potential_fn``).
Pyro's ``transforms`` map constrained values to the unconstrained space.
"""

import torch
from pyro import poutine
from pyro.infer.mcmc.util import initialize_model
from pyro.infer.autoguide.initialization import InitMessenger


def init_trace(model, data, init):
    """A trace of ``model(**data)`` at the initial values (``init`` strategy)."""
    with poutine.block():
        return poutine.trace(InitMessenger(init)(model)).get_trace(**data)


def max_plate_nesting(model, data, init):
    """As Pyro guesses it, but running the model at the initial values, not at prior draws
    (which may make the model raise)."""
    trace = init_trace(model, data, init)
    dims = [frame.dim for site in trace.nodes.values() if site["type"] == "sample"
            for frame in site["cond_indep_stack"] if frame.vectorized]
    return -min(dims) if dims else 0


def _non_finite_sites(model, data, init) -> str:
    """The sample sites whose log density is not finite at the initial values."""
    try:
        trace = init_trace(model, data, init)
        trace.compute_log_prob()
    except Exception as error:  # the model itself fails there: say so
        return f"the model raises {type(error).__name__} at the initial values"
    bad = [k for k, s in trace.nodes.items()
           if s["type"] == "sample" and not bool(torch.isfinite(s["log_prob_sum"]))]
    return "sites with a non-finite log density at the start: " + ", ".join(repr(k) for k in bad) if bad else \
        "each site is finite at the start, their sum or gradient is not"


class Unconstrained:
    """Flat unconstrained parametrisation of ``model(**data)``, started at ``init``."""

    def __init__(self, model, data, init):
        try:
            start, self._potential, self.transforms, self.trace = initialize_model(
                model, model_kwargs=data, init_strategy=init,
                max_plate_nesting=max_plate_nesting(model, data, init))
        except ValueError as error:
            if "cannot find valid initial params" not in str(error):
                raise
            raise ValueError(f"the model's log density is not finite at any start Pyro tried "
                             f"({_non_finite_sites(model, data, init)}): check the data (values the "
                             "likelihood cannot reach, or so large that their square overflows), "
                             "the priors and init_values") from error
        self.names = sorted(start)
        self.shapes = {k: start[k].shape for k in self.names}
        self.initial = self.flatten(start).detach()

    @property
    def dim(self) -> int:
        return self.initial.numel()

    @property
    def labels(self) -> list[str]:
        """One label per coordinate: ``K`` for a scalar site, ``theta[0]``, ... for others."""
        return [k if not len(self.shapes[k]) else f"{k}[{i}]"
                for k in self.names for i in range(self.shapes[k].numel())]

    def flatten(self, values: dict) -> torch.Tensor:
        return torch.cat([values[k].reshape(-1) for k in self.names])

    def unflatten(self, z: torch.Tensor) -> dict:
        """``{site: unconstrained value}``; z may carry leading batch dims."""
        parts = torch.split(z, [self.shapes[k].numel() for k in self.names], dim=-1)
        return {k: p.reshape(z.shape[:-1] + self.shapes[k]) for k, p in zip(self.names, parts)}

    def potential(self, z: torch.Tensor) -> torch.Tensor:
        return self._potential(self.unflatten(z))

    def constrain(self, z: torch.Tensor) -> dict:
        """Constrained values of every site for z of shape (..., dim)."""
        return {k: self.transforms[k].inv(v) for k, v in self.unflatten(z).items()}

    def unconstrain(self, values: dict) -> torch.Tensor:
        """Flat unconstrained vector(s) of constrained ``values`` (leading batch dims kept)."""
        parts = []
        for k in self.names:
            u = self.transforms[k](torch.as_tensor(values[k]))
            parts.append(u.reshape(*u.shape[:u.dim() - len(self.shapes[k])], -1))
        return torch.cat(parts, dim=-1)
