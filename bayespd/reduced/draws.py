"""Parameter draws for an approximation-error term: from the prior (Kaipio & Somersalo 2007) or
from a Gaussian on Pyro's unconstrained space, e.g. a Laplace fit or the moments of a first
posterior's draws (Calvetti, Dunlop, Somersalo & Stuart 2018). The numerical core: no Pyro."""
from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch
from torch.distributions import constraints, transform_to


def prior_draws(priors: dict, num: int, seed: int, names: Sequence[str] | None = None) -> list[dict]:
    """``num`` parameter dicts drawn from ``priors`` (``{name: torch distribution}``, Pyro's
    included), only ``names`` if given, reproducibly from ``seed``."""
    names = list(priors) if names is None else list(names)
    missing = set(names) - set(priors)
    if missing:
        raise ValueError(f"no prior for {sorted(missing)} (priors given for {sorted(priors)})")
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        return [{k: priors[k].sample() for k in names} for _ in range(num)]


def _supports(names: Sequence[str], bounds: dict | None) -> list:
    """Per name its open support (low, high), default (0, inf), and the map of the real line onto
    it that Pyro's unconstrained space uses (exp for (low, inf), a scaled sigmoid for (low, high),
    identity for (-inf, inf))."""
    bounds = {} if bounds is None else dict(bounds)
    unknown = set(bounds) - set(names)
    if unknown:
        raise ValueError(f"bounds given for {sorted(unknown)}, which are not among the parameters {list(names)}")
    out = []
    for k in names:
        low, high = (float(v) for v in bounds.get(k, (0.0, math.inf)))
        if not low < high:
            raise ValueError(f"bounds of {k!r} must satisfy low < high, got ({low}, {high})")
        if low == -math.inf:
            support = constraints.real if high == math.inf else constraints.less_than(high)
        else:
            support = constraints.greater_than(low) if high == math.inf else constraints.interval(low, high)
        out.append((low, high, transform_to(support)))
    return out


def _unconstrained(names: Sequence[str], values: torch.Tensor, supports: list) -> torch.Tensor:
    """(draws, p) values mapped to the real line; values on or outside a support are refused."""
    columns = []
    for j, (k, (low, high, transform)) in enumerate(zip(names, supports)):
        inside = (values[:, j] > low) & (values[:, j] < high)
        if not bool(inside.all()):
            bad = values[:, j][~inside][:3].tolist()
            raise ValueError(f"{k} = {bad} lies on or outside its bounds ({low}, {high}): give bounds that hold "
                             "every draw inside (the prior's support, e.g. {'delta': (h, delta_max)})")
        columns.append(transform.inv(values[:, j]))
    return torch.stack(columns, 1)


def _gaussian(names: list, mean: torch.Tensor, covariance: torch.Tensor, supports: list, num: int, seed: int,
              inflate: float) -> list[dict]:
    """``num`` draws z ~ N(mean, inflate * covariance) on the real line, mapped onto the supports."""
    if not inflate > 0:
        raise ValueError(f"inflate must be > 0 (the factor on the covariance), got {inflate}")
    if num < 1:
        raise ValueError(f"num must be >= 1, got {num}")
    p = len(names)
    if covariance.shape != (p, p):
        raise ValueError(f"covariance must be ({p}, {p}) for {names}, got {tuple(covariance.shape)}")
    if not torch.allclose(covariance, covariance.T, rtol=1e-10, atol=0):
        raise ValueError("covariance must be symmetric")
    variance = covariance.diagonal()
    spread = bool((variance > (1e-10 * mean.abs().clamp(min=1.0)).square()).all())  # above rounding
    if not spread or int(torch.linalg.cholesky_ex(covariance / (variance[:, None] * variance).sqrt()).info) != 0:
        raise ValueError(f"covariance of {names} is not positive definite: some combination of the parameters "
                         "has no spread (too few or identical draws, or a parameter held fixed)")
    gen = torch.Generator().manual_seed(seed)
    z = mean + math.sqrt(inflate) * torch.randn(num, p, generator=gen, dtype=torch.float64) @ torch.linalg.cholesky(
        covariance).T
    x = torch.stack([transform(z[:, j]) for j, (_, _, transform) in enumerate(supports)], 1)
    return [dict(zip(names, row)) for row in x]


def gaussian_draws(mean: dict, covariance, num: int, seed: int, *, inflate: float = 1.0,
                   bounds: dict | None = None) -> list[dict]:
    """``num`` parameter dicts from a Gaussian on the unconstrained space, e.g. a Laplace
    approximation: ``mean`` ``{name: value}`` (its centre, in the parameters' own units),
    ``covariance`` (p, p) of the unconstrained parameters (log(x - low) for (low, inf),
    logit((x - low) / (high - low)) for (low, high), as Pyro's; order of ``mean``), multiplied
    by ``inflate``; ``bounds`` ``{name: (low, high)}``, default (0, inf). Reproducible from ``seed``."""
    names = list(mean)
    supports = _supports(names, bounds)
    centre = torch.tensor([[float(mean[k]) for k in names]], dtype=torch.float64)
    z = _unconstrained(names, centre, supports)[0]
    return _gaussian(names, z, torch.as_tensor(covariance, dtype=torch.float64), supports, num, seed, inflate)


def _per_draw_scalar(array) -> bool:
    """One value per draw: a DataArray over (chain, draw) only, or a 1-D array."""
    dims = getattr(array, "dims", None)
    return tuple(dims) == ("chain", "draw") if dims is not None else np.ndim(array) == 1


def posterior_draws(tree, num: int, seed: int, *, names: Sequence[str] | None = None, inflate: float = 1.0,
                    bounds: dict | None = None) -> list[dict]:
    """``num`` parameter dicts from the Gaussian with the mean and covariance of a fitted
    posterior's draws on the unconstrained space (see ``gaussian_draws``), the covariance
    multiplied by ``inflate``: the draws of a posterior-informed error term (module docstring;
    Calvetti et al. 2018). ``tree``: a fit's DataTree (its ``posterior`` group, any chains) or a
    mapping ``{name: draws}``; ``names``: the parameters to draw (default: every scalar one);
    ``bounds`` ``{name: (low, high)}``, default (0, inf), e.g. the prior's support of delta."""
    posterior = tree["posterior"] if "posterior" in tree else tree
    names = [k for k in posterior if _per_draw_scalar(posterior[k])] if names is None else list(names)
    missing = [k for k in names if k not in posterior]
    if missing or not names:
        raise ValueError(f"no posterior draws of {missing or 'any scalar parameter'} (it holds {list(posterior)})")
    wrong = [k for k in names if not _per_draw_scalar(posterior[k])]
    if wrong:
        raise ValueError(f"{wrong} hold more than one value per draw: name scalar parameters only")
    columns = {k: torch.as_tensor(np.asarray(posterior[k]), dtype=torch.float64) for k in names}
    values = torch.stack([columns[k].reshape(-1) for k in names], 1)
    if len(values) < len(names) + 2:
        raise ValueError(f"{len(values)} posterior draws cannot give the covariance of {len(names)} parameters: "
                         f"give at least {len(names) + 2}")
    supports = _supports(names, bounds)
    z = _unconstrained(names, values, supports)
    return _gaussian(names, z.mean(0), torch.cov(z.T).reshape(len(names), len(names)), supports, num, seed,
                     inflate)
