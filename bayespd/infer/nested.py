"""Scalar hyperparameters integrated by quadrature on a product grid, the rest by Laplace given
them (the nested Laplace of Rue, Martino & Chopin 2009, eqs 3-5), summed over every conditional
mode found.

A joint Laplace at the MAP fails for a variance parameter tau that few numbers inform: where the
other parameters can absorb what tau scales (a common offset and the moduli, models/md_dispersion.py),
the joint density grows like 1 / tau as tau falls, so the joint mode sits near tau = 0 and the
Gaussian there is too narrow (the hierarchical funnel). It fails too for a parameter on which the
potential is only piecewise smooth: the PD horizon delta, where the partial-volume weights are
piecewise linear (``bayespd.bonds.partial_volume``) and a clamped influence kinks at r = delta, so
the potential kinks wherever a bond length crosses delta or delta +- h/2 (``Bonds.kinks``) and its
minima may sit on a kink (a Gaussian there has no meaning; on the MD sheet most of the mass does).
Integrating such sites out on a grid removes both: given them, the rest is smooth. Rue et al.'s
eq 3, p(psi | y) ~ p(y, theta*(psi), psi) / p_G(theta*(psi) | psi, y), applied per mode m of the
conditional p(theta | psi, y) and summed (its integral over theta is the sum of the modes' basins):

    p(psi | y) ~ J(psi) sum_m p(y, theta_m(psi), psi) (2 pi)^(d/2) |H_m(psi)|^-1/2

on a product of grids (a scale integrated over log psi_a: J takes its factor psi_a), each site by
``bayespd.infer.grid_axis``'s rule (log density linear between points, integrated exactly: exact at
a cusp that is a grid point), the weights of the product rule the product of each site's; the
posterior is the mixture of the Gaussians N(theta_m(psi_j), H_m(psi_j)^-1) over (grid point, mode)
with those masses, the grid sites drawn from the interpolated density over their point's cells.
Exact for a theta Gaussian given psi, up to the grid's quadrature error; for separated modes, each
mode's Laplace error.

Which modes: a conditional with several modes makes one walk along the grid take whichever its
path meets (models/md_dispersion.py on the MD data has two modes, 2.0-2.2 nats apart, at tau >= 2 %
with delta free; two walks from phase-1 optima 3e-8 apart gave tau means of 4.2 and 3.0 %). So every
point of each grid line through the point nearest ``init`` (every point of a single site's grid) is
searched from ``init``, and every mode found is continued to each neighbouring point (one step along
one site's grid, from its branch's linear extrapolation where it was itself continued along that
site), until no search finds a new mode. The result is the closure of those searches, the same modes
in whichever order they run (continuations run before the next search from init, so that search
mostly ends in a mode already found, with gradients only). Searching every point of a product grid
from init would cost a full search each (on the MD sheet's (tau, delta) grid, 20 Hessians a point:
the conditional mode moves by whitened distances of 2-13 per 0.05-0.4 A of delta, the kernel shape
trading off against delta). A mode that no search meets is still missed (a minor mode at every psi
where another exists, with the start in the other's basin: tests/infer/test_nested_bimodal.py).
Each search: a start that a chord iteration on the Hessian of a mode already found takes into it
ends there, with gradients only; a continuation runs the chord iteration on its parent's Hessian,
one exact Hessian confirming the mode; else trust-region Newton steps on the exact Hessian
(``find_map``, L-BFGS first, where they do not converge).
"""

import itertools
import math
import time
from collections import deque
from dataclasses import dataclass
from functools import partial

import numpy as np
import torch
from pyro import poutine
from pyro.infer.autoguide.initialization import init_to_value
from scipy.special import logsumexp

from .grid_axis import GridAxis
from .laplace import Gaussian, exact_hessian
from .mixture import allocate, laplace_log_mass
from .mode import find_map, grad_or_refused, newton_decrement
from .space import Unconstrained
from .trust_region import polish


NEWTON_STEPS = 30  # trust-region Newton trials from a search's start before L-BFGS takes over
CONVERGED = 1e-6  # Newton decrement at a mode (find_map's test: 1e-3 posterior sd from the quadratic model's mode)
SAME_MODE = 1e-2  # whitened distance (in each end's Hessian metric) within which two search ends are one mode
CHORD_STEPS = 20  # chord iterations (gradients only) that may take a start into a mode already found
ROUNDING = 1e-8  # whitened step at which a chord iteration has converged to the last digits


@dataclass
class _Mode:
    """A conditional mode at one grid point: unconstrained z, potential, Hessian, Laplace log mass
    (with the grid's Jacobian) and the mode (at a neighbouring point) it was continued from."""
    z: torch.Tensor
    potential: float
    hessian: torch.Tensor
    log_mass: float
    parent: tuple | None  # (point, mode) or None: found from init


def nested_laplace(model, data: dict, grids: dict, init: dict, num_samples: int, seed: int = 0, log=()) -> dict:
    """Posterior draws of ``model(**data)`` with the scalar sites of ``grids`` ({site: increasing
    points}; those in ``log`` integrated over log site; each grid's ends should carry negligible
    weight: check each marginal's ``end_weights``) integrated on their product grid
    (``bayespd.infer.grid_axis``, the rule along each), the other sites Laplace given them at each of
    their conditional modes (module docstring); ``init``: constrained start values.
    Returns ``{"draws": {site: (num_samples, ...)}, "marginals": {grid site: {"grid", "log_marginal"
    (per point, its quadrature weight included, up to a constant), "weights", "end_weights"}}, "points"
    (each grid point's indices, C order), then per point: "log_marginal" (the grid sites' joint log
    density, over log site for those in ``log``, up to a constant: its largest 0), "mode_log_masses"
    (largest first, on that scale), "searches", "evaluations" ((gradients, exact Hessians), all its
    searches), "wall_time_s"}``."""
    axes = [GridAxis(site, grid, site in log) for site, grid in grids.items()]
    if not axes or not set(log) <= set(grids):
        raise ValueError(f"give at least one site to integrate on a grid, and name in log only grid sites ({list(grids)}), "
                         f"got {list(log)}")
    shape = tuple(len(a.grid) for a in axes)
    points = list(itertools.product(*map(range, shape)))
    index = {p: j for j, p in enumerate(points)}
    free = {k: torch.as_tensor(v) for k, v in init.items() if k not in grids}
    spaces = {}

    def space(j):
        if j not in spaces:
            fixed = {a.site: torch.tensor(a.grid[i], dtype=torch.float64) for a, i in zip(axes, points[j])}
            spaces[j] = Unconstrained(poutine.condition(model, data=fixed), data, init_to_value(values=free))
        return spaces[j]

    def neighbours(j):
        for axis in range(len(axes)):
            for step in (-1, 1):
                p = list(points[j])
                p[axis] += step
                if 0 <= p[axis] < shape[axis]:
                    yield index[tuple(p)]

    modes = [[] for _ in points]
    searches, gradients, hessians = (np.zeros(len(points), int) for _ in range(3))
    wall = np.zeros(len(points))
    centre = tuple(_nearest(a, init.get(a.site)) for a in axes)
    from_init = sorted((j for j, p in enumerate(points) if sum(i != c for i, c in zip(p, centre)) <= 1),
                       key=lambda j: sum(abs(i - c) for i, c in zip(points[j], centre)))  # the lines through centre
    continuations, unsearched = deque(), deque(from_init)  # (point, start or None for init, parent)
    while continuations or unsearched:
        j, start, parent = continuations.popleft() if continuations else (unsearched.popleft(), None, None)
        t = time.perf_counter()
        guide = None if parent is None else modes[parent[0]][parent[1]].hessian
        end, (n_grad, n_hess) = _search(space(j), space(j).initial if start is None else start, modes[j], guide)
        searches[j] += 1
        gradients[j] += n_grad
        hessians[j] += n_hess
        z, u, h = end or (None, None, None)
        mass = None if end is None else laplace_log_mass(u, h)
        if mass is not None and not any(_same_mode(z, h, m.z, m.hessian) for m in modes[j]):
            jacobian = sum(a.log_jacobian(i) for a, i in zip(axes, points[j]))
            modes[j].append(_Mode(z, u, h, mass + jacobian, parent))
            i = len(modes[j]) - 1
            continuations.extend((k, _extrapolate(modes, points, index, j, i, k), (j, i)) for k in neighbours(j))
        wall[j] += time.perf_counter() - t
    empty = [{a.site: float(a.grid[i]) for a, i in zip(axes, points[j])} for j in range(len(points)) if not modes[j]]
    if empty:
        raise ValueError(f"no conditional mode with a positive definite Hessian at {empty}: every search ended on a "
                         "saddle, ridge or kink; narrow the grids, or tighten the priors there")
    masses = [sorted((m.log_mass for m in point), reverse=True) for point in modes]
    log_joint = np.reshape([logsumexp(m) for m in masses], shape)
    lines = [np.moveaxis(log_joint, axis, -1) for axis in range(len(axes))]  # each site's grid lines, last
    log_weight = sum(np.moveaxis(np.apply_along_axis(a.log_weights, -1, line), -1, axis)
                     for axis, (a, line) in enumerate(zip(axes, lines)))
    top = (log_joint + log_weight).max()
    pairs = [(j, m) for j in range(len(points)) for m in sorted(modes[j], key=lambda m: -m.log_mass)]
    weights = np.exp(np.array([m.log_mass + log_weight[points[j]] for j, m in pairs]) - top)
    weights /= weights.sum()
    generator = torch.Generator().manual_seed(seed)
    parts = []
    for (j, mode), count in zip(pairs, allocate(weights, num_samples)):
        if count:
            p = points[j]
            gaussian = Gaussian(mode.z, mode.hessian, space(j).labels)
            values = {k: v.detach() for k, v in space(j).constrain(gaussian.sample(int(count), generator)).items()}
            values |= {a.site: a.draw(p[axis], line[p[:axis] + p[axis + 1:]], int(count), generator)
                       for axis, (a, line) in enumerate(zip(axes, lines))}
            parts.append(values)
    draws = {k: torch.cat([p[k] for p in parts]).numpy() for k in parts[0]}
    return {"draws": draws, "marginals": _marginals(axes, log_joint + log_weight - top), "points": points,
            "log_marginal": (log_joint.ravel() - log_joint.max()).tolist(),
            "mode_log_masses": [[m - log_joint.max() for m in point] for point in masses],
            "searches": searches.tolist(), "evaluations": [[int(g), int(h)] for g, h in zip(gradients, hessians)],
            "wall_time_s": wall.tolist()}


def _marginals(axes, log_mass) -> dict:
    """Each grid site's log marginal mass per point (the others summed out, each point's quadrature
    weight included), its normalised weights and end weights."""
    out = {}
    for axis, a in enumerate(axes):
        others = tuple(b for b in range(len(axes)) if b != axis)
        log_marginal = logsumexp(log_mass, axis=others) if others else log_mass
        weights = np.exp(log_marginal - log_marginal.max())
        weights /= weights.sum()
        out[a.site] = {"grid": a.grid.tolist(), "log_marginal": (log_marginal - log_marginal.max()).tolist(),
                       "weights": weights.tolist(), "end_weights": [float(weights[0]), float(weights[-1])]}
    return out


def _nearest(axis, value) -> int:
    """The index of ``axis``'s point nearest ``value`` (in its variable), the middle one for None."""
    if value is None:
        return len(axis.grid) // 2
    x = math.log(float(value)) if axis.log else float(value)
    return int(np.argmin(np.abs(axis.x - x)))


def _same_mode(za, ha, zb, hb) -> bool:
    """Two search ends are one mode when each lies within SAME_MODE of the other in both ends'
    Hessian metrics. An end that passed the decrement test lies within sqrt(CONVERGED) = 1e-3
    whitened units of its mode, so two ends of one mode lie within 2e-3; two distinct minima of a
    smooth potential are separated by a saddle, whitened distance O(1) (closer than 1e-2 the barrier
    between them would be ~1e-4 nats and their Laplace masses one)."""
    return max(_whitened(za - zb, ha), _whitened(za - zb, hb)) <= SAME_MODE


def _extrapolate(modes, points, index, j, i, k):
    """Start for continuing mode i of point j to its neighbour k: linear along that grid line
    (2 z - z_parent) where the mode was itself continued from the point beyond j, else its own z."""
    mode = modes[j][i]
    beyond = index.get(tuple(2 * a - b for a, b in zip(points[j], points[k])))
    if mode.parent is not None and mode.parent[0] == beyond:
        return 2 * mode.z - modes[mode.parent[0]][mode.parent[1]].z
    return mode.z


def _search(space, start, known, guide=None):
    """One search at a grid point from ``start`` (unconstrained): ((z, potential, exact Hessian) of
    the mode it ends at, or None where it ends at one of ``known``, the point's modes so far),
    (gradient evaluations, Hessian evaluations)). A start from which the chord iteration on a known
    mode's Hessian contracts into it (``_chord``, gradients only) ends there; otherwise the chord
    iteration on ``guide`` (the Hessian of the mode continued, at the neighbouring point; else the
    nearest known mode's) while it contracts, to a known mode (gradients only) or to a mode the
    exact Hessian confirms; otherwise trust-region Newton steps while they converge, else
    ``find_map`` from ``start`` (from ``init`` where the model refuses ``start``)."""
    hessians, gradients = [], 0

    def hessian(z):
        hessians.append(None)
        return exact_hessian(space, z)

    known = sorted(known, key=lambda m: _whitened(start - m.z, m.hessian))
    for mode in known:
        reached, _, evaluations = _chord(space, start, mode.hessian, mode.z)
        gradients += evaluations
        if reached:
            return None, (gradients, 0)
    evaluate = partial(grad_or_refused, space)
    guide = guide if guide is not None or not known else known[0].hessian
    if guide is not None:
        reached, start, evaluations = _chord(space, start, guide)
        gradients += evaluations
        if reached and any(_whitened(start - m.z, m.hessian) <= SAME_MODE for m in known):
            return None, (gradients, 0)
    u, g = evaluate(start)
    gradients += 1
    if g is not None:
        h = hessian(start)
        if newton_decrement(g, h) > CONVERGED:
            start, u, g, h, trials = polish(evaluate, hessian, start, u, g, h, NEWTON_STEPS)
            gradients += trials
        if newton_decrement(g, h) <= CONVERGED:
            return (start, float(u), h), (gradients, len(hessians))
    z, u, _, h, evaluations = find_map(space, hessian, progress=False, start=start if g is not None else None)
    return (z, u, h), (gradients + evaluations, len(hessians))


def _chord(space, z, hessian, target=None):
    """The chord iteration z <- z - H^-1 grad U(z) on a fixed positive definite ``hessian`` H, for
    at most CHORD_STEPS while it contracts. With a ``target`` (a mode of Hessian H): whether it takes
    z within SAME_MODE whitened units of it, nearer at every step (near a mode it contracts at the
    rate |I - H^-1 H(z)| < 1, so a start it takes there lies in that mode's basin, found without a
    Hessian). Without: whether its steps shrink, each shorter than the last, to ROUNDING whitened
    units (a mode to the last digits, where its Laplace mass is taken: a mode 1e-3 sd off, the
    decrement test's bound, shifts the log mass by 1e-3 times U's third derivative in sd units).
    Returns (reached, the last point it contracted to, gradient evaluations)."""
    chol = torch.linalg.cholesky((hessian + hessian.T) / 2)
    before = math.inf if target is None else _whitened(z - target, hessian)
    for n in range(1, CHORD_STEPS + 1):
        _, g = grad_or_refused(space, z)
        if g is None:
            return False, z, n
        step = torch.cholesky_solve(g[:, None], chol)[:, 0]
        after = _whitened(z - step - target, hessian) if target is not None else _whitened(step, hessian)
        if after <= (SAME_MODE if target is not None else ROUNDING):
            return True, z - step, n
        if not after < before:
            return False, z, n
        z, before = z - step, after
    return False, z, CHORD_STEPS


def _whitened(d, h) -> float:
    """|d| in the metric of h: sqrt(d^T h d)."""
    return math.sqrt(max(float(d @ h @ d), 0.0))
