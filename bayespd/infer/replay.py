"""Replay a model at posterior draws: pointwise log-likelihood, replicated data, deterministics."""

from collections import defaultdict

import numpy as np
import torch
from pyro import poutine
from tqdm.auto import tqdm


def replay(model, data, posterior, observed, progress):
    """Run the model once per draw, conditioned on it. Returns the pointwise log-likelihood
    of the data (mask and scale applied, masked entries 0), one replicated data set per draw
    and the ``pyro.deterministic`` sites, each shaped ``(chain, draw, ...)``."""
    loglik, predictive, deterministic = [], [], defaultdict(list)
    num_chains, num_draws = next(iter(posterior.values())).shape[:2]
    with torch.no_grad():
        for c, d in tqdm(np.ndindex(num_chains, num_draws), "predictive",
                         total=num_chains * num_draws, disable=not progress):
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
