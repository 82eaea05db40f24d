"""NUTS against the nested Laplace on the compliance posterior of the MD sheet (issue 28, paper 004 phase 1).

experiments/md_learning.py reports the posterior of models/md_dispersion.py (the 2D moduli, the
horizon, the kernel shape, the shells' relative errors s and the common offset's scale tau) by a
nested Laplace: tau by quadrature on a grid, the rest Laplace given tau at every conditional mode
(``bayespd.infer.nested``). That is exact for a Gaussian conditional and otherwise carries each
mode's Laplace error; this experiment measures that error on the real posterior with the sampler
that makes none: NUTS (``bayespd.infer.fit``, two chains of 300 + 1000 from the phase-1 fit, the dense
mass matrix seeded by the Laplace covariance at the MAP and adapted; unseeded, the first windows'
trees reach depth 10 at 28 ms a gradient).
Reads the records of experiments/md_graphene_data.py; writes runs/md_nuts_check/metrics.json:
both methods' means, sds and 90 % intervals of lambda + 2 mu, mu, delta and tau, NUTS's R-hat,
bulk ESS and divergences, each method's wall time.

Targets: NUTS converged (R-hat <= 1.01, bulk ESS >= 400 for every reported quantity, no
divergence), so it can serve as the reference; then for each quantity the nested Laplace's mean
within 0.2 NUTS sds of NUTS's plus three Monte Carlo standard errors (sd / sqrt(ESS)), and its
sd within 20 % of NUTS's (the Laplace's leading error in a mean is O(n^-1/2) sds for n informative
numbers, about 90 compliance entries here: 0.1 sd, doubled; tau, integrated by quadrature, has
none of its own). ``--quick``: short chains (no targets).
"""
from __future__ import annotations

import time

import arviz as az
import numpy as np
import torch

from common import quick_seed_arguments, run_dir, write_metrics
from md_learning import TAU_GRID, compliance_model, phase_one
from bayespd.infer import fit
from bayespd.infer.nested import nested_laplace

NAME = "md_nuts_check"
QUANTITIES = ("lambda_plus_2mu", "mu", "delta", "tau")
MEAN_SDS, SD_RATIO, RHAT, ESS = 0.2, 0.2, 1.01, 400
TARGET_ACCEPT = 0.95  # at 0.8 (700 draws a chain), 7 of 1,400 draws diverged


def quantities(draws: dict) -> dict:
    """The reported quantities from draws of the model's sites (flat arrays)."""
    return {"lambda_plus_2mu": np.ravel(draws["lam_plus_mu"]) + np.ravel(draws["mu"]),
            "mu": np.ravel(draws["mu"]), "delta": np.ravel(draws["delta"]), "tau": np.ravel(draws["tau"])}


def summary(values: np.ndarray) -> dict:
    lo, hi = np.quantile(values, [0.05, 0.95])
    return {"mean": float(values.mean()), "sd": float(values.std()), "q05": float(lo), "q95": float(hi)}


def main():
    args = quick_seed_arguments(__doc__, "short chains, no targets")
    start = time.perf_counter()
    one, data = phase_one(False, run_dir("md_learning"))
    model, observed, init, _ = compliance_model(one["best"], data)
    t = time.perf_counter()
    nested = nested_laplace(model, observed, "tau", TAU_GRID, init, 4000, seed=args.seed)
    nested_wall = time.perf_counter() - t
    samples, warmup = (30, 30) if args.quick else (1000, 300)
    tree = fit(model, observed, "nuts", num_samples=samples, num_warmup=warmup, num_chains=2, chains="sequential",
               dense_mass=True, mass_matrix_from="laplace", target_accept=TARGET_ACCEPT, seed=args.seed,
               progress=False, predictive=False, observed="C", init_values={k: torch.as_tensor(v) for k, v in init.items()})
    post = tree["posterior"]
    chains = quantities({k: post[k].values for k in ("lam_plus_mu", "mu", "delta", "tau")})
    by_chain = {k: v.reshape(post.sizes["chain"], post.sizes["draw"]) for k, v in chains.items()}
    divergences = int(tree["sample_stats"]["diverging"].values.sum())
    laplace = quantities(nested["draws"])
    out, targets = {}, {}
    for k in QUANTITIES:
        rhat, ess = float(az.rhat(by_chain[k])), float(az.ess(by_chain[k], method="bulk"))
        ref, est = summary(chains[k]), summary(laplace[k])
        shift = abs(est["mean"] - ref["mean"]) / ref["sd"]
        allowed = MEAN_SDS + 3 / np.sqrt(ess)
        out[k] = {"nuts": ref, "nested_laplace": est, "rhat": rhat, "ess_bulk": ess, "mean_shift_in_nuts_sds": shift,
                  "sd_ratio": est["sd"] / ref["sd"]}
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
        "wall_time_s": time.perf_counter() - start, "quantities": out, "divergences": divergences,
        "nested_laplace": {"wall_time_s": nested_wall, "searches": nested["searches"],
                           "evaluations": nested["evaluations"]},
        "nuts": {"wall_time_s": float(tree.attrs["wall_time_s"]), "num_grad_evals": int(tree.attrs["num_grad_evals"]),
                 "samples_per_chain": samples, "warmup": warmup, "chains": 2},
        "targets": targets, "settings": {"seed": args.seed, "tau_grid": TAU_GRID.tolist(), "dense_mass": True,
                                         "mass_matrix_from": "laplace", "target_accept": TARGET_ACCEPT}})


if __name__ == "__main__":
    main()
