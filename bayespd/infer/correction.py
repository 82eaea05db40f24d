"""Exactness correction of an approximate posterior by Pareto-smoothed importance sampling.

A cheap model (a reduced-order forward model, a coarse discretisation) is fitted; its draws
theta_s are then reweighted towards the posterior of the exact model by the importance ratios
``log w_s = log p_exact(y, theta_s) - log p_approx(y, theta_s)`` (the log joints of the two
Pyro models conditioned on the draw: priors may differ, the latent sites may not). Only a
thinned set of draws is used, since every exact evaluation is a full solve. The ratios are
Pareto smoothed (PSIS, Vehtari, Simpson, Gelman, Yao & Gabry 2024, "Pareto smoothed importance
sampling", JMLR 25(72)): the largest ones are replaced by the quantiles of a generalized Pareto
distribution fitted to them, whose shape k diagnoses the estimate. For k <= 0.7 the
self-normalised estimates converge at a usable rate; for k > 0.7 the weights are too
heavy-tailed (the approximation misses mass of the exact posterior) and nothing is reported.
"""

import itertools
import math
import time
import warnings

import arviz as az
import numpy as np
import pandas as pd
import torch
import xarray as xr
from pyro import poutine
from pyro.infer.autoguide.initialization import init_to_median
from pyro.poutine.condition_messenger import ConditionMessenger
from pyro.poutine.util import site_is_subsample
from scipy.special import logsumexp
from tqdm.auto import tqdm

from .mode import REFUSED
from .space import Unconstrained

GROUP = "importance"
K_MAX = 0.7  # Vehtari et al. (2024): beyond it the estimates are unreliable whatever the draws
K_GOOD = 0.5
# arviz.psislw fits the largest ceil(S / 5) ratios (for S <= 225) and needs 5 of them
MIN_DRAWS = 21
STATISTICS = ("mean", "sd", "mcse_mean", "q05", "q95")
# log ratios spread by at most this are taken as equal: the weights are uniform to 1e-8 (the
# models differ by a constant) and their ties leave no tail for a Pareto fit
AGREE = 1e-8


class UnreliableCorrectionError(RuntimeError):
    """The importance correction has Pareto k > 0.7: its reweighted summary is not reported."""


class _ConditionLatent(ConditionMessenger):
    """``poutine.condition`` that leaves ``pyro.deterministic`` sites alone (the exact model
    recomputes them; a stored approximate value must not leak into its likelihood)."""

    def _pyro_sample(self, msg):
        if not msg["infer"].get("_deterministic"):
            super()._pyro_sample(msg)


def importance_correction(tree: xr.DataTree, approximate, exact, data: dict, num_draws: int = 200,
                          progress: bool = False) -> xr.DataTree:
    """``tree`` (a fit of ``approximate``) plus a group ``importance``: the posterior of ``exact``
    estimated by Pareto-smoothed importance sampling of ``num_draws`` of its draws.

    The draws are evenly spaced over the flattened (chain, draw) set. At each, both models are
    traced conditioned on its latent sites (under ``torch.no_grad``), and ``log w = log p_exact(y,
    theta) - log p_approx(y, theta)`` (every sample site: priors and likelihood) is smoothed by
    ``arviz.psislw`` (Vehtari et al. 2024; the thinned draws are taken as independent, r_eff = 1).

    The group, over a dim ``sample`` (coordinates ``chain`` and ``draw``: where each draw came
    from): the latent sites' values; ``log_joint_exact``, ``log_joint_approximate``;
    ``log_weight_raw`` and ``log_weight_psis``, both normalised (logsumexp 0); and per site
    ``corrected_<site>`` over a dim ``statistic`` = (mean, sd, mcse_mean, q05, q95): the weighted
    mean, sd, Monte-Carlo standard error of the mean (sqrt(sum w^2 (theta - mean)^2), the
    delta-method error of a self-normalised estimate from independent draws) and 5 / 95 % weighted quantiles.
    Attributes: ``pareto_k``, ``ess`` (1 / sum w^2 of the smoothed weights), ``num_draws``,
    ``reliable`` (1 if k <= 0.7, else 0: NetCDF has no booleans), ``wall_time_s`` (the whole
    correction), ``exact_wall_time_s`` and ``approximate_wall_time_s`` (the model evaluations).

    Log ratios that agree to ``AGREE`` (models that differ by a constant) give uniform weights
    and k = -inf (the weights are as bounded as can be; a Pareto fit of ties is undefined).
    With k > 0.7 the ``corrected_*`` variables are NaN, ``reliable`` is 0 and a ``UserWarning``
    says why; with 0.5 < k <= 0.7 (or k above the sample-size bound 1 - 1/log10 S) a softer one.
    :func:`corrected_summary` reads the result back.
    """
    if "posterior" not in tree.children:
        raise ValueError("importance_correction needs a tree with a posterior group: the output of fit(...)")
    posterior = tree["posterior"].to_dataset()
    available = posterior.sizes.get("chain", 0) * posterior.sizes.get("draw", 0)
    if not isinstance(num_draws, (int, np.integer)) or not MIN_DRAWS <= num_draws <= available:
        raise ValueError(
            f"num_draws must be an integer from {MIN_DRAWS} (PSIS fits a generalized Pareto tail to the "
            f"largest fifth of the weights and needs 5 of them) to the {available} draws of the posterior, "
            f"not {num_draws!r}: {'fit more draws' if available < MIN_DRAWS else 'choose num_draws in that range'}")
    chain, draw = np.divmod(np.linspace(0, available - 1, num_draws).round().astype(int), posterior.sizes["draw"])
    index = {"chain": xr.DataArray(chain, dims="sample"), "draw": xr.DataArray(draw, dims="sample")}

    start = time.perf_counter()
    log_joint = {"approximate": np.empty(num_draws), "exact": np.empty(num_draws)}
    seconds = {"approximate": 0.0, "exact": 0.0}
    sites = {}
    with torch.no_grad():
        for s in tqdm(range(num_draws), "importance", disable=not progress):
            values = {k: torch.as_tensor(v.values) for k, v in posterior.isel(chain=chain[s], draw=draw[s]).items()}
            for name, model in (("approximate", approximate), ("exact", exact)):
                tic = time.perf_counter()
                trace = poutine.trace(_ConditionLatent(values)(model)).get_trace(**data)
                log_joint[name][s] = float(trace.log_prob_sum(lambda _, site: not site_is_subsample(site)))
                seconds[name] += time.perf_counter() - tic
                if s == 0:
                    sites[name] = _latent_sites(trace, values, name)
            if s == 0:
                _check_same_sites(sites)

    bad = ~np.isfinite(log_joint["approximate"]) | np.isnan(log_joint["exact"]) | (log_joint["exact"] == np.inf)
    if bad.any() or np.all(log_joint["exact"] == -np.inf):
        s = int(np.flatnonzero(bad)[0]) if bad.any() else 0
        raise ValueError(
            f"log joints not finite (e.g. at chain {chain[s]}, draw {draw[s]}: approximate "
            f"{log_joint['approximate'][s]}, exact {log_joint['exact'][s]}): the approximate one must be finite "
            "at its own draws (is the tree a fit of `approximate` to these data?), the exact one finite or "
            "-inf, and finite somewhere")
    names = sorted(sites["approximate"])
    group = _weighted_group(xr.Dataset({name: posterior[name].isel(index) for name in names}), log_joint["exact"],
                            log_joint["approximate"])
    group.attrs.update(wall_time_s=time.perf_counter() - start, exact_wall_time_s=seconds["exact"],
                       approximate_wall_time_s=seconds["approximate"])
    out = tree.copy()
    out[GROUP] = xr.DataTree(group)
    return out


def laplace_importance(tree: xr.DataTree, model, data: dict) -> xr.DataTree:
    """``tree`` (a ``method="laplace"`` fit of ``model`` to ``data``) plus the group ``importance``
    of :func:`importance_correction`: its draws reweighted to the exact posterior by PSIS with
    the Laplace Gaussian q as the proposal, ``log w = -U(z) - log q(z)`` on Pyro's unconstrained
    space (U: the potential, Jacobians included; Vehtari et al. 2024, sec. 2: PSIS corrects a
    Gaussian approximation, and its k says whether it may). Every draw is used: one model
    evaluation each. Here ``log_joint_exact`` is -U and ``log_joint_approximate`` log q."""
    stats = tree["sample_stats"].to_dataset() if "sample_stats" in tree.children else xr.Dataset()
    if "mode_unconstrained" not in stats or "covariance_unconstrained" not in stats:
        raise ValueError("laplace_importance needs a fit with method='laplace' (its sample_stats hold the mode "
                         "and covariance on the unconstrained space)")
    posterior = tree["posterior"].to_dataset()
    start = time.perf_counter()
    space = Unconstrained(model, data, init_to_median)
    if space.labels != [str(v) for v in stats["unconstrained"].values]:
        raise ValueError(f"the model's unconstrained coordinates {space.labels} are not the fit's "
                         f"{list(stats['unconstrained'].values)}: pass the model the tree was fitted with")
    flat = posterior.stack(sample=("chain", "draw")).transpose("sample", ...)
    z = space.unconstrain({k: torch.as_tensor(flat[k].values) for k in space.names})
    proposal = torch.distributions.MultivariateNormal(
        torch.as_tensor(stats["mode_unconstrained"].values), torch.as_tensor(stats["covariance_unconstrained"].values))
    with torch.no_grad():
        log_target = np.array([_log_density(space, row) for row in z])
        log_proposal = proposal.log_prob(z).numpy()
    if not np.isfinite(log_proposal).all() or np.isnan(log_target).any() or (log_target == np.inf).any():
        raise ValueError("the Laplace draws give non-finite densities: is the tree a Laplace fit of this model "
                         "to these data?")
    values = xr.Dataset({k: (("sample", *flat[k].dims[1:]), flat[k].values) for k in space.names})
    group = _weighted_group(values, log_target, log_proposal)
    group.attrs["wall_time_s"] = time.perf_counter() - start
    out = tree.copy()
    out[GROUP] = xr.DataTree(group)
    return out


def _log_density(space, z) -> float:
    """-U(z), or -inf where the model refuses the parameters (``mode.REFUSED``: outside its support)."""
    try:
        return -float(space.potential(z))
    except REFUSED:
        return -math.inf


def _weighted_group(values: xr.Dataset, log_target: np.ndarray, log_proposal: np.ndarray) -> xr.Dataset:
    """``values`` (over ``sample``) with the raw and PSIS-smoothed log weights of target over
    proposal, the ``corrected_*`` statistics (NaN when k > 0.7) and the attributes ``pareto_k``,
    ``ess``, ``num_draws``, ``refused_draws``, ``reliable``, ``pareto_k_max``. A draw with
    log_target = -inf (refused by the model) has weight 0; PSIS smooths the others."""
    log_ratio = log_target - log_proposal
    num_draws, kept = len(log_ratio), np.isfinite(log_ratio)
    if not kept.any():
        raise ValueError("the model refuses every draw of the approximation (zero exact density at all of "
                         "them): the approximation misses the model's support; fit it again or draw more")
    log_raw = log_ratio - logsumexp(log_ratio)
    log_psis = np.full(num_draws, -math.inf)
    if np.ptp(log_ratio[kept]) <= AGREE:  # the models differ by a constant: uniform weights, nothing to fit
        log_psis[kept], k = log_raw[kept], -math.inf
    else:
        log_psis[kept], k = az.psislw(log_ratio[kept], reff=1.0)
        k = float(k)
    weights = np.exp(log_psis)
    reliable = bool(k <= K_MAX)
    _warn(k, num_draws)
    group = values.copy()
    group["log_joint_exact"] = ("sample", log_target)
    group["log_joint_approximate"] = ("sample", log_proposal)
    group["log_weight_raw"] = ("sample", log_raw)
    group["log_weight_psis"] = ("sample", log_psis)
    for name in values.data_vars:
        stats = _weighted_statistics(group[name].values, weights)
        group[f"corrected_{name}"] = (("statistic", *group[name].dims[1:]),
                                      stats if reliable else np.full_like(stats, np.nan))
    group = group.assign_coords(sample=np.arange(num_draws), statistic=list(STATISTICS))
    group.attrs = {"pareto_k": k, "ess": float(1.0 / np.sum(weights**2)), "num_draws": int(num_draws),
                   "refused_draws": int(num_draws - kept.sum()),
                   "reliable": int(reliable), "pareto_k_max": K_MAX}
    return group


def corrected_summary(tree: xr.DataTree) -> pd.DataFrame:
    """The importance-corrected posterior summary of :func:`importance_correction`: one row per
    latent scalar, labelled as ``az.summary`` labels them (``b[0]``, ``b[1]``, or the dim's
    coordinates ``b[u]``, ``b[v]``), the columns of ``STATISTICS``;
    ``df.attrs`` holds ``pareto_k``, ``ess`` and ``num_draws``. Raises
    ``UnreliableCorrectionError`` when the correction had Pareto k > 0.7."""
    if GROUP not in tree.children:
        raise ValueError(f"the tree has no {GROUP!r} group: run importance_correction(tree, ...) first")
    group = tree[GROUP].to_dataset()
    attrs = group.attrs
    if not int(attrs["reliable"]):
        raise UnreliableCorrectionError(
            f"the importance correction is unreliable (Pareto k = {attrs['pareto_k']:.2f} > {K_MAX}): "
            "its summary is not reported. Improve the approximation, draw more, or fit the exact model")
    rows = {}
    for name in sorted(v for v in group.data_vars if v.startswith("corrected_") and "statistic" in group[v].dims):
        stats = group[name].transpose("statistic", ...)
        labels = [group[d].values if d in group.coords else range(stats.sizes[d]) for d in stats.dims[1:]]
        flat = stats.values.reshape(len(STATISTICS), -1)
        for i, idx in enumerate(itertools.product(*labels)):
            rows[name.removeprefix("corrected_") + (f"[{', '.join(map(str, idx))}]" if idx else "")] = flat[:, i]
    df = pd.DataFrame.from_dict(rows, orient="index", columns=list(group["statistic"].values))
    df.attrs = {k: attrs[k] for k in ("pareto_k", "ess", "num_draws")}
    return df


def _latent_sites(trace, values, model_name):
    """The latent sites of a trace conditioned on ``values``; a latent site the posterior lacks
    is refused."""
    latent, missing = set(), []
    for name, site in trace.nodes.items():
        if site["type"] != "sample" or site_is_subsample(site) or site["infer"].get("_deterministic"):
            continue
        if name in values:
            latent.add(name)
        elif not site["is_observed"]:
            missing.append(name)
    if missing:
        raise ValueError(
            f"the {model_name} model samples {', '.join(missing)}, which the posterior lacks: both models must "
            "sample the latent sites of the fitted one (same pyro.sample names; their priors may differ)")
    return latent


def _check_same_sites(sites):
    only_approx = sorted(sites["approximate"] - sites["exact"])
    only_exact = sorted(sites["exact"] - sites["approximate"])
    if only_approx or only_exact:
        raise ValueError(
            f"the approximate and exact models must sample the same latent sites (only in approximate: "
            f"{only_approx}, only in exact: {only_exact}): give both the same pyro.sample names; their "
            "priors may differ")


def _warn(k, num_draws):
    """Vehtari et al. (2024): k > 0.7 unreliable; the error also falls slowly above
    min(0.5, 1 - 1/log10 S) (S draws), where more draws help."""
    if k > K_MAX:
        warnings.warn(
            f"IMPORTANCE CORRECTION UNRELIABLE: Pareto k = {k:.2f} > {K_MAX}. The importance weights "
            "exact/approximate are so heavy-tailed that a few draws dominate (the approximate posterior "
            "misses mass of the exact one) and the reweighted estimates may be far off whatever the number of "
            "draws; the corrected summary is NOT reported (NaN). Make the approximation better (a bigger "
            "reduced basis, a smaller tolerance, a finer discretisation), or fit the exact model.",
            UserWarning, stacklevel=3)
    elif k > min(K_GOOD, 1 - 1 / math.log10(num_draws)):
        warnings.warn(
            f"importance correction: Pareto k = {k:.2f} > {min(K_GOOD, 1 - 1 / math.log10(num_draws)):.2f}: the "
            f"weights are heavy-tailed and the corrected estimates converge slowly; use more draws "
            f"(about {10 ** (1 / (1 - k)):.0f} for this k) or a better approximation", UserWarning, stacklevel=3)


def _weighted_statistics(values, weights):
    """Mean, sd, MCSE of the mean and 5 / 95 % quantiles of ``values`` (sample first) under
    normalised ``weights``; quantiles interpolate the weighted CDF at the midpoints of the
    sorted draws' weights (with equal weights: the Hazen quantile)."""
    w = weights.reshape(-1, *([1] * (values.ndim - 1)))
    mean = np.sum(w * values, axis=0)
    sd = np.sqrt(np.sum(w * (values - mean) ** 2, axis=0))
    mcse = np.sqrt(np.sum(w**2 * (values - mean) ** 2, axis=0))
    flat = values.reshape(len(values), -1)
    quantiles = np.empty((2, flat.shape[1]))
    for j in range(flat.shape[1]):
        order = np.argsort(flat[:, j])
        cdf = np.cumsum(weights[order]) - weights[order] / 2
        quantiles[:, j] = np.interp([0.05, 0.95], cdf, flat[order, j])
    return np.stack([mean, sd, mcse, *quantiles.reshape(2, *values.shape[1:])])
