"""NUTS against the nested Laplace on the compliance posterior of the MD sheet (issue 28, paper 004 phase 1).

experiments/md_learning.py reports the posterior of models/md_dispersion.py (the 2D moduli, the
horizon, the kernel shape, the shells' relative errors s and the common offset's scale tau) by a
nested Laplace: tau and delta by quadrature on a grid (delta's with every kink as a point), the rest
Laplace given them at every conditional mode (``bayespd.infer.nested``). That is exact for a Gaussian
conditional and otherwise carries each mode's Laplace error; this experiment measures that error on
the real posterior with the sampler that makes none: NUTS (``bayespd.infer.fit``, two chains of
300 + 1000 from the phase-1 fit, the dense mass matrix seeded by the Laplace covariance at the MAP
and adapted; unseeded, the first windows' trees reach depth 10 at 28 ms a gradient).
Reads the records of experiments/md_graphene_data.py; writes runs/md_nuts_check/metrics.json:
both methods' means, sds and 90 % intervals of lambda + 2 mu, mu, delta and tau (NUTS's also per
chain), NUTS's R-hat, bulk ESS and divergences (per chain), each method's wall time.

The potential is kinked in delta: the partial-volume weights are piecewise linear in it, with a
kink wherever a bond length crosses delta +- h/2, and the Bernstein influence, clamped beyond delta,
kinks where a bond length equals delta (``Bonds.kinks``; on this sheet, 4.90 x 5.04 A cells, at
11.02, 11.21, 11.58, 12.21, 12.29, 12.57 A near the posterior, whose largest peak sits on the kink
at 11.02 A). HMC's leapfrog steps across a kink diverge or stall; a NUTS chain that crosses to
another piece shows as a chain of its own (R-hat, the per-chain summaries), so the targets below may
fail for the reference's sake rather than the Laplace's.
``delta_basins`` records where searches from starts below those kinks end at three tau (on a kink
``find_map`` warns that the gradient does not vanish: there the potential is an upper bound on the
region's minimum and the "log mass" no Laplace mass).

Targets: NUTS converged (R-hat <= 1.01, bulk ESS >= 400 for every reported quantity, no
divergence), so it can serve as the reference; then for each quantity the nested Laplace's mean
within 0.2 NUTS sds of NUTS's plus three Monte Carlo standard errors (sd / sqrt(ESS)), and its
sd within 20 % of NUTS's (the Laplace's leading error in a mean is O(n^-1/2) sds for n informative
numbers, about 90 compliance entries here: 0.1 sd, doubled; tau, integrated by quadrature, has
none of its own). ``--quick``: short chains (no targets).
"""
from __future__ import annotations

import time
from functools import partial

import arviz as az
import numpy as np
import torch

from common import quick_seed_arguments, run_dir, write_metrics
from md_learning import compliance_model, phase_one, quadrature_grids
from pyro import poutine
from pyro.infer.autoguide.initialization import init_to_value

from bayespd.infer import fit
from bayespd.infer.calibration import central_interval
from bayespd.infer.laplace import exact_hessian
from bayespd.infer.mixture import laplace_log_mass
from bayespd.infer.mode import find_map
from bayespd.infer.nested import nested_laplace
from bayespd.infer.space import Unconstrained

NAME = "md_nuts_check"
QUANTITIES = ("lambda_plus_2mu", "mu", "delta", "tau")
MEAN_SDS, SD_RATIO, RHAT, ESS = 0.2, 0.2, 1.01, 400
BASIN_TAUS, BASIN_DELTAS = (0.02, 0.04, 0.08), (11.3, 11.0, 10.6)  # starts below the kinks at 11.58 and 12.21 A
TARGET_ACCEPT = 0.95  # at 0.8 (700 draws a chain), 7 of 1,400 draws diverged


def quantities(draws: dict) -> dict:
    """The reported quantities from draws of the model's sites (flat arrays)."""
    return {"lambda_plus_2mu": np.ravel(draws["lam_plus_mu"]) + np.ravel(draws["mu"]),
            "mu": np.ravel(draws["mu"]), "delta": np.ravel(draws["delta"]), "tau": np.ravel(draws["tau"])}


def summary(values: np.ndarray) -> dict:
    lo, hi = central_interval(values)
    return {"mean": float(values.mean()), "sd": float(values.std()), "q05": float(lo), "q95": float(hi)}


def delta_basins(model, observed, init: dict, taus, deltas) -> list:
    """Where ``find_map`` (L-BFGS, then trust-region Newton) ends from ``init`` with delta moved to each
    of ``deltas``, at each tau: delta, mu, the potential U and the Laplace log mass there (None where
    the Hessian is not positive definite). Ends on different linear pieces of the partial-volume
    weights show as different deltas."""
    found = []
    for tau in taus:
        conditioned = poutine.condition(model, data={"tau": torch.tensor(tau, dtype=torch.float64)})
        for delta in deltas:
            start = {k: torch.as_tensor(v) for k, v in init.items() if k != "tau"} | {"delta": torch.tensor(delta)}
            space = Unconstrained(conditioned, observed, init_to_value(values=start))
            z, u, _, h, _ = find_map(space, partial(exact_hessian, space), progress=False)
            at = space.constrain(z[None])
            positive = bool(torch.linalg.eigvalsh((h + h.T) / 2)[0] > 0)
            found.append({"tau": tau, "start_delta_A": delta, "delta_A": float(at["delta"]), "mu": float(at["mu"]),
                          "potential": float(u), "laplace_log_mass": laplace_log_mass(u, h) if positive else None})
            print(found[-1], flush=True)
    return found


def main():
    args = quick_seed_arguments(__doc__, "short chains, no targets")
    start = time.perf_counter()
    one, data = phase_one(False, run_dir("md_learning"))
    model, observed, init, _ = compliance_model(one["best"], data)
    basins = delta_basins(model, observed, init, BASIN_TAUS, [float(init["delta"]), *BASIN_DELTAS])
    t = time.perf_counter()
    grids = quadrature_grids(data["sheet"])
    nested = nested_laplace(model, observed, grids, init, 4000, seed=args.seed, log=("tau",))
    nested_wall = time.perf_counter() - t
    samples, warmup = (30, 30) if args.quick else (1000, 300)
    tree = fit(model, observed, "nuts", num_samples=samples, num_warmup=warmup, num_chains=2, chains="sequential",
               dense_mass=True, mass_matrix_from="laplace", target_accept=TARGET_ACCEPT, seed=args.seed,
               progress=False, predictive=False, observed="C", init_values={k: torch.as_tensor(v) for k, v in init.items()})
    post = tree["posterior"]
    chains = quantities({k: post[k].values for k in ("lam_plus_mu", "mu", "delta", "tau")})
    by_chain = {k: v.reshape(post.sizes["chain"], post.sizes["draw"]) for k, v in chains.items()}
    stats = tree["sample_stats"]
    divergences = int(stats["diverging"].values.sum())
    per_chain = {"divergences": stats["diverging"].values.sum(1).tolist(), "lp_mean": stats["lp"].values.mean(1).tolist()}
    laplace = quantities(nested["draws"])
    out, targets = {}, {}
    for k in QUANTITIES:
        rhat, ess = float(az.rhat(by_chain[k])), float(az.ess(by_chain[k], method="bulk"))
        ref, est = summary(chains[k]), summary(laplace[k])
        shift = abs(est["mean"] - ref["mean"]) / ref["sd"]
        allowed = MEAN_SDS + 3 / np.sqrt(ess)
        out[k] = {"nuts": ref, "nested_laplace": est, "rhat": rhat, "ess_bulk": ess, "mean_shift_in_nuts_sds": shift,
                  "sd_ratio": est["sd"] / ref["sd"], "nuts_per_chain": [summary(c) for c in by_chain[k]]}
        if not args.quick:
            ratio = est["sd"] / ref["sd"]
            targets[f"nuts_{k}_converged"] = {"value": {"rhat": rhat, "ess_bulk": ess},
                                              "target": f"rhat <= {RHAT}, ess >= {ESS}", "passed": rhat <= RHAT and ess >= ESS}
            targets[f"{k}_mean_within_{MEAN_SDS}_sd"] = {"value": shift, "target": allowed, "passed": shift <= allowed}
            targets[f"{k}_sd_within_{int(SD_RATIO * 100)}pct"] = {"value": ratio, "target": f"|ratio - 1| <= {SD_RATIO}",
                                                                   "passed": abs(ratio - 1) <= SD_RATIO}
        print(k, out[k], flush=True)
    if not args.quick:
        targets["nuts_no_divergence"] = {"value": divergences, "target": 0, "passed": divergences == 0}
    write_metrics(NAME + ("_quick" if args.quick else ""), {
        "wall_time_s": time.perf_counter() - start, "quantities": out, "divergences": divergences, "per_chain": per_chain,
        "delta_basins": basins,
        "nested_laplace": {"wall_time_s": nested_wall, "searches": nested["searches"],
                           "evaluations": nested["evaluations"]},
        "nuts": {"wall_time_s": float(tree.attrs["wall_time_s"]), "num_grad_evals": int(tree.attrs["num_grad_evals"]),
                 "samples_per_chain": samples, "warmup": warmup, "chains": 2},
        "targets": targets, "settings": {"seed": args.seed, "grids": {k: v.tolist() for k, v in grids.items()}, "dense_mass": True,
                                         "mass_matrix_from": "laplace", "target_accept": TARGET_ACCEPT}})


if __name__ == "__main__":
    main()
