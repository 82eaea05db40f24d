"""One scale hyperparameter integrated by quadrature, the rest by Laplace given it (the
nested Laplace of Rue, Martino & Chopin 2009, eqs 3-5 with a grid in log scale).

A joint Laplace at the MAP fails for a variance parameter tau that few numbers inform: where the
other parameters can absorb what tau scales (a common offset and the moduli, models/md_dispersion.py),
the joint density grows like 1 / tau as tau falls, so the joint mode sits near tau = 0 and the
Gaussian there is too narrow (the hierarchical funnel). Integrating theta out first removes that:

    p(log tau | y) ~ tau p(y, theta*(tau), tau) |H(tau)|^-1/2   (Laplace in theta at fixed tau)

on a grid uniform in log tau, and the posterior is the mixture of the conditional Gaussians
N(theta*(tau_j), H(tau_j)^-1) weighted by it. Exact for a theta Gaussian given tau, up to the
grid's quadrature error.
"""

import math

import numpy as np
import torch
from pyro import poutine
from pyro.infer.autoguide.initialization import init_to_value

from .laplace import Gaussian, exact_hessian
from .mixture import allocate
from .mode import find_map
from .space import Unconstrained


def nested_laplace(model, data: dict, site: str, grid, init: dict, num_samples: int, seed: int = 0) -> dict:
    """Posterior draws of ``model(**data)`` with the positive scalar site ``site`` on ``grid``
    (increasing, uniform in log; its ends should carry negligible weight: check
    ``end_weights``) and the other sites Laplace given it; ``init``: constrained start values.
    Returns ``{"draws": {site: (num_samples, ...)}, "grid", "log_marginal" (of log site, up to a
    constant), "weights", "end_weights"}``; the site's draws are spread uniformly in log
    over their grid cell."""
    grid = np.asarray(grid, float)
    steps = np.diff(np.log(grid))
    if grid.ndim != 1 or len(grid) < 3 or not np.all(grid > 0) or not np.allclose(steps, steps[0], rtol=1e-6):
        raise ValueError(f"the grid of {site!r} must be positive, >= 3 points, uniform in log (np.geomspace), got {grid}")
    free = {k: torch.as_tensor(v) for k, v in init.items() if k != site}
    first = int(np.argmin(np.abs(np.log(grid) - math.log(float(init[site])))))
    fits, start = {}, free
    for order in (range(first, len(grid)), range(first - 1, -1, -1)):  # outwards, each warm-started
        for j in order:
            conditioned = poutine.condition(model, data={site: torch.tensor(grid[j], dtype=torch.float64)})
            space = Unconstrained(conditioned, data, init_to_value(values=start))
            z, u, _, h, _ = find_map(space, lambda x, s=space: exact_hessian(s, x), progress=False)
            gaussian = Gaussian(z, h, space.labels)
            log_det = 2 * float(torch.log(torch.diagonal(gaussian._chol)).sum())
            fits[j] = (space, gaussian, -u - 0.5 * log_det + math.log(grid[j]))
            start = {k: v.detach() for k, v in space.constrain(z).items()}
        start = {k: v.detach() for k, v in fits[first][0].constrain(fits[first][1].mean).items()}
    log_marginal = np.array([fits[j][2] for j in range(len(grid))])
    weights = np.exp(log_marginal - log_marginal.max())
    weights /= weights.sum()
    generator = torch.Generator().manual_seed(seed)
    parts = []
    for j, count in enumerate(allocate(weights, num_samples)):
        if count:
            space, gaussian, _ = fits[j]
            values = {k: v.detach() for k, v in space.constrain(gaussian.sample(int(count), generator)).items()}
            cell = (torch.rand(int(count), generator=generator, dtype=torch.float64) - 0.5) * steps[0]
            values[site] = grid[j] * torch.exp(cell)
            parts.append(values)
    draws = {k: torch.cat([p[k] for p in parts]).numpy() for k in parts[0]}
    return {"draws": draws, "grid": grid.tolist(), "log_marginal": (log_marginal - log_marginal.max()).tolist(),
            "weights": weights.tolist(), "end_weights": [float(weights[0]), float(weights[-1])]}
