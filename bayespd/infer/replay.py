"""Replay a model at posterior draws: pointwise log-likelihood, replicated data, deterministics.

The draws are replayed inside ``bayespd.linalg.reuse.reusing_factors``: the first draw's
factorisation preconditions conjugate gradients at every later draw (relative residual 1e-10),
so a draw costs an assembly and a few triangular solves, not a factorisation."""

from collections import defaultdict

import numpy as np
import torch
from pyro import poutine
from tqdm.auto import tqdm

from bayespd.linalg.reuse import reusing_factors


def thinned(num_draws: int, num_chains: int, predictive) -> np.ndarray:
    """The draw indices replayed in each chain: all (``predictive`` True), or about
    ``predictive`` draws in all, evenly spaced along each chain."""
    if predictive is True:
        return np.arange(num_draws)
    per_chain = min(num_draws, -(-int(predictive) // num_chains))
    return np.unique(np.round(np.linspace(0, num_draws - 1, per_chain)).astype(int))


def replay(model, data, posterior, observed, progress, draws=None):
    """Run the model once per draw (``draws``: the draw indices of each chain, default all),
    conditioned on it. Returns the pointwise log-likelihood of the data (mask and scale
    applied, masked entries 0), one replicated data set per draw and the
    ``pyro.deterministic`` sites, each shaped ``(chain, len(draws), ...)``."""
    loglik, predictive, deterministic = [], [], defaultdict(list)
    num_chains, total = next(iter(posterior.values())).shape[:2]
    draws = np.arange(total) if draws is None else np.asarray(draws)
    num_draws = len(draws)
    with torch.no_grad(), reusing_factors():
        for c, k in tqdm(np.ndindex(num_chains, num_draws), "predictive",
                         total=num_chains * num_draws, disable=not progress):
            d = draws[k]
            draw = {k: torch.as_tensor(v[c, d]) for k, v in posterior.items()}
            trace = poutine.trace(poutine.condition(model, data=draw)).get_trace(**data)
            trace.compute_log_prob(lambda name, site: name == observed)
            site = trace.nodes[observed]
            loglik.append(site["log_prob"])
            predictive.append(site["fn"].sample())
            for name, s in trace.nodes.items():
                if s["type"] == "sample" and s["infer"].get("_deterministic"):
                    deterministic[name].append(s["value"])

    def stack(values):
        return torch.stack(values).reshape(num_chains, num_draws, *values[0].shape).numpy()

    return stack(loglik), stack(predictive), {k: stack(v) for k, v in deterministic.items()}
