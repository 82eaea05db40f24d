"""The cost of the posterior predictive of a Laplace fit at ~5k particles: the fit with
``predictive=False`` (timed once), then the replay ``fit`` adds for every draw (one factorisation, then CG preconditioned by
it: ``bayespd.linalg.reuse``), a thinned replay (``predictive=20``), and, for comparison, the
replay with a fresh factorisation per draw (reuse switched off); then the same fit with its
predictive on a reduced scene (``bp.ReducedScene`` from 30 prior draws, tolerance 1 % of the
noise sd), its build included, and how far its posterior is from the full fit's.

Scene: benchmarks/inference.py's ``5k`` plate with a hole (h = 0.4 mm, delta_max = 3 h,
4,684 particles, 9.4k dofs, ``rule="smooth"``), data from the model plus 1 % noise;
``models.elastic_plate`` (K, G, delta, sigma), Laplace with the exact Hessian, MAP search
started at the truth, 100 draws.

    python benchmarks/predictive.py [--draws 100]
"""
from __future__ import annotations

import argparse
import contextlib
import time

import inference as bi  # noqa: F401  (experiments/ on sys.path, one torch thread)

import bayespd as bp
from bayespd.infer import fit
from bayespd.infer import replay as replay_module
from bayespd.linalg import sparse
from bayespd.models.elastic_plate import elastic_plate
import demo  # noqa: E402


def timed(f):
    start = time.perf_counter()
    out = f()
    return out, time.perf_counter() - start


def main(draws: int):
    scene, y, sigma = bi.fine_problem(rule="smooth")  # the linear ramp's kinks in delta break Laplace
    start = {k: v for k, v in bi.at_truth(scene, sigma).items() if k != "sigma"}
    noise = 0.05 * float(y.abs().max())
    model = elastic_plate(scene, demo.NOMINAL, noise_scale=noise)
    print(f"{scene.particles.n} particles, backend {sparse.default_backend()}, {draws} draws")
    tree, fit_s = timed(lambda: fit(model, {"y": y}, "laplace", num_samples=draws, progress=False,
                                    predictive=False, init_values=start))
    posterior = {k: tree["posterior"][k].values for k in tree["posterior"].data_vars}
    data = {"y": y}

    def replayed(predictive):
        return timed(lambda: replay_module.replay(model, data, posterior, "y", False,
                                                  replay_module.thinned(draws, 1, predictive)))[1]

    runs = {"fit(predictive=False)": 0.0, "fit(predictive=True)": replayed(True),
            "fit(predictive=20)": replayed(20)}
    reuse_on = replay_module.reusing_factors
    replay_module.reusing_factors = contextlib.nullcontext  # a fresh factorisation per draw
    try:
        runs["predictive=True, a factorisation per draw (before)"] = replayed(True)
    finally:
        replay_module.reusing_factors = reuse_on
    print("| run | Laplace fit (s) | replay (s) | total (s) |\n|---|---|---|---|")
    for name, replay_s in runs.items():
        print(f"| {name} | {fit_s:.1f} | {replay_s:.1f} | {fit_s + replay_s:.1f} |")
    reduced_fit(model, noise, y, sigma, start, draws, tree)


def reduced_fit(model, noise, y, sigma, start, draws, full_tree):
    """The Laplace fit and its predictive on a reduced scene of ``model``'s, build included,
    against the full fit."""
    snapshots = bp.prior_draws(model.priors, 30, 0, names=["K", "G", "delta"])
    reduced, build_s = timed(lambda: bp.ReducedScene(model.scene, snapshots, 0.01 * sigma))
    tree, fit_s = timed(lambda: fit(elastic_plate(reduced, demo.NOMINAL, noise_scale=noise), {"y": y}, "laplace",
                                    num_samples=draws, progress=False, init_values=start))
    print(f"reduced (rank {reduced.rank}): build {build_s:.1f} s + Laplace with predictive({draws}) "
          f"{fit_s:.1f} s = {build_s + fit_s:.1f} s")
    for k in ("K", "G", "delta", "sigma"):
        a, b = tree["posterior"][k].values.ravel(), full_tree["posterior"][k].values.ravel()
        print(f"  {k}: reduced mean {a.mean():.5g} sd {a.std():.3g}, full mean {b.mean():.5g} sd {b.std():.3g}: "
              f"{(a.mean() - b.mean()) / b.std():+.3f} full sd, sd ratio {a.std() / b.std():.3f}")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--draws", type=int, default=100)
    main(parser.parse_args().draws)
