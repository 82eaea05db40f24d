"""Error against run time of the deterministic baselines and the Bayesian fits on noisy
three-point bending data.

One scikit-fem field (bayespd.reference.three_point_bending, Q2 h = 0.5 mm) at the particles
of a PD grid (spacing h, delta = m h) plus seeded Gaussian noise Sigma = 1e-4 mm (Delorme 2018
§6.3's range). Each method in METHODS is one point: x = wall time (everything it needs after
the data exist: building virtual works, solving, optimising or sampling; for the Bayesian
fits ``fit``'s own wall time, without the posterior-predictive replay), y = max relative
error over (K, G) of the estimate (Bayesian: posterior mean). Each entry is a name and a
callable ``method(problem) -> {"estimates": {...}, "wall_time_s": ..., "evaluations": ...}``;
the Bayesian ones (Laplace, SVI with each guide, NUTS; delta known, K, G, sigma inferred
with ``models.elastic_plate``'s priors centred at INIT) also give 90 % intervals, their
width relative to the truth, and whether they cover it. The FE data are not the PD model's
own (no inverse crime): the intervals reflect the noise only, so where the discretisation
bias exceeds them they miss the truth, and the table says so.
Writes runs/baselines_pareto/{metrics.json, pareto.png}.

    python experiments/baselines_pareto.py [--h 2] [--m 3] [--sigma 1e-4]

A gradient costs about 40 ms at h = 2, m = 3 (1,024 particles) and 0.65 s at h = 1 (4,096;
2-core machine, loaded): the Bayesian methods are run at h = 2 (a few minutes in all). With
``--deterministic-only`` the earlier setting h = 0.5, m = 5 runs in about a minute.
"""
from __future__ import annotations

import argparse
import time
from dataclasses import dataclass

import numpy as np
import pyro
import torch

import common  # noqa: F401  (one torch thread; repository root on sys.path)
from common import run_dir, write_metrics

import bayespd as bp
from bayespd.linalg import sparse
from bayespd.infer import fit
from bayespd.inverse import tikhonov
from bayespd.inverse.vfm import VirtualWork, identify, optimise
from bayespd.reference import three_point_bending as tpb
from bayespd.infer.calibration import central_interval
from bayespd.models.elastic_plate import elastic_plate
from vfm_three_point_bending import fields

SEED = 7
INIT = {"K": 5000.0, "G": 5000.0}  # Delorme 2018 Table 2, start #1


@dataclass
class Problem:
    scene: bp.Scene
    u: torch.Tensor       # noisy displacement at every particle (N, 2)
    truth: dict
    delta: float
    sigma: float
    h: float


def vfm_closed_form(pb: Problem) -> dict:
    t = time.perf_counter()
    r = identify(VirtualWork(pb.scene, fields(pb.delta, "interior"), {"delta": pb.delta}), pb.u)
    return {"estimates": r.params, "wall_time_s": time.perf_counter() - t, "evaluations": 0}


def vfm_gauss_newton(pb: Problem) -> dict:
    t = time.perf_counter()
    r = optimise(VirtualWork(pb.scene, fields(pb.delta, "interior"), {"delta": pb.delta}), pb.u, INIT)
    return {"estimates": r.params, "wall_time_s": time.perf_counter() - t, "evaluations": r.evaluations}


def tikhonov_scalar(pb: Problem) -> dict:
    scene = observed_scene(pb)
    r = tikhonov(scene, pb.u, INIT, fixed={"delta": pb.delta}, sigma=pb.sigma, gtol=1e-9, maxiter=100)
    return {"estimates": r.params, "wall_time_s": r.wall_time_s, "evaluations": r.evaluations}


def observed_scene(pb: Problem) -> bp.Scene:
    """The PD scene observed at every particle (the data's points)."""
    scene = tpb.pd_scene(pb.h, pb.delta)
    scene.observation = bp.ParticleObservation(scene.particles, np.arange(scene.particles.n))
    return scene


# the Bayesian fits: one NUTS chain from the MAP (Laplace covariance as mass matrix), SVI
# from the MAP with each guide, Laplace with the exact Hessian
BAYES = {
    "laplace": {"method": "laplace", "num_samples": 1000},
    **{f"svi_{g}": {"method": "svi", "guide": g, "svi_steps": 400, "num_samples": 1000, "init": "map"}
       for g in ("normal", "mvn", "lowrank", "flow")},
    "nuts": {"method": "nuts", "num_warmup": 150, "num_samples": 300, "num_chains": 1, "init": "map",
             "mass_matrix_from": "laplace"},
}


def bayesian(name: str):
    """A METHODS entry fitting ``models.elastic_plate`` (delta known) with ``BAYES[name]``."""
    def method(pb: Problem) -> dict:
        scene = observed_scene(pb)
        # delta is known and equals the scene's delta_max, where the default ScaledBeta prior
        # has zero density: condition a hair inside (a constant log prior; the solve changes
        # by ~1e-9 relative)
        known = torch.tensor(pb.delta * (1 - 1e-9))
        model = pyro.poutine.condition(elastic_plate(scene, INIT, noise_scale=5 * pb.sigma),
                                       data={"delta": known})
        tree = fit(model, {"y": pb.u}, seed=SEED, progress=False, **BAYES[name])
        post = tree["posterior"]
        draws = {k: post[k].values.reshape(-1) for k in ("K", "G", "sigma")}
        intervals = {k: central_interval(v, 0.9) for k, v in draws.items()}
        truth = dict(pb.truth, sigma=pb.sigma)
        return {"estimates": {k: float(v.mean()) for k, v in draws.items()},
                "wall_time_s": float(tree.attrs["wall_time_s"]),
                "predictive_wall_time_s": float(tree.attrs["predictive_wall_time_s"]),
                "evaluations": int(tree.attrs["num_grad_evals"]), "interval_90": intervals,
                "rel_width_90": {k: (hi - lo) / truth[k] for k, (lo, hi) in intervals.items()},
                "covers_truth": {k: bool(lo <= truth[k] <= hi) for k, (lo, hi) in intervals.items()}}
    return method


DETERMINISTIC = [("vfm_closed_form", vfm_closed_form), ("vfm_gauss_newton", vfm_gauss_newton),
                 ("tikhonov_scalar", tikhonov_scalar)]
METHODS = DETERMINISTIC + [(name, bayesian(name)) for name in BAYES]


def figure(out, results, title):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax, bx) = plt.subplots(1, 2, figsize=(11, 4.5), constrained_layout=True)
    for j, (name, r) in enumerate(results.items()):
        ax.loglog(r["wall_time_s"], r["rel_error"], "o", ms=8, color=f"C{j}", label=name)
        ax.annotate(name, (r["wall_time_s"], r["rel_error"]), fontsize=7, xytext=(4, 4),
                    textcoords="offset points")
        if "rel_width_90" in r:
            for k, marker in (("K", "o"), ("G", "s")):
                bx.loglog(r["wall_time_s"], r["rel_width_90"][k], marker, ms=7, color=f"C{j}",
                          mfc="none" if not r["covers_truth"][k] else f"C{j}")
            bx.annotate(name, (r["wall_time_s"], r["rel_width_90"]["K"]), fontsize=7, xytext=(4, 4),
                        textcoords="offset points")
    ax.set(xlabel="wall time (s)", ylabel="max relative error over (K, G) of the estimate / posterior mean",
           title=title)
    bx.set(xlabel="wall time (s)", ylabel="90 % interval width / truth",
           title="Bayesian fits: circles K, squares G (hollow: misses the truth)")
    ax.legend(fontsize=7)
    fig.savefig(out / "pareto.png", dpi=110)
    plt.close(fig)


def table(results) -> list[dict]:
    """One row per method: wall time, errors of the estimate, interval widths and coverage."""
    rows = []
    for name, r in results.items():
        row = {"method": name, "wall_time_s": r["wall_time_s"], "evaluations": r["evaluations"],
               "rel_error_K": r["rel_error_per_param"]["K"], "rel_error_G": r["rel_error_per_param"]["G"],
               "rel_error": r["rel_error"]}
        for k in ("K", "G"):
            if "rel_width_90" in r:
                row[f"rel_width_90_{k}"] = r["rel_width_90"][k]
                row[f"covers_{k}"] = r["covers_truth"][k]
        rows.append(row)
    return rows


def main(h: float, m: int, sigma: float, deterministic_only: bool):
    out = run_dir("baselines_pareto")
    start = time.perf_counter()
    fe = tpb.fe_solution(**tpb.REFERENCE_MESH)
    delta = m * h
    scene = tpb.pd_scene(h, delta)
    rng = np.random.default_rng(SEED)
    u = torch.as_tensor(fe.at(scene.particles.x) + sigma * rng.standard_normal((scene.particles.n, 2)))
    pb = Problem(scene, u, tpb.params(delta), delta, sigma, h)
    results = {}
    for name, method in DETERMINISTIC if deterministic_only else METHODS:
        r = method(pb)
        err = {k: r["estimates"][k] / pb.truth[k] - 1 for k in ("K", "G")}
        r.update(rel_error_per_param=err, rel_error=max(abs(e) for e in err.values()))
        results[name] = r
        widths = " ".join(f"{k} width {w:.2e}{'' if r['covers_truth'][k] else ' (misses)'}"
                          for k, w in r.get("rel_width_90", {}).items() if k != "sigma")
        print(f"{name:18s} {r['wall_time_s']:8.2f} s  {r['evaluations']:5d} evaluations  "
              f"K {err['K']:+.4f}  G {err['G']:+.4f}  {widths}", flush=True)
    figure(out, results, f"three-point bending, FE data + noise {sigma:g} mm, h = {h:g}, m = {m}")
    metrics = {"wall_time_s": time.perf_counter() - start,
               "settings": {"h": h, "m": m, "delta": delta, "sigma_mm": sigma, "seed": SEED, "init": INIT,
                            "fe_mesh": tpb.REFERENCE_MESH, "particles": scene.particles.n,
                            "truth": {k: pb.truth[k] for k in ("K", "G")}, "bayes": {} if deterministic_only else BAYES,
                            "backend": sparse.default_backend()},
               "targets": {},
               "table": table(results),
               "methods": results}
    write_metrics("baselines_pareto", metrics)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--h", type=float, default=2.0, help="PD grid spacing in mm (default 2; must divide 2)")
    parser.add_argument("--m", type=int, default=3, help="delta / h (default 3)")
    parser.add_argument("--sigma", type=float, default=1e-4, help="noise std in mm (default 1e-4)")
    parser.add_argument("--deterministic-only", action="store_true", help="VFM and Tikhonov only")
    args = parser.parse_args()
    main(args.h, args.m, args.sigma, args.deterministic_only)
