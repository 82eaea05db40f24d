"""Posterior-predictive crack ensemble of a ~10k-particle notched plate (Dodwell 2019 eq 4 with
damage) and its scale-out: the material (K, s0) is calibrated on a small coupon by
``bayespd calibrate`` (Laplace; s0 keeps its prior: elastic data do not inform it), then the
crack ensemble runs over a local process pool of 2 workers, and a subset over Dask
LocalClusters of 1 and 2 workers (scaling, peak memory per worker).
Writes runs/crack_ensemble/ (metrics.json, posterior.nc, store/ with ensemble.nc, PNG figures).

    python experiments/crack_ensemble.py [--quick] [--realisations N] [--side MM] [--scaling M]
"""
from __future__ import annotations

import argparse
import dataclasses
import os
import shutil
import time

import numpy as np

import common  # noqa: F401  (one torch thread, repository root on sys.path)
from common import run_dir, write_metrics

from bayespd import cli
from bayespd.damage import CriticalStretch, crack_path
from bayespd.infer import load
from bayespd.ensemble.demo_inputs import write_inputs
from bayespd.scenes.notched_plate import notched_plate, plate_scene
from bayespd.ensemble.scene import BATCH
from bayespd.ensemble.predictive import ensemble
from bayespd.plot import ensemble_figures
from bayespd.solvers.quasistatic import quasi_static

H, STEPS = 1.0, 50


def observed_crack(scene, side, K, s0):
    """The 'observed' crack: the deterministic quasi-static path (You 2023 §5.2) at the
    calibrated K and the nominal s0 on the same plate."""
    plate = plate_scene(side, H, 3, CriticalStretch(s0))
    qs = quasi_static(plate, {"K": K, "delta": 3 * H}, scene.load_factors)
    return crack_path(plate.particles, qs.damage[-1], scene.path_threshold)


def peak_worker_memory_mb(client) -> dict:
    import resource

    def rss():
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # KiB on Linux -> MiB

    return {str(k): float(v) for k, v in client.run(rss).items()}


def dask_run(tree, scene, m, workers, store):
    """m posterior realisations on a LocalCluster of ``workers`` single-threaded processes."""
    import distributed

    shutil.rmtree(store, ignore_errors=True)
    with distributed.LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                                  dashboard_address=None) as cluster, distributed.Client(cluster) as client:
        client.run(lambda: __import__("bayespd.ensemble.predictive"))  # imports are not part of the timing
        start = time.perf_counter()
        ds = ensemble(tree, scene, m, n_mean=0, store=store, scheduler=client, progress=False)
        wall = time.perf_counter() - start
        memory = peak_worker_memory_mb(client)
    return ds, wall, memory


def summary_of(ds) -> dict:
    out = {}
    for name in [str(v) for v in ds["outcome"].values]:
        sd = ds["spread"].sel(outcome=name).values
        row = {"sd_total": sd[0], "sd_aleatoric": sd[1], "sd_epistemic": sd[2]}
        if f"{name}_quantiles" in ds:
            for kind in ("posterior", "mean"):
                row[f"{kind}_q05_q50_q95"] = ds[f"{name}_quantiles"].sel(kind=kind).values.tolist()
        out[name] = row
    return out


def main(quick: bool, realisations: int | None, side: float | None, scaling: int | None):
    out = run_dir("crack_ensemble")
    start = time.perf_counter()
    side = side or (30.0 if quick else 100.0)
    total = realisations or (12 if quick else 200)  # two thirds at posterior draws, one third at the mean
    n_mean = max(2, total // 3)
    n = total - n_mean
    m = 4 * BATCH if scaling is None else scaling  # four tasks: two per worker, so one long task weighs less
    load_avg = os.getloadavg()

    inputs = write_inputs(out / "coupon")
    t0 = time.perf_counter()
    code = cli.main(["calibrate", str(inputs["model"]), "--data", str(inputs["data"]), "--method", "laplace",
                     "--out", str(out), "--samples", "400", "--quiet"])
    if code:
        raise SystemExit(f"calibration failed (exit {code})")
    calibrate_wall = time.perf_counter() - t0
    tree = load(out / "posterior.nc")
    post = tree["posterior"]
    K_mean, s0_mean = float(post["K"].mean()), float(post["s0"].mean())

    scene = notched_plate(side=side, h=H, steps=STEPS, sigma=1500.0)
    t0 = time.perf_counter()
    observed = observed_crack(scene, side, K_mean, s0_mean)
    observed_wall = time.perf_counter() - t0
    scene = dataclasses.replace(scene, observed_path=observed)

    store = out / "store"
    shutil.rmtree(store, ignore_errors=True)
    t0 = time.perf_counter()
    ds = ensemble(tree, scene, n, n_mean=n_mean, store=store, workers=2)
    ensemble_wall = time.perf_counter() - t0
    figures = ensemble_figures(ds, out)

    wall1 = wall2 = np.nan
    mem1 = mem2 = {}
    identical = False
    if m:  # the first m posterior realisations again, on Dask clusters of 1 and 2 workers
        _, wall1, mem1 = dask_run(tree, scene, m, 1, out / "dask1")
        ds2, wall2, mem2 = dask_run(tree, scene, m, 2, out / "dask2")
        k = min(m, n)
        local = ds.sel(realisation=ds["ensemble"] == "posterior")["phi"].values[:k]
        identical = bool(np.array_equal(ds2["phi"].values[:k], local))
        for folder in ("dask1", "dask2"):
            shutil.rmtree(out / folder, ignore_errors=True)

    per = ds["wall_time_s"].values
    projected_200 = ensemble_wall * 200 / total  # 200 realisations (of either kind) at this throughput
    speedup = wall1 / wall2
    memory = max(list(mem1.values()) + list(mem2.values()), default=np.nan)
    probability = ds["probability"].sel(kind="posterior").values
    wall = time.perf_counter() - start
    targets = {
        "wall_time_200_realisations_s": {"value": ensemble_wall if total == 200 else projected_200, "target": 600.0,
                                         "measured": total == 200, "passed": bool(
                                             (ensemble_wall if total == 200 else projected_200) <= 600.0)},
        "dask_speedup_2_vs_1_workers": {"value": speedup, "target": 1.8, "passed": bool(speedup >= 1.8)},
        "dask_equals_local_bit_for_bit": {"value": identical, "target": True, "passed": identical},
        "peak_memory_per_worker_mb": {"value": memory, "target": 2048.0, "passed": bool(memory <= 2048.0)},
        "failed_realisations": {"value": int(ds.attrs["failed"]), "target": 0, "passed": ds.attrs["failed"] == 0},
    }
    metrics = {
        "wall_time_s": wall, "targets": targets,
        "calibration": {"method": "laplace", "wall_time_s": calibrate_wall,
                        "K_mean": K_mean, "K_sd": float(post["K"].std()), "s0_mean": s0_mean, "s0_sd": float(post["s0"].std())},
        "ensemble": {"realisations_posterior": n, "realisations_mean": n_mean, "workers": 2,
                     "wall_time_s": ensemble_wall, "realisations_per_s": total / ensemble_wall,
                     "wall_time_s_per_realisation": {"mean": float(per.mean()), "sd": float(per.std()),
                                                     "min": float(per.min()), "max": float(per.max())},
                     "cpu_time_s_per_realisation_mean": float(ds["cpu_time_s"].values.mean()),
                     "steps_per_realisation_mean": float(np.isfinite(ds["t"].values).sum(1).mean()),
                     "uncertain_particles_0.05_to_0.95": int(np.sum((probability > 0.05) & (probability < 0.95))),
                     "failure_reached": ds["failure_reached"].values.tolist(), "outcomes": summary_of(ds)},
        "scaling": {"realisations": m, "dask_1_worker_s": wall1, "dask_2_workers_s": wall2, "speedup": speedup,
                    "efficiency": speedup / 2, "peak_rss_mb_1_worker": mem1, "peak_rss_mb_2_workers": mem2},
        "settings": {"quick": quick, "side_mm": side, "h_mm": H, "particles": len(scene.x), "load_steps": STEPS,
                     "sigma": 1500.0, "seed": 0, "observed_crack": "quasi-static at the posterior mean",
                     "observed_crack_wall_time_s": observed_wall, "load_average_at_start": list(load_avg),
                     "load_average_at_end": list(os.getloadavg()), "cores": os.cpu_count(),
                     "figures": [p.name for p in figures]},
    }
    path = write_metrics("crack_ensemble", metrics)
    passed = sum(t["passed"] for t in targets.values())
    for line in (f"{len(scene.x)} particles: {n} + {n_mean} realisations, {ensemble_wall:.1f} s on 2 workers",
                 f"  per realisation {per.mean():.1f} +- {per.std():.1f} s wall, "
                 f"{float(ds['cpu_time_s'].values.mean()):.1f} s CPU",
                 f"  Dask, {m} realisations: 1 worker {wall1:.1f} s, 2 workers {wall2:.1f} s, speedup {speedup:.2f}",
                 f"  peak RSS per worker {memory:.0f} MB; {passed}/{len(targets)} targets; {path}"):
        print(line)


def options():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="30 mm plate (900 particles), 8 + 4 realisations")
    parser.add_argument("--realisations", type=int, default=None, help="realisations in all, 2/3 at posterior draws and 1/3 at the posterior mean (default 200)")
    parser.add_argument("--side", type=float, default=None, help="plate side in mm, h = 1 (default 100: 10k particles)")
    parser.add_argument("--scaling", type=int, default=None, help=f"realisations for the Dask scaling runs (default {4 * BATCH}: four tasks; 0: skip)")
    return vars(parser.parse_args())


if __name__ == "__main__":
    main(**options())
