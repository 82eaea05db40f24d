"""Statistical check of the crack ensemble's fast path against the exact tangent (issue 29):
on the quick notched plate (``bayespd.scenes.notched_plate``, 30 mm, 900 particles, the
calibrated posterior mean K, s0), N realisations with the lagged tangent (the ensemble's
default: the steps use the Woodbury-updated factor itself) and N with the exact one (conjugate gradients on the exact tangent),
on disjoint Brownian seeds (independent samples). Targets: two-sample Kolmogorov-Smirnov
p > 0.05 for the failure load factor, the peak load and the final crack length, and the
damage-probability maps (phi > the scene's path threshold) equal within their binomial band:
|p_lagged - p_exact| <= z sqrt(2 p (1 - p) / N) at every particle, p the pooled frequency, z
Bonferroni's for the particles where p is neither 0 nor 1 at 5 % in all. Power: with N = 100
a two-sample KS at 5 % detects a shift of the mean of a normal outcome by 0.5 sd with
probability 0.82 and by 0.7 sd with 0.98 (``ks_power``, 2,000 simulated trials).
Writes runs/crack_validation/metrics.json.

    python experiments/crack_validation.py [--realisations 100] [--side 30] [--workers 2]
"""
from __future__ import annotations

import argparse
import dataclasses
import os
import time

import numpy as np
from scipy import stats

import common  # noqa: F401  (one torch thread, repository root on sys.path)
from common import write_metrics

from bayespd.ensemble.execution import run_tasks
from bayespd.ensemble.scene import BATCH, realise_batch
from bayespd.linalg import sparse
from bayespd.scenes.notched_plate import notched_plate

PARAMS = {"K": 2886.0, "s0": 0.0094}  # the posterior mean of experiments/crack_ensemble.py
OUTCOMES = ("failure_load_factor", "peak_load", "final_crack_length")
SEED_BASE = {"lagged": 10_000, "exact": 20_000}  # disjoint seeds: independent samples


def _task(scene, tangent, seeds):
    outs = realise_batch(dataclasses.replace(scene, tangent=tangent), [(PARAMS, s) for s in seeds])
    for out in outs:
        if isinstance(out, BaseException):
            raise out
    return [{**{k: float(o[k]) for k in OUTCOMES}, "phi": o["phi"], "cpu": float(o["cpu_time_s"])} for o in outs]


def ks_power(n: int, shift: float, trials: int = 2000) -> float:
    """Power of the two-sample KS test at 5 % for a shift of ``shift`` sd of a normal, n each."""
    rng = np.random.default_rng(0)
    return float(np.mean([stats.ks_2samp(rng.standard_normal(n), rng.standard_normal(n) + shift).pvalue < 0.05
                          for _ in range(trials)]))


def main(n: int, side: float, workers: int):
    scene = notched_plate(side=side, h=1.0, steps=50, sigma=1500.0)
    load = os.getloadavg()
    results = {t: [] for t in SEED_BASE}
    tasks = {(t, b): (t, list(range(SEED_BASE[t] + b, SEED_BASE[t] + min(b + BATCH, n))))
             for t in SEED_BASE for b in range(0, n, BATCH)}
    start = time.perf_counter()
    run_tasks(_task, tasks, lambda key, value: results[key[0]].extend(value), shared=scene, workers=workers)
    wall = time.perf_counter() - start
    ks = {}
    for k in OUTCOMES:
        a = np.array([r[k] for r in results["lagged"]])
        b = np.array([r[k] for r in results["exact"]])
        ks[k] = {"p": float(stats.ks_2samp(a[np.isfinite(a)], b[np.isfinite(b)]).pvalue),
                 "mean_lagged": float(np.nanmean(a)), "mean_exact": float(np.nanmean(b)),
                 "sd_lagged": float(np.nanstd(a, ddof=1)), "sd_exact": float(np.nanstd(b, ddof=1)),
                 "unfailed_lagged": int(np.sum(~np.isfinite(a))), "unfailed_exact": int(np.sum(~np.isfinite(b)))}
    maps = {t: np.mean([r["phi"] > scene.path_threshold for r in results[t]], axis=0) for t in SEED_BASE}
    pooled = (maps["lagged"] + maps["exact"]) / 2
    uncertain = (pooled > 0) & (pooled < 1)
    z = stats.norm.isf(0.025 / max(int(uncertain.sum()), 1))
    band = z * np.sqrt(2 * pooled * (1 - pooled) / n)
    diff = np.abs(maps["lagged"] - maps["exact"])
    worst = float((diff[uncertain] / band[uncertain]).max()) if uncertain.any() else 0.0
    outside = int(np.sum(diff[uncertain] > band[uncertain]))
    cpu = {t: float(np.mean([r["cpu"] for r in results[t]])) for t in SEED_BASE}
    targets = {f"KS p {k} > 0.05": {"value": ks[k]["p"], "target": 0.05, "passed": ks[k]["p"] > 0.05} for k in OUTCOMES}
    targets["damage map within its Bonferroni binomial band (max |dp| / band <= 1)"] = {
        "value": worst, "target": 1.0, "passed": outside == 0}
    write_metrics("crack_validation", {
        "settings": {"realisations_each": n, "side_mm": side, "particles": len(scene.x), "params": PARAMS,
                     "seeds": {t: [SEED_BASE[t], SEED_BASE[t] + n - 1] for t in SEED_BASE}, "workers": workers,
                     "backend": sparse.default_backend(), "load_average_at_start": load},
        "ks": ks, "damage_map": {"uncertain_particles": int(uncertain.sum()), "z_bonferroni": float(z),
                                 "max_diff_over_band": worst, "outside_band": outside},
        "ks_power_n_each": {"shift_0.5_sd": ks_power(n, 0.5), "shift_0.7_sd": ks_power(n, 0.7)},
        "cpu_s_per_realisation": cpu, "wall_time_s": wall, "targets": targets})


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--realisations", type=int, default=100, help="realisations per tangent")
    parser.add_argument("--side", type=float, default=30.0, help="plate side in mm (h = 1 mm)")
    parser.add_argument("--workers", type=int, default=2)
    args = parser.parse_args()
    main(args.realisations, args.side, args.workers)
