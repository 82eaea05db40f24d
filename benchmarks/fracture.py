"""Stochastic fracture realisations of the crack-ensemble plate (Dodwell 2019 eq 4 with damage,
``bayespd.scenes.notched_plate``), as a worker of the ensemble runs them (``realise_batch``: one
torch and one BLAS thread): wall time against error for each way of treating the operator.

A run is ``TANGENT:MAX_RANK``: the exact tangent (conjugate gradients preconditioned by the
Woodbury-updated factor) or the lagged one (that factor itself, a W-method), updated by
Woodbury up to MAX_RANK rows (0: a fresh factorisation at every change of the intact
bonds). The first run listed is the reference: with the same Brownian seeds, every other
run's failure load factor, peak load and crack length are compared with it seed by seed,
and the difference of their means with its Monte-Carlo standard error (the error an
ensemble of that many realisations would see). The seeds run ``--batch`` at a time in
lock-step (``scene.realise_batch``, as the ensemble's tasks run them; the times
are each batch's wall and CPU time shared out over its realisations).

    python benchmarks/fracture.py [--side 100] [--runs exact:512 lagged:512] [--seeds 3 4] [--batch 8]
"""
from __future__ import annotations

import argparse
import dataclasses
import os
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bayespd.linalg import sparse  # noqa: E402
from bayespd.scenes.notched_plate import notched_plate  # noqa: E402
from bayespd.ensemble.scene import BATCH, realise_batch  # noqa: E402
from bayespd.solvers import fracture  # noqa: E402

PARAMS = {"K": 2886.0, "s0": 0.0094}  # the posterior mean of experiments/crack_ensemble.py
OUTCOMES = ("failure_load_factor", "peak_load", "final_crack_length")


def _counting_factorisations():
    """Count StochasticFracture's fresh factorisations (a dict whose "n" they increment)."""
    counted, factorised = {"n": 0}, fracture.StochasticFracture._factorised

    def counting(self, *a):
        counted["n"] += 1
        return factorised(self, *a)

    fracture.StochasticFracture._factorised = counting
    return counted


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--side", type=float, default=100.0, help="plate side in mm (h = 1 mm): 100 -> 10k particles")
    parser.add_argument("--runs", nargs="+", default=["exact:512", "lagged:512"], help="TANGENT:MAX_RANK, reference first")
    parser.add_argument("--seeds", type=int, nargs="+", default=list(range(3, 11)))
    parser.add_argument("--batch", type=int, default=BATCH, help="realisations run in lock-step at a time")
    args = parser.parse_args()
    scene = notched_plate(side=args.side, h=1.0, steps=50, sigma=1500.0)
    counted = _counting_factorisations()
    print(f"load average {os.getloadavg()[0]:.2f}; {len(scene.x)} particles; backend {sparse.default_backend()}; "
          f"seeds {args.seeds}")
    results = {}
    for spec in args.runs:
        tangent, rank = spec.split(":")
        variant = dataclasses.replace(scene, tangent=tangent, max_rank=int(rank))
        rows = []
        for first in range(0, len(args.seeds), args.batch):
            seeds = args.seeds[first:first + args.batch]
            counted["n"] = 0
            outs = realise_batch(variant, [(PARAMS, seed) for seed in seeds])
            print(f"{spec} seeds {seeds}: {counted['n']} factorisations; per realisation "
                  f"{float(outs[0]['wall_time_s']):.2f} s wall, {float(outs[0]['cpu_time_s']):.2f} s CPU", flush=True)
            for seed, out in zip(seeds, outs):
                rows.append({"wall": float(out["wall_time_s"]), "steps": len(out["t"]),
                             "broken": int(out["broken"][-1]), **{k: float(out[k]) for k in OUTCOMES}})
                print(f"  seed {seed}: {rows[-1]['steps']} steps, {rows[-1]['broken']} bonds broken, failure "
                      f"{rows[-1]['failure_load_factor']:.4f}, peak {rows[-1]['peak_load']:.1f} N, "
                      f"crack {rows[-1]['final_crack_length']:.1f} mm", flush=True)
        results[spec] = {k: np.array([r[k] for r in rows]) for k in rows[0]}
    reference = args.runs[0]
    ref = results[reference]
    print(f"\nper realisation (mean over {len(args.seeds)} seeds), against {reference}:")
    for spec, res in results.items():
        line = f"{spec:>12}: {res['wall'].mean():6.1f} s, {res['steps'].mean():.0f} steps"
        for k in OUTCOMES:
            diff = res[k] - ref[k]
            mc = ref[k].std(ddof=1) / np.sqrt(len(diff))
            line += (f"; {k} {res[k].mean():.4g} (sd {res[k].std(ddof=1):.3g}), mean diff {diff.mean():+.3g}"
                     f" +- {diff.std(ddof=1) / np.sqrt(len(diff)):.2g} (MC error of the mean {mc:.2g})")
        print(line)


if __name__ == "__main__":
    main()
