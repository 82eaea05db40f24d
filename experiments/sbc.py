"""Simulation-based calibration (Talts et al. 2018) of NUTS on the calibration plate.

For each of n prior draws (K, G, sigma; delta known, or with ``--free-delta`` also delta) the
data are simulated from the model itself, so this checks the *inference*, not the model: data
from a finer model are not wanted here (see scenes/calibration_scene.py). Each fit is one NUTS chain
started at the MAP with the Laplace covariance as its mass matrix (100 warmup + 100 draws);
the rank of the truth among 19 evenly thinned draws is uniform on 0..19 if the posterior is
right. Ranks are binned into 5 bins of 4 values and tested by chi-square (4 df); target
p > 0.01 per parameter. Replications are checkpointed one file each (resumable after a
kill) and shared with interval_coverage.py. Writes runs/sbc[_free_delta][_quick]/{metrics.json,
ranks.png}.

    python experiments/sbc.py [--quick] [--n 100] [--free-delta]
"""
from __future__ import annotations

import time

import numpy as np

import common  # noqa: F401  (one torch thread; repository root on sys.path)
from bayespd.scenes import calibration_scene as cs
from bayespd.infer.calibration import binomial_band, chi2_power_overconfident, chi2_uniformity, rank_counts
from common import run_dir, write_metrics

BINS, ALPHA = 5, 0.01


def figure(out, ranks: dict, num_draws: int, n: int):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(ranks), figsize=(3.2 * len(ranks), 3), constrained_layout=True)
    lo, hi = binomial_band(n, 1 / BINS, 0.99)
    for ax, (k, r) in zip(np.atleast_1d(axes), ranks.items()):
        counts = rank_counts(r, num_draws, BINS)
        ax.axhspan(lo * n, hi * n, color="0.85", label="99 % band if uniform")
        ax.bar(np.arange(BINS), counts, width=0.9, color="C0")
        ax.axhline(n / BINS, color="k", lw=1)
        ax.set(title=f"{k}: p = {chi2_uniformity(r, num_draws, BINS):.3f}", xlabel=f"rank bin (0..{num_draws})",
               ylabel="replications", xticks=range(BINS))
    np.atleast_1d(axes)[0].legend(fontsize=7, loc="lower left")
    fig.suptitle(f"SBC rank histograms, NUTS, {n} prior draws")
    fig.savefig(out / "ranks.png", dpi=110)
    plt.close(fig)


def main(n: int, free_delta: bool, quick: bool):
    name = cs.run_name("sbc", free_delta, quick)
    out = run_dir(name)
    start = time.perf_counter()
    records = cs.replications("nuts", n, free_delta)
    ok = cs.successful(records)
    settings = cs.settings("nuts", free_delta)
    num_draws = settings["rank_draws"]
    ranks = {k: [r["params"][k]["rank"] for r in ok] for k in cs.names(free_delta)}
    targets, per_param = {}, {}
    for k, r in ranks.items():
        p = chi2_uniformity(r, num_draws, BINS)
        targets[f"{k}_chi2_p"] = {"value": p, "target": f"> {ALPHA}", "passed": p > ALPHA}
        errors = [abs(x["params"][k]["mean"] / x["truth"][k] - 1) for x in ok]
        per_param[k] = {"rank_counts": rank_counts(r, num_draws, BINS).tolist(), "chi2_p": p,
                        "median_rel_error_of_mean": float(np.median(errors))}
    targets["failed_fits"] = {"value": n - len(ok), "target": 0, "passed": len(ok) == n}
    figure(out, ranks, num_draws, len(ok))
    fit_times = [r["fit_wall_time_s"] for r in ok]
    wall = time.perf_counter() - start
    metrics = {
        "wall_time_s": wall,
        "settings": {"replications": n, "free_delta": free_delta, "quick": quick, "bins": BINS,
                     "rank_draws": num_draws, "nuts": settings, "scene": cs.fingerprint("nuts", free_delta),
                     "particles": cs.plate().particles.n, "partial_volume_rule": cs.rule(free_delta), "delta_known": None if free_delta else cs.DELTA_KNOWN},
        "targets": targets,
        "power": {f"overconfident_sd_x{c}": chi2_power_overconfident(len(ok), BINS, c, ALPHA)
                  for c in (0.5, 0.7, 0.8)},
        "parameters": per_param,
        "fits": {"mean_wall_time_s": float(np.mean(fit_times)), "total_wall_time_s": float(np.sum(fit_times)),
                 "mean_grad_evals": float(np.mean([r["grad_evals"] for r in ok])),
                 "divergences": int(sum(r.get("divergences", 0) for r in ok)),
                 "failures": [r["failed"] for r in records if "failed" in r]},
    }
    write_metrics(name, metrics)
    for k, v in per_param.items():
        print(f"{k:6s} counts {v['rank_counts']}  chi2 p = {v['chi2_p']:.3f}  "
              f"median |mean/truth - 1| = {v['median_rel_error_of_mean']:.3f}")
    print(f"{len(ok)}/{n} fits, {np.mean(fit_times):.1f} s each; power {metrics['power']}; wrote {out}")


if __name__ == "__main__":
    main(*cs.command_line(__doc__, "prior draws"))
