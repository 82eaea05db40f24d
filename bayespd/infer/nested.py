"""One scale hyperparameter integrated by quadrature, the rest by Laplace given it (the
nested Laplace of Rue, Martino & Chopin 2009, eqs 3-5 with a grid in log scale), summed over
every conditional mode found.

A joint Laplace at the MAP fails for a variance parameter tau that few numbers inform: where the
other parameters can absorb what tau scales (a common offset and the moduli, models/md_dispersion.py),
the joint density grows like 1 / tau as tau falls, so the joint mode sits near tau = 0 and the
Gaussian there is too narrow (the hierarchical funnel). Integrating theta out first removes that:
Rue et al.'s eq 3, p(tau | y) ~ p(y, theta*(tau), tau) / p_G(theta*(tau) | tau, y), applied per mode
m of the conditional p(theta | tau, y) and summed (its integral over theta is the sum of the
modes' basins):

    p(log tau | y) ~ tau sum_m p(y, theta_m(tau), tau) (2 pi)^(d/2) |H_m(tau)|^-1/2

on a grid uniform in log tau, and the posterior is the mixture of the Gaussians N(theta_m(tau_j),
H_m(tau_j)^-1) over (grid point, mode) with those masses. Exact for a theta Gaussian given tau, up
to the grid's quadrature error; for separated modes, each mode's Laplace error.

Which modes: a conditional with several modes makes one walk along the grid take whichever its
path meets (models/md_dispersion.py on the MD data has two modes, 2.0-2.2 nats apart, at tau >= 2 %;
two walks from phase-1 optima 3e-8 apart gave tau means of 4.2 and 3.0 %). So every grid point is
searched from ``init``, and every mode found is continued to both neighbouring points (from its
branch's linear extrapolation in log tau); modes new in a sweep are continued in the next, until a
sweep finds none. The result is the closure of those searches, the same whichever point a walk would
have started from. A mode that no search meets is still missed (a minor mode at every tau where
another exists, with the start in the other's basin: tests/infer/test_nested_bimodal.py). Each
search: trust-region Newton steps on the exact Hessian (``find_map``, L-BFGS first, where they do
not converge); a start that a chord iteration on the Hessian of a mode already found takes into it
ends there, with gradients only (most continuations).
"""

import math
import time
from dataclasses import dataclass
from functools import partial

import numpy as np
import torch
from pyro import poutine
from pyro.infer.autoguide.initialization import init_to_value
from scipy.special import logsumexp

from .laplace import Gaussian, exact_hessian
from .mixture import allocate, laplace_log_mass
from .mode import find_map, grad_or_refused, newton_decrement
from .space import Unconstrained
from .trust_region import polish


NEWTON_STEPS = 30  # trust-region Newton trials from a search's start before L-BFGS takes over
CONVERGED = 1e-6  # Newton decrement at a mode (find_map's test: 1e-3 posterior sd from the quadratic model's mode)
SAME_MODE = 1e-2  # whitened distance (in each end's Hessian metric) within which two search ends are one mode
CHORD_STEPS = 20  # chord iterations (gradients only) that may take a start into a mode already found


@dataclass
class _Mode:
    """A conditional mode at one grid point: unconstrained z, potential, Hessian, Laplace log mass
    (with the grid's log tau Jacobian) and the mode (at a neighbouring point) it was continued from."""
    z: torch.Tensor
    potential: float
    hessian: torch.Tensor
    log_mass: float
    parent: tuple | None  # (point, mode) or None: found from init


def nested_laplace(model, data: dict, site: str, grid, init: dict, num_samples: int, seed: int = 0) -> dict:
    """Posterior draws of ``model(**data)`` with the positive scalar site ``site`` on ``grid``
    (increasing, uniform in log; its ends should carry negligible weight: check ``end_weights``)
    and the other sites Laplace given it at each of their conditional modes (module docstring);
    ``init``: constrained start values.
    Returns ``{"draws": {site: (num_samples, ...)}, "grid", "log_marginal" (of log site, up to a
    constant), "weights", "end_weights", "mode_log_masses" (per point, largest first, on the
    log marginal's scale), "searches" (per point), "evaluations" ((gradients, exact Hessians) per
    point, all its searches), "wall_time_s" (per point), "sweeps"}``; the site's draws are spread
    uniformly in log over their grid cell."""
    grid = np.asarray(grid, float)
    steps = np.diff(np.log(grid))
    if grid.ndim != 1 or len(grid) < 3 or not np.all(grid > 0) or not np.allclose(steps, steps[0], rtol=1e-6):
        raise ValueError(f"the grid of {site!r} must be positive, >= 3 points, uniform in log (np.geomspace), got {grid}")
    free = {k: torch.as_tensor(v) for k, v in init.items() if k != site}
    spaces = [Unconstrained(poutine.condition(model, data={site: torch.tensor(t, dtype=torch.float64)}), data,
                            init_to_value(values=free)) for t in grid]
    modes = [[] for _ in grid]
    searches, gradients, hessians = (np.zeros(len(grid), int) for _ in range(3))
    wall = np.zeros(len(grid))
    pending, sweeps = [(j, None, None) for j in range(len(grid))], 0  # (point, start or None for init, parent)
    while pending:
        sweeps += 1
        new = []
        for j, start, parent in pending:
            t = time.perf_counter()
            end, (n_grad, n_hess) = _search(spaces[j], spaces[j].initial if start is None else start, modes[j])
            searches[j] += 1
            gradients[j] += n_grad
            hessians[j] += n_hess
            z, u, h = end or (None, None, None)
            mass = None if end is None else laplace_log_mass(u, h)
            if mass is not None and not any(_same_mode(z, h, m.z, m.hessian) for m in modes[j]):
                modes[j].append(_Mode(z, u, h, mass + math.log(grid[j]), parent))
                new.append((j, len(modes[j]) - 1))
            wall[j] += time.perf_counter() - t
        pending = [(k, _extrapolate(modes, j, i, k), (j, i)) for j, i in new for k in (j - 1, j + 1) if 0 <= k < len(grid)]
    empty = [float(grid[j]) for j in range(len(grid)) if not modes[j]]
    if empty:
        raise ValueError(f"no conditional mode with a positive definite Hessian at {site} = {empty}: every search "
                         "ended on a saddle, ridge or kink; narrow the grid, or tighten the priors there")
    masses = [sorted((m.log_mass for m in point), reverse=True) for point in modes]
    log_marginal = np.array([logsumexp(m) for m in masses])
    top = log_marginal.max()
    pairs = [(j, m) for j in range(len(grid)) for m in sorted(modes[j], key=lambda m: -m.log_mass)]
    weights = np.exp(np.array([m.log_mass for _, m in pairs]) - top)
    weights /= weights.sum()
    generator = torch.Generator().manual_seed(seed)
    parts = []
    for (j, mode), count in zip(pairs, allocate(weights, num_samples)):
        if count:
            space = spaces[j]
            gaussian = Gaussian(mode.z, mode.hessian, space.labels)
            values = {k: v.detach() for k, v in space.constrain(gaussian.sample(int(count), generator)).items()}
            cell = (torch.rand(int(count), generator=generator, dtype=torch.float64) - 0.5) * steps[0]
            values[site] = grid[j] * torch.exp(cell)
            parts.append(values)
    draws = {k: torch.cat([p[k] for p in parts]).numpy() for k in parts[0]}
    point_weights = np.exp(log_marginal - top)
    point_weights /= point_weights.sum()
    return {"draws": draws, "grid": grid.tolist(), "log_marginal": (log_marginal - top).tolist(),
            "weights": point_weights.tolist(), "end_weights": [float(point_weights[0]), float(point_weights[-1])],
            "mode_log_masses": [[m - top for m in point] for point in masses], "searches": searches.tolist(),
            "evaluations": [[int(g), int(h)] for g, h in zip(gradients, hessians)], "wall_time_s": wall.tolist(),
            "sweeps": sweeps}


def _same_mode(za, ha, zb, hb) -> bool:
    """Two search ends are one mode when each lies within SAME_MODE of the other in both ends'
    Hessian metrics. An end that passed the decrement test lies within sqrt(CONVERGED) = 1e-3
    whitened units of its mode, so two ends of one mode lie within 2e-3; two distinct minima of a
    smooth potential are separated by a saddle, whitened distance O(1) (closer than 1e-2 the barrier
    between them would be ~1e-4 nats and their Laplace masses one)."""
    return max(_whitened(za - zb, ha), _whitened(za - zb, hb)) <= SAME_MODE


def _extrapolate(modes, j, i, k):
    """Start for continuing mode i of point j to point k: linear in log tau along its branch
    (2 z - z_parent) where it was itself continued from the point beyond, else its own z."""
    mode = modes[j][i]
    if mode.parent is not None and mode.parent[0] == 2 * j - k:
        return 2 * mode.z - modes[mode.parent[0]][mode.parent[1]].z
    return mode.z


def _search(space, start, known):
    """One search at a grid point from ``start`` (unconstrained): ((z, potential, exact Hessian) of
    the mode it ends at, or None where it ends at one of ``known``, the point's modes so far),
    (gradient evaluations, Hessian evaluations)). A start from which the chord iteration on a known
    mode's Hessian contracts into it (``_chord``, gradients only) ends there; otherwise trust-region
    Newton steps while they converge, else ``find_map`` from ``start`` (from ``init`` where the model
    refuses ``start``)."""
    hessians, gradients = [], 0

    def hessian(z):
        hessians.append(None)
        return exact_hessian(space, z)

    for mode in sorted(known, key=lambda m: _whitened(start - m.z, m.hessian)):
        reached, evaluations = _chord(space, start, mode)
        gradients += evaluations
        if reached:
            return None, (gradients, 0)
    evaluate = partial(grad_or_refused, space)
    u, g = evaluate(start)
    gradients += 1
    if g is not None:
        z, u, g, h, trials = polish(evaluate, hessian, start, u, g, hessian(start), NEWTON_STEPS)
        gradients += trials
        if newton_decrement(g, h) <= CONVERGED:
            return (z, float(u), h), (gradients, len(hessians))
    z, u, _, h, evaluations = find_map(space, hessian, progress=False, start=start if g is not None else None)
    return (z, u, h), (gradients + evaluations, len(hessians))


def _chord(space, z, mode):
    """Whether the chord iteration z <- z - H^-1 grad U(z) on ``mode``'s Hessian H takes z into
    ``mode`` (within SAME_MODE whitened units), nearer to it at every step, in at most CHORD_STEPS:
    near a mode it contracts at the rate |I - H^-1 H(z)| < 1, so a start it takes there lies in that
    mode's basin, found without a Hessian. Returns (reached, gradient evaluations)."""
    chol = torch.linalg.cholesky((mode.hessian + mode.hessian.T) / 2)
    before = _whitened(z - mode.z, mode.hessian)
    for n in range(1, CHORD_STEPS + 1):
        _, g = grad_or_refused(space, z)
        if g is None:
            return False, n
        z = z - torch.cholesky_solve(g[:, None], chol)[:, 0]
        after = _whitened(z - mode.z, mode.hessian)
        if after <= SAME_MODE:
            return True, n
        if not after < before:
            return False, n
        before = after
    return False, CHORD_STEPS


def _whitened(d, h) -> float:
    """|d| in the metric of h: sqrt(d^T h d)."""
    return math.sqrt(max(float(d @ h @ d), 0.0))
