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
import time
from functools import partial

import numpy as np
import torch
from pyro import poutine
from pyro.infer.autoguide.initialization import init_to_value

from .laplace import Gaussian, exact_hessian
from .mixture import allocate
from .mode import find_map, grad_or_refused, newton_decrement
from .space import Unconstrained
from .trust_region import polish


NEWTON_STEPS = 30  # trust-region Newton trials from a predicted conditional mode before L-BFGS takes over
CONVERGED = 1e-6  # Newton decrement at a mode (find_map's test: 1e-3 posterior sd from the quadratic model's mode)


def nested_laplace(model, data: dict, site: str, grid, init: dict, num_samples: int, seed: int = 0,
                   newton: bool = True) -> dict:
    """Posterior draws of ``model(**data)`` with the positive scalar site ``site`` on ``grid``
    (increasing, uniform in log; its ends should carry negligible weight: check
    ``end_weights``) and the other sites Laplace given it; ``init``: constrained start values.
    The grid is walked outwards from the point nearest ``init[site]``; each conditional mode
    is found by ``find_map`` (L-BFGS, then Newton) from the neighbour's mode or, with ``newton``,
    by trust-region Newton steps alone from the modes' linear extrapolation in log ``site``
    (``find_map`` again where those do not converge): the same modes, with a few exact Hessians
    in place of an L-BFGS run.
    Returns ``{"draws": {site: (num_samples, ...)}, "grid", "log_marginal" (of log site, up to a
    constant), "weights", "end_weights", "evaluations" ((gradients, exact Hessians) per grid point),
    "newton" (which points Newton alone found), "wall_time_s" (per point)}``; the site's draws
    are spread uniformly in log over their grid cell."""
    grid = np.asarray(grid, float)
    steps = np.diff(np.log(grid))
    if grid.ndim != 1 or len(grid) < 3 or not np.all(grid > 0) or not np.allclose(steps, steps[0], rtol=1e-6):
        raise ValueError(f"the grid of {site!r} must be positive, >= 3 points, uniform in log (np.geomspace), got {grid}")
    free = {k: torch.as_tensor(v) for k, v in init.items() if k != site}
    first = int(np.argmin(np.abs(np.log(grid) - math.log(float(init[site])))))
    fits, modes, cost = {}, {}, {}
    for direction, order in ((1, range(first, len(grid))), (-1, range(first - 1, -1, -1))):  # outwards
        start = free if direction == 1 else {k: v.detach() for k, v in fits[first][0].constrain(modes[first]).items()}
        for j in order:
            t = time.perf_counter()
            conditioned = poutine.condition(model, data={site: torch.tensor(grid[j], dtype=torch.float64)})
            space = Unconstrained(conditioned, data, init_to_value(values=start))
            near = [modes[i] for i in (j - direction, j - 2 * direction) if i in modes]
            guess = None if not (newton and near) else near[0] if len(near) == 1 else 2 * near[0] - near[1]
            z, u, h, evaluations, by_newton = _conditional_mode(space, guess)
            gaussian = Gaussian(z, h, space.labels)
            log_det = 2 * float(torch.log(torch.diagonal(gaussian._chol)).sum())
            fits[j], modes[j] = (space, gaussian, -u - 0.5 * log_det + math.log(grid[j])), z
            cost[j] = (evaluations, by_newton, time.perf_counter() - t)
            start = {k: v.detach() for k, v in space.constrain(z).items()}
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
            "weights": weights.tolist(), "end_weights": [float(weights[0]), float(weights[-1])],
            **{key: [cost[j][i] for j in range(len(grid))] for i, key in enumerate(("evaluations", "newton", "wall_time_s"))}}


def _conditional_mode(space, guess):
    """(z, potential, exact Hessian, (gradient evaluations, Hessian evaluations), whether Newton alone
    found it): trust-region Newton from ``guess`` (unconstrained) if it is given and converges
    there, else ``find_map`` from ``space.initial``."""
    hessians = []

    def hessian(z):
        hessians.append(None)
        return exact_hessian(space, z)

    gradients = 0
    if guess is not None:
        evaluate = partial(grad_or_refused, space)
        u, g = evaluate(guess)
        gradients += 1
        if g is not None:
            z, u, g, h, trials = polish(evaluate, hessian, guess, u, g, hessian(guess), NEWTON_STEPS)
            gradients += trials
            if newton_decrement(g, h) <= CONVERGED:
                return z, u, h, (gradients, len(hessians)), True
    z, u, _, h, evaluations = find_map(space, hessian, progress=False)
    return z, u, h, (gradients + evaluations, len(hessians)), False
