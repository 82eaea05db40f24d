"""NUTS against the nested Laplace's Gaussian at its heaviest grid points (issue 28, paper 004 phase 1).

experiments/md_learning.py reports the posterior of models/md_dispersion.py (the 2D moduli, the
horizon, the kernel shape, the shells' relative errors s and the common offset's scale tau) by a
nested Laplace: tau and delta by quadrature on a grid (delta's with every kink of the weights as a
point, ``Bonds.kinks``), the rest Laplace given them (``bayespd.infer.nested``). The quadrature's
error is measured by experiments/md_quadrature_check.py; what is left is the Laplace given (tau,
delta), exact for a Gaussian conditional and otherwise carrying its error. This experiment
measures it with the sampler that makes none, at the grid points that carry the posterior: NUTS
(``bayespd.infer.fit``, two chains of 300 + 500, the dense mass matrix seeded by the Laplace) on
the model conditioned on (tau, delta), against ``fit(..., "laplace")`` there (``LAPLACE_DRAWS``).

Why conditioned: the potential is only piecewise smooth in delta, and md_learning's posterior
peaks on a kink (delta = 11.022 A, a bond length). NUTS over delta as well (stop 44, and stop 45's
run) stalls there: after 300 warmup draws its second chain took 12 s a draw (trees of depth ~10)
and was stopped after 70 minutes. Given delta and tau the potential is smooth.

Points: from runs/md_learning/metrics.json (run it first): the grid point with the largest joint
log marginal, and the largest in the horizon's second bump (delta > 11.5 A). Writes
runs/md_nuts_check/metrics.json: per point, both methods' means, sds and 90 % intervals of
lambda + 2 mu and mu (NUTS's also per chain), NUTS's R-hat, bulk ESS and divergences, wall times.

Targets per point: NUTS converged (R-hat <= 1.01, bulk ESS >= 400, no divergence), then the
Laplace's mean within 0.2 NUTS sds of NUTS's plus three Monte Carlo standard errors (sd / sqrt(ESS))
and its sd within 20 % of NUTS's (the Laplace's leading error in a mean is O(n^-1/2) sds for n
informative numbers, about 90 compliance entries here: 0.1 sd, doubled). ``--quick``: short
chains, the first point only (no targets).
"""
from __future__ import annotations

import json
import time

import arviz as az
import numpy as np
import torch
from pyro import poutine

from common import quick_seed_arguments, run_dir, write_metrics
from md_learning import compliance_model, phase_one

from bayespd.infer import fit
from bayespd.infer.calibration import central_interval

NAME = "md_nuts_check"
QUANTITIES = ("lambda_plus_2mu", "mu")
MEAN_SDS, SD_RATIO, RHAT, ESS = 0.2, 0.2, 1.01, 400
SECOND_BUMP = 11.5  # A: delta's second bump lies above it (md_learning: 10 % of the mass at 11.6-12.3 A)
TARGET_ACCEPT = 0.95
LAPLACE_DRAWS = 4000


def quantities(draws: dict) -> dict:
    """lambda + 2 mu, mu, and delta and tau where drawn, from draws of the model's sites (arrays of
    any shape, e.g. (chain, draw))."""
    values = {k: np.asarray(v) for k, v in draws.items()}
    return {"lambda_plus_2mu": values["lam_plus_mu"] + values["mu"], "mu": values["mu"],
            **{k: values[k] for k in ("delta", "tau") if k in values}}


def summary(values: np.ndarray) -> dict:
    values = np.ravel(values)
    lo, hi = central_interval(values)
    return {"mean": float(values.mean()), "sd": float(values.std()), "q05": float(lo), "q95": float(hi)}


def heaviest_points(metrics: dict) -> list[dict]:
    """(tau, delta) of md_learning's grid point with the largest joint log marginal, and of the largest
    in delta's second bump."""
    q = metrics["bayes"]["quadrature"]
    grids = {k: np.asarray(v["grid"]) for k, v in q["marginals"].items()}
    points = [{k: float(grids[k][i]) for k, i in zip(grids, index)} for index in q["points"]]
    order = np.argsort(q["log_marginal"])[::-1]
    first = points[order[0]]
    second = next(points[j] for j in order if points[j]["delta"] > SECOND_BUMP)
    return [first, second]


def compare(model, observed, init, point, quick, seed) -> tuple[dict, dict]:
    """NUTS and the Laplace on ``model`` conditioned on ``point``; their summaries and the targets."""
    conditioned = poutine.condition(model, data={k: torch.tensor(v, dtype=torch.float64) for k, v in point.items()})
    start = {k: torch.as_tensor(v) for k, v in init.items() if k not in point}
    laplace = fit(conditioned, observed, "laplace", num_samples=LAPLACE_DRAWS, seed=seed, progress=False, predictive=False,
                  observed="C", init_values=start)
    samples, warmup = (30, 30) if quick else (500, 300)
    nuts = fit(conditioned, observed, "nuts", num_samples=samples, num_warmup=warmup, num_chains=2, chains="sequential",
               dense_mass=True, mass_matrix_from="laplace", target_accept=TARGET_ACCEPT, seed=seed, progress=False,
               predictive=False, observed="C", init_values=start)
    by_chain, gauss = (quantities({k: v.values for k, v in fitted["posterior"].items()}) for fitted in (nuts, laplace))
    divergences = int(nuts["sample_stats"]["diverging"].values.sum())
    out, targets = {"point": point, "divergences": divergences,
                    "nuts": {"wall_time_s": float(nuts.attrs["wall_time_s"]), "num_grad_evals": int(nuts.attrs["num_grad_evals"]),
                             "samples_per_chain": samples, "warmup": warmup, "chains": 2},
                    "laplace": {"wall_time_s": float(laplace.attrs["wall_time_s"]), "draws": LAPLACE_DRAWS}}, {}
    for k in QUANTITIES:
        rhat, ess = float(az.rhat(by_chain[k])), float(az.ess(by_chain[k], method="bulk"))
        ref, est = summary(by_chain[k]), summary(gauss[k])
        shift, ratio = abs(est["mean"] - ref["mean"]) / ref["sd"], est["sd"] / ref["sd"]
        allowed = MEAN_SDS + 3 / np.sqrt(ess)
        out[k] = {"nuts": ref, "laplace": est, "rhat": rhat, "ess_bulk": ess, "mean_shift_in_nuts_sds": shift,
                  "sd_ratio": ratio, "nuts_per_chain": [summary(c) for c in by_chain[k]]}
        targets |= {f"nuts_{k}_converged": {"value": {"rhat": rhat, "ess_bulk": ess},
                                            "target": f"rhat <= {RHAT}, ess >= {ESS}", "passed": rhat <= RHAT and ess >= ESS},
                    f"{k}_mean_within_{MEAN_SDS}_sd": {"value": shift, "target": allowed, "passed": shift <= allowed},
                    f"{k}_sd_within_{int(SD_RATIO * 100)}pct": {"value": ratio, "target": f"|ratio - 1| <= {SD_RATIO}",
                                                                "passed": abs(ratio - 1) <= SD_RATIO}}
        print(point, k, out[k], flush=True)
    targets["nuts_no_divergence"] = {"value": divergences, "target": 0, "passed": divergences == 0}
    return out, targets


def main():
    args = quick_seed_arguments(__doc__, "short chains, the first point, no targets")
    start = time.perf_counter()
    source = run_dir("md_learning") / "metrics.json"
    if not source.exists():
        raise SystemExit(f"{source} is missing: run experiments/md_learning.py first (its grid points are checked here)")
    points = heaviest_points(json.loads(source.read_text()))[:1 if args.quick else 2]
    one, data = phase_one(False, run_dir("md_learning"))
    model, observed, init, _ = compliance_model(one["best"], data)
    results, targets = [], {}
    for n, point in enumerate(points):
        out, passed = compare(model, observed, init, point, args.quick, args.seed)
        results.append(out)
        targets |= {} if args.quick else {f"point{n}_{k}": v for k, v in passed.items()}
    write_metrics(NAME + ("_quick" if args.quick else ""), {
        "wall_time_s": time.perf_counter() - start, "points": results, "targets": targets,
        "settings": {"seed": args.seed, "dense_mass": True, "mass_matrix_from": "laplace", "target_accept": TARGET_ACCEPT,
                     "source": str(source)}})


if __name__ == "__main__":
    main()
