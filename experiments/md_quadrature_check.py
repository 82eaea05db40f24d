"""The quadrature error of md_learning's nested Laplace: its grids against grids with half the step (issue 28).

experiments/md_learning.py integrates tau (a log grid) and delta (a grid with every kink of the
sheet's weights as a point) by quadrature, the rest Laplace given them (``bayespd.infer.nested``).
This run repeats that posterior with delta's step halved, and then tau's too, kinks kept, 4,000
draws each (the same seed), and compares the means, sds and 90 % intervals of delta, lambda + 2 mu,
mu and tau. Reads the records of experiments/md_graphene_data.py; writes
runs/md_quadrature_check/metrics.json with each grid's summaries, points, searches and wall time.

Target: for every quantity, each finer grid's mean within 0.1 sd of md_learning's grid and its sd
within 5 % (the rule's error is second order in the step, so halving the step shows most of the
coarse grid's error; 4,000 draws give a Monte Carlo sd of 0.016 sd for a mean, 1.1 % for an sd).
``--quick``: the quick phase 1, 400 draws (no targets).
"""
from __future__ import annotations

import time

import numpy as np

from common import quick_seed_arguments, run_dir, write_metrics
from md_learning import compliance_model, phase_one, quadrature_grids
from md_nuts_check import quantities, summary

from bayespd.infer.nested import nested_laplace

NAME = "md_quadrature_check"
MEAN_SDS, SD_RATIO = 0.1, 0.05


def halved(grid: np.ndarray, log: bool) -> np.ndarray:
    """``grid`` with a point between each pair (their geometric mean for a log grid)."""
    middle = np.sqrt(grid[1:] * grid[:-1]) if log else (grid[1:] + grid[:-1]) / 2
    return np.sort(np.concatenate([grid, middle]))


def main():
    args = quick_seed_arguments(__doc__, "the quick phase 1, 400 draws, no targets")
    start = time.perf_counter()
    one, data = phase_one(args.quick, run_dir("md_learning" + ("_quick" if args.quick else "")))
    model, observed, init, _ = compliance_model(one["best"], data)
    base = quadrature_grids(data["sheet"], args.quick)
    variants = {"md_learning": base, "delta_halved": {**base, "delta": halved(base["delta"], False)},
                "both_halved": {"tau": halved(base["tau"], True), "delta": halved(base["delta"], False)}}
    runs = {}
    for name, grids in variants.items():
        t = time.perf_counter()
        out = nested_laplace(model, observed, grids, init, 400 if args.quick else 4000, seed=args.seed, log=("tau",))
        runs[name] = {"summary": {k: summary(v) for k, v in quantities(out["draws"]).items()},
                      "points": len(out["points"]), "searches": int(sum(out["searches"])),
                      "end_weights": {k: m["end_weights"] for k, m in out["marginals"].items()},
                      "wall_time_s": time.perf_counter() - t, "grids": {k: v.tolist() for k, v in grids.items()}}
        print(name, runs[name]["summary"], runs[name]["wall_time_s"], flush=True)
    targets = {}
    reference = runs["md_learning"]["summary"]
    for name in ("delta_halved", "both_halved"):
        for k, ref in reference.items():
            fine = runs[name]["summary"][k]
            shift, ratio = abs(fine["mean"] - ref["mean"]) / fine["sd"], ref["sd"] / fine["sd"]
            runs[name].setdefault("mean_shift_in_sds", {})[k] = shift
            runs[name].setdefault("sd_ratio", {})[k] = ratio
            if not args.quick:
                targets[f"{name}_{k}_mean_within_{MEAN_SDS}_sd"] = {"value": shift, "target": MEAN_SDS,
                                                                    "passed": shift <= MEAN_SDS}
                targets[f"{name}_{k}_sd_within_{int(SD_RATIO * 100)}pct"] = {
                    "value": ratio, "target": f"|ratio - 1| <= {SD_RATIO}", "passed": abs(ratio - 1) <= SD_RATIO}
    write_metrics(NAME + ("_quick" if args.quick else ""), {
        "wall_time_s": time.perf_counter() - start, "runs": runs, "targets": targets,
        "settings": {"seed": args.seed, "draws": 400 if args.quick else 4000}})


if __name__ == "__main__":
    main()
