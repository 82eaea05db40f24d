"""The posterior mode on Pyro's unconstrained space, from one start or several.

``find_map``: L-BFGS on the potential U(z) = -log p(y, z), restarted while it still falls
(a line search that meets a kink stops early), then trust-region Newton steps on the
Laplace step's Hessian (``trust_region``). ``best_map``: the lowest of several searches,
from the initial point and from a Latin hypercube of prior draws. A PD likelihood can have
several basins in delta, split by kinks where a bond length crosses delta +- h/2 (the
partial-volume weights are piecewise linear in delta) or delta (a clamped influence; ``Bonds.kinks``
lists both): on the 64-particle calibration plate,
searches from the prior median end in one of three basins with potentials up to 120 nats apart,
the lowest usually near the true delta, and a chain started in another stays there
(``experiments/sbc.py --free-delta``).
"""

import json
import math
import warnings
from functools import partial

import numpy as np
import torch
from scipy.optimize import minimize
from tqdm.auto import tqdm

from bayespd.materials import ParameterRangeError
from bayespd.linalg.sparse import NotPositiveDefiniteError

from .space import init_trace
from .trust_region import polish

MODE_GAP = 3.0  # nats: a second mode closer than this to the best holds >= 5 % of its density
BARRIER = 1.0  # nats above the higher of two search ends that make them separate modes


# parameters the model refuses; torch.linalg.LinAlgError: a likelihood covariance that is not
# positive definite there (a trial step to extreme moduli: the error term's scale under- or overflows)
REFUSED = (NotPositiveDefiniteError, ParameterRangeError, torch.linalg.LinAlgError)


def _grad(space, z):
    z = z.detach().requires_grad_()
    u = space.potential(z)
    return u.detach(), torch.autograd.grad(u, z, materialize_grads=True)[0]


def grad_or_refused(space, z):
    """(potential, gradient) at z, or (inf, None) where the model refuses the parameters (non-
    finite or not positive definite, e.g. a kernel with m <= 0): a rejected trial point."""
    try:
        return _grad(space, z)
    except REFUSED:
        return math.inf, None


def find_map(space, hessian_fn=None, gtol=1e-8, max_iter=1000, newton_steps=30, restarts=20,
             progress=True, start=None):
    """Mode of the potential: L-BFGS from ``start`` (default ``space.initial``), then (given
    ``hessian_fn``) at most ``newton_steps`` trust-region Newton trials on that Hessian
    (``trust_region.polish``: a saddle or an early stop with an indefinite Hessian is followed
    down to a mode); a trial point the model refuses is an infinite potential (rejected, the
    trust region shrinks), never an error. Returns (z, potential, gradient, Hessian or None,
    gradient evaluations)."""
    def value_and_grad(x):
        """A trial step into parameters the model refuses (non-finite or not positive
        definite) is an infinite potential: the line search backs off from it."""
        u, g = grad_or_refused(space, torch.as_tensor(x))
        return (math.inf, np.zeros_like(x)) if g is None else (float(u), g.numpy())

    x, evaluations, f = (space.initial if start is None else start).numpy(), 0, math.inf
    with tqdm(desc="MAP (L-BFGS)", disable=not progress) as bar:
        for _ in range(restarts):  # a line search that meets a kink (the partial-volume weights
            # are piecewise linear in delta) or a refused point stops L-BFGS early, and scipy
            # may call that convergence: restart from there while the potential still falls
            res = minimize(value_and_grad, x, jac=True, method="L-BFGS-B",
                           options={"maxiter": max_iter, "gtol": gtol, "ftol": 1e-15},
                           callback=lambda _: bar.update())
            evaluations += res.nfev
            fell = res.fun < f - 1e-12 * abs(res.fun)
            x, f = res.x, min(f, res.fun)
            if "GRADIENT" in str(res.message) or not fell:
                break
    z = torch.as_tensor(x)
    u, g = _grad(space, z)
    evaluations += 1
    h = None if hessian_fn is None else hessian_fn(z)
    if h is not None:
        z, u, g, h, trials = polish(partial(grad_or_refused, space), hessian_fn, z, u, g, h, newton_steps)
        evaluations += trials
    _warn_if_not_a_mode(g, h, u, res)
    return z, float(u), g, h, evaluations


def newton_decrement(g, h) -> float:
    """g^T H^-1 g (twice the quadratic model's predicted decrease), inf where H is not positive
    definite."""
    chol, info = torch.linalg.cholesky_ex((h + h.T) / 2)
    return float(g @ torch.cholesky_solve(g[:, None], chol)[:, 0]) if not info else math.inf


def _warn_if_not_a_mode(g, h, u, res):
    """Warn when the search ended where the gradient does not vanish: Newton decrement
    g^T H^-1 g above 1e-6 (more than 1e-3 posterior sd from the quadratic model's mode), or,
    without a Hessian, when max |grad| exceeds 1e-4 max(1, |potential|) (a stall at a kink
    ends L-BFGS through its relative-reduction test, which scipy also calls success)."""
    if h is not None:
        decrement = newton_decrement(g, h)
        if decrement <= 1e-6:
            return
        detail = f"Newton decrement {decrement:.3g}"
    elif float(g.abs().max()) <= 1e-4 * max(1.0, abs(float(u))):
        return
    else:
        detail = f"L-BFGS: {res.message}"
    warnings.warn(f"the MAP search ended where the gradient does not vanish (|grad| = "
                  f"{float(g.norm()):.3g}, {detail}): the potential has kinks in delta where a "
                  "bond length crosses delta or delta +- h/2 (Bonds.kinks), and a search can stop "
                  "at one (a spurious local mode, or a mode on a kink, where a Laplace "
                  "approximation is not defined); start elsewhere (init_values), fix delta, or "
                  "integrate delta on a grid holding its kinks (infer.nested.nested_laplace)",
                  RuntimeWarning, stacklevel=3)


def prior_starts(space, model, data, init, n: int, seed: int) -> list[torch.Tensor]:
    """``n`` unconstrained starting points: a Latin hypercube of each latent site's prior
    (its distribution in the trace at ``init``; for a hierarchical prior, at the parents'
    initial values): 16 n draws per site, sorted elementwise, one from each of n equal
    quantile bands, the bands shuffled independently per site."""
    trace = init_trace(model, data, init)
    rng = np.random.default_rng(seed)
    picks = np.arange(n) * 16 + 8
    values = {}
    with torch.random.fork_rng():
        torch.manual_seed(seed)
        for k in space.names:
            draws = trace.nodes[k]["fn"].sample((16 * n,)).sort(dim=0).values
            values[k] = draws[torch.as_tensor(rng.permutation(picks))]
    z = space.unconstrain(values)
    return list(z.reshape(n, -1).detach())


def separated(space, za, ua: float, zb, ub: float) -> bool:
    """True when the searches that ended at za and zb found different basins: the potential
    rises more than BARRIER nats above the higher end somewhere on the segment between them
    (at 1/4, 1/2, 3/4; a point the model refuses counts as a barrier). Searches that stall
    at different kinks of one basin see no barrier and are one mode."""
    if float((za - zb).abs().max()) <= 1e-6 * max(1.0, float(za.abs().max())):
        return False
    top = max(ua, ub)
    for t in (0.25, 0.5, 0.75):
        try:
            u = float(space.potential((1 - t) * za + t * zb).detach())
        except REFUSED:
            return True
        if not u <= top + BARRIER:
            return True
    return False


def distinct_modes(space, model, data, init, starts: int = 1, seed: int = 0, hessian_fn=None,
                   progress=True, warn=True):
    """``find_map`` from ``space.initial`` (the point ``init`` gives ``model(**data)``) and,
    for ``starts`` > 1, from ``starts - 1`` prior points (``prior_starts``); returns (the
    distinct modes found (``separated``), lowest potential first, each a ``find_map`` result
    (z, potential, gradient, Hessian or None); the gradient evaluations of all searches).
    Warns (given ``warn``) when a second mode lies within MODE_GAP nats of the lowest."""
    if int(starts) != starts or starts < 1:
        raise ValueError(f"the number of MAP starts must be a positive integer, got {starts}")
    points = [None] + (prior_starts(space, model, data, init, int(starts) - 1, seed) if starts > 1 else [])
    results = sorted((find_map(space, hessian_fn, progress=progress, start=point) for point in points),
                     key=lambda r: r[1])
    modes = []
    for r in results:
        if all(separated(space, m[0], m[1], r[0], r[1]) for m in modes):
            modes.append(r[:4])
    close = [m[1] for m in modes[1:] if m[1] - modes[0][1] < MODE_GAP]
    if close and warn:
        warnings.warn(f"{len(close)} of the modes found from {len(points)} starts lie within "
                      f"{MODE_GAP:g} nats of the lowest (potentials {modes[0][1]:.6g}, "
                      f"{', '.join(f'{u:.6g}' for u in close)}): the posterior is multimodal and a "
                      "chain started at one mode may not visit the others; pass modes='weighted' "
                      "to fit (chains or Laplace approximations at each mode, mixed by their "
                      "mass), or run chains from each (init_values) and compare",
                      RuntimeWarning, stacklevel=3)
    return modes, sum(r[4] for r in results)


def modes_json(space, modes, **extra) -> str:
    """The modes as a JSON list of {potential, values, **per-mode extras}."""
    return json.dumps([{"potential": m[1], "values": {k: v.tolist() for k, v in space.constrain(m[0]).items()},
                        **{k: v[i] for k, v in extra.items()}} for i, m in enumerate(modes)])


def best_map(space, model, data, init, starts: int = 1, seed: int = 0, hessian_fn=None, progress=True):
    """The lowest of ``distinct_modes``: (its z, potential, gradient, Hessian, the gradient
    evaluations of all searches), and the modes as JSON (``modes_json``)."""
    modes, evaluations = distinct_modes(space, model, data, init, starts, seed, hessian_fn, progress)
    return (*modes[0], evaluations), modes_json(space, modes)
