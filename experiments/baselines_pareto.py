"""Error against run time of the deterministic baselines on noisy three-point bending data.

One scikit-fem field (bayespd.reference.three_point_bending, Q2 h = 0.5 mm) at the particles
of a PD grid (h = 0.5 mm, delta = m h) plus seeded Gaussian noise Sigma = 1e-4 mm (seed 001
§6.3's range). Each method in METHODS is one point: x = wall time (everything it needs after
the data exist: building virtual works or solving), y = max relative error over (K, G).
Later methods (Laplace, SVI, NUTS) are further entries of METHODS: a name and a callable
``method(problem) -> {"estimates": {...}, "wall_time_s": ..., "evaluations": ...}``.
Writes runs/baselines_pareto/{metrics.json, pareto.png}.

    python experiments/baselines_pareto.py [--m 5] [--sigma 1e-4]
"""
from __future__ import annotations

import argparse
import time
from dataclasses import dataclass

import numpy as np
import torch

import common  # noqa: F401  (one torch thread; repository root on sys.path)
from common import run_dir, write_metrics

import bayespd as bp
from bayespd.inverse import tikhonov
from bayespd.inverse.vfm import VirtualWork, identify, optimise
from bayespd.reference import three_point_bending as tpb
from vfm_three_point_bending import H, fields

SEED = 7
INIT = {"K": 5000.0, "G": 5000.0}  # seed 001 Table 2, start #1


@dataclass
class Problem:
    scene: bp.Scene
    u: torch.Tensor       # noisy displacement at every particle (N, 2)
    truth: dict
    delta: float
    sigma: float


def vfm_closed_form(pb: Problem) -> dict:
    t = time.perf_counter()
    r = identify(VirtualWork(pb.scene, fields(pb.delta, "interior"), {"delta": pb.delta}), pb.u)
    return {"estimates": r.params, "wall_time_s": time.perf_counter() - t, "evaluations": 0}


def vfm_gauss_newton(pb: Problem) -> dict:
    t = time.perf_counter()
    r = optimise(VirtualWork(pb.scene, fields(pb.delta, "interior"), {"delta": pb.delta}), pb.u, INIT)
    return {"estimates": r.params, "wall_time_s": time.perf_counter() - t, "evaluations": r.evaluations}


def tikhonov_scalar(pb: Problem) -> dict:
    scene = tpb.pd_scene(H, pb.delta)
    scene.observation = bp.ParticleObservation(scene.particles, np.arange(scene.particles.n))
    r = tikhonov(scene, pb.u, INIT, fixed={"delta": pb.delta}, sigma=pb.sigma, gtol=1e-9, maxiter=100)
    return {"estimates": r.params, "wall_time_s": r.wall_time_s, "evaluations": r.evaluations}


METHODS = [("vfm_closed_form", vfm_closed_form), ("vfm_gauss_newton", vfm_gauss_newton),
           ("tikhonov_scalar", tikhonov_scalar)]


def figure(out, results):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4.5), constrained_layout=True)
    for name, r in results.items():
        ax.loglog(r["wall_time_s"], r["rel_error"], "o", ms=9, label=name)
        ax.annotate(name, (r["wall_time_s"], r["rel_error"]), fontsize=8, xytext=(4, 4),
                    textcoords="offset points")
    ax.set(xlabel="wall time (s)", ylabel="max relative error over (K, G)",
           title="three-point bending, FE data + noise")
    ax.legend(fontsize=8)
    fig.savefig(out / "pareto.png", dpi=110)
    plt.close(fig)


def main(m: int, sigma: float):
    out = run_dir("baselines_pareto")
    start = time.perf_counter()
    fe = tpb.fe_solution(**tpb.REFERENCE_MESH)
    delta = m * H
    scene = tpb.pd_scene(H, delta)
    rng = np.random.default_rng(SEED)
    u = torch.as_tensor(fe.at(scene.particles.x) + sigma * rng.standard_normal((scene.particles.n, 2)))
    pb = Problem(scene, u, tpb.params(delta), delta, sigma)
    results = {}
    for name, method in METHODS:
        r = method(pb)
        err = {k: r["estimates"][k] / pb.truth[k] - 1 for k in ("K", "G")}
        r.update(rel_error_per_param=err, rel_error=max(abs(e) for e in err.values()))
        results[name] = r
        print(f"{name:18s} {r['wall_time_s']:8.2f} s  {r['evaluations']:4d} evaluations  "
              f"K {err['K']:+.4f}  G {err['G']:+.4f}", flush=True)
    figure(out, results)
    metrics = {"wall_time_s": time.perf_counter() - start,
               "settings": {"h": H, "m": m, "delta": delta, "sigma_mm": sigma, "seed": SEED, "init": INIT,
                            "fe_mesh": tpb.REFERENCE_MESH, "particles": scene.particles.n,
                            "truth": {k: pb.truth[k] for k in ("K", "G")},
                            "backend": bp.sparse.default_backend()},
               "targets": {},
               "methods": results}
    write_metrics("baselines_pareto", metrics)
    print(f"wrote {out}")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--m", type=int, default=5, help="delta / h (default 5)")
    parser.add_argument("--sigma", type=float, default=1e-4, help="noise std in mm (default 1e-4)")
    args = parser.parse_args()
    main(args.m, args.sigma)
