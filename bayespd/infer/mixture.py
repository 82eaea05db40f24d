"""A posterior over separated modes: each mode's mass, and draws of their mixture.

A chain (or a Laplace approximation) started at one mode of a multimodal posterior may see
that basin only. ``fit(..., modes="weighted")`` fits each mode the MAP search found
(``mode``), splits the space into one cell per mode, estimates the posterior mass
Z_m = integral over cell m of exp(-U(z)) dz of each, and returns draws of the mixture
sum_m w_m p(z | cell m) with w_m = Z_m / sum Z:

* ``laplace_log_mass``: log Z_m of the Gaussian at the mode, -U(z_m) + d/2 log 2 pi
  - 1/2 log det H_m (Laplace's method; the weights of a mixture of Laplace approximations);
* ``cells``: each draw belongs to the mode whose Laplace Gaussian gives it the highest
  density; cells between which the chains move (``merged``: the chains started at one
  mode put at least CROSSING of their draws in another's cell, as over a barrier of a few
  nats between kinks) are one cell, sampled by all their chains. So chains that mix and
  chains that stay put both give the mixture;
* ``harmonic_log_mass``: Geweke's (1999) modified harmonic mean from the draws z_i of all
  chains that fall in a cell and their log densities lp_i = -U(z_i): 1/Z_m = E[q(z) /
  exp(-U(z))] under p(z | cell m) for any density q supported in the cell; q is the Gaussian
  of those draws' mean and covariance truncated to its central ``level`` ellipsoid
  (renormalised by ``level``), so the ratio stays bounded where the chains have been.

Draws are ``allocate``d to the cells in proportion to w (largest remainders) and each
cell's share taken evenly spaced from the chains' draws in it (``stratified``; independent
Laplace or guide draws are simply concatenated, ``one_chain``): every output chain
holds the same mixture, so the result is read like any other fit.
"""

import math

import numpy as np
import torch
from scipy.special import logsumexp
from scipy.stats import chi2

MASS_GAP = math.log(1000.0)  # modes with under 1e-3 of the largest Laplace mass are left out
CROSSING = 0.05  # a share of a mode's chains' draws in another cell that makes the two one
MIN_CELL_DRAWS = 20  # fewer draws in a cell than this: its mass is not estimated (weight 0)


def laplace_log_mass(potential: float, hessian) -> float | None:
    """log of the Laplace mass of a mode; None when the Hessian is not positive definite."""
    if hessian is None:
        return None
    h = (hessian + hessian.T) / 2
    chol, info = torch.linalg.cholesky_ex(h)
    if info:
        return None
    d = h.shape[0]
    return -potential + d / 2 * math.log(2 * math.pi) - float(torch.log(torch.diagonal(chol)).sum())


def kept(modes, log_masses) -> list[int]:
    """Indices of the modes worth fitting: Laplace log mass within MASS_GAP of the largest.
    A mode without one (its Hessian is not positive definite: on a kink) is judged by its
    potential, with the curvature term of the lowest mode that has one."""
    with_mass = [i for i, m in enumerate(log_masses) if m is not None]
    curvature = log_masses[with_mass[0]] + modes[with_mass[0]][1] if with_mass else 0.0
    masses = [m if m is not None else curvature - mode[1] for mode, m in zip(modes, log_masses)]
    return [i for i, m in enumerate(masses) if m >= max(masses) - MASS_GAP]


def harmonic_log_mass(z: np.ndarray, lp: np.ndarray, level: float = 0.5) -> float:
    """log Z of the unnormalised density exp(lp) from draws ``z`` (n, d) of it (module
    docstring). The relative error is about sqrt((1 - level) / (level n_eff)) for a
    Gaussian basin."""
    z, lp = np.asarray(z, dtype=float), np.asarray(lp, dtype=float)
    n, d = z.shape
    mean = z.mean(axis=0)
    cov = np.atleast_2d(np.cov(z, rowvar=False))
    chol = np.linalg.cholesky(cov)
    white = np.linalg.solve(chol, (z - mean).T)
    distance = (white**2).sum(axis=0)
    inside = distance <= chi2.ppf(level, d)
    if not inside.any():
        raise ValueError("no draw lies in the central ellipsoid of the draws: too few draws "
                         "to estimate the mode's mass")
    log_q = (-d / 2 * math.log(2 * math.pi) - np.log(np.diag(chol)).sum() - distance / 2
             - math.log(level))
    return float(-(logsumexp(log_q[inside] - lp[inside]) - math.log(n)))


def mode_weights(log_masses) -> np.ndarray:
    masses = np.asarray(log_masses, dtype=float)
    if not np.isfinite(masses.max()):
        raise ValueError("no mode's mass could be estimated (too few draws in every cell): "
                         "draw more (num_samples)")
    w = np.exp(masses - masses.max())
    return w / w.sum()


def allocate(weights, n: int) -> np.ndarray:
    """Integer counts summing to n, proportional to ``weights`` (largest remainders)."""
    exact = np.asarray(weights, dtype=float) * n
    counts = np.floor(exact).astype(int)
    counts[np.argsort(counts - exact, kind="stable")[: n - counts.sum()]] += 1
    return counts


def one_chain(per_mode: list[dict], counts) -> dict:
    """Independent draws of each mode (``{site: (1, n, ...)}``, e.g. Laplace or guide draws):
    the first ``counts[m]`` of mode m, as one chain ``(1, sum(counts), ...)``."""
    return {k: np.concatenate([np.asarray(d[k])[:, :c] for d, c in zip(per_mode, counts)], axis=1)
            for k in per_mode[0]}


def cells(z, centres, precisions) -> np.ndarray:
    """For each row of ``z`` (n, d), the index of the Gaussian N(centre, precision^-1) under
    which it is most probable."""
    z = np.asarray(z, dtype=float)
    scores = []
    for c, p in zip(centres, precisions):
        c, p = np.asarray(c, dtype=float), np.asarray(p, dtype=float)
        r = z - c
        scores.append(np.linalg.slogdet(p)[1] / 2 - np.einsum("ni,ij,nj->n", r, p, r) / 2)
    return np.argmax(np.stack(scores), axis=0)


def merged(labels, groups, n_cells: int) -> tuple[np.ndarray, list[int]]:
    """``labels`` with communicating cells joined (module docstring), and the cell each
    mode's cell joined: the draws of chains started at mode j are those with
    ``groups == j``; a joined cell takes the lowest index."""
    labels, groups = np.asarray(labels), np.asarray(groups)
    parent = list(range(n_cells))

    def root(a):
        while parent[a] != a:
            a = parent[a]
        return a

    for j in range(n_cells):
        own = labels[groups == j]
        share = np.bincount(own, minlength=n_cells) / max(len(own), 1)
        for k in np.flatnonzero(share >= CROSSING):
            a, b = sorted((root(j), root(int(k))))
            parent[b] = a
    return np.array([root(int(c)) for c in labels]), [root(j) for j in range(n_cells)]


def cell_log_masses(z, lp, labels, n_cells: int) -> list[float]:
    """``harmonic_log_mass`` of each cell from the draws in it; -inf for a cell with fewer
    than MIN_CELL_DRAWS (or under two per dimension) draws, e.g. one joined to another."""
    out = []
    for m in range(n_cells):
        inside = labels == m
        enough = inside.sum() >= max(MIN_CELL_DRAWS, 2 * z.shape[1])
        out.append(harmonic_log_mass(z[inside], lp[inside]) if enough else -math.inf)
    return out


def stratified(arrays: dict, labels, counts, num_chains: int) -> dict:
    """``(num_chains, sum(counts), ...)`` arrays from pooled ``arrays`` (n, ...) whose rows
    belong to the cells ``labels``: ``num_chains x counts[m]`` rows of cell m evenly spaced
    in pooled order (chain after chain), split into one contiguous block per output chain,
    cell after cell. With one cell the chains come back as they were."""
    out = {}
    for k, v in arrays.items():
        parts = []
        for m, c in enumerate(counts):
            rows = np.flatnonzero(labels == m)
            if c:
                index = rows[np.round(np.linspace(0, len(rows) - 1, c * num_chains)).astype(int)]
                parts.append(v[index].reshape(num_chains, c, *v.shape[1:]))
        out[k] = np.concatenate(parts, axis=1)
    return out
