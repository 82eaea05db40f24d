"""The cost of the posterior predictive of a Laplace fit at ~5k particles: the fit with
``predictive=False``, the replay of every draw (one factorisation, then CG preconditioned by
it: ``bayespd.linalg.reuse``), a thinned replay (``predictive=20``), and, for comparison, the
replay with a fresh factorisation per draw (reuse switched off).

Scene: benchmarks/inference.py's ``5k`` plate with a hole (h = 0.4 mm, delta_max = 3 h,
4,684 particles, 9.4k dofs), data from the model plus 1 % noise; ``models.elastic_plate``
(K, G, delta, sigma), Laplace with the exact Hessian, 100 draws.

    python benchmarks/predictive.py [--draws 100]
"""
from __future__ import annotations

import argparse
import contextlib
import time

import inference as bi  # noqa: F401  (experiments/ on sys.path, one torch thread)

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
    scene, y, sigma = bi.fine_problem()
    model = elastic_plate(scene, demo.NOMINAL, noise_scale=0.05 * float(y.abs().max()))
    print(f"{scene.particles.n} particles, backend {sparse.default_backend()}, {draws} draws")

    def laplace(predictive):
        return fit(model, {"y": y}, "laplace", num_samples=draws, progress=False, predictive=predictive)

    runs = {}
    for name, predictive in (("no predictive", False), ("predictive, every draw", True), ("predictive=20", 20)):
        tree, wall = timed(lambda: laplace(predictive))
        runs[name] = (wall, tree.attrs["wall_time_s"], tree.attrs["predictive_wall_time_s"])
    reuse_on = replay_module.reusing_factors
    replay_module.reusing_factors = contextlib.nullcontext  # a fresh factorisation per draw
    try:
        tree, wall = timed(lambda: laplace(True))
        runs["predictive, every draw, no factor reuse"] = (wall, tree.attrs["wall_time_s"],
                                                          tree.attrs["predictive_wall_time_s"])
    finally:
        replay_module.reusing_factors = reuse_on
    print("| run | total (s) | Laplace fit (s) | replay (s) |\n|---|---|---|---|")
    for name, (wall, fit_s, replay_s) in runs.items():
        print(f"| {name} | {wall:.1f} | {fit_s:.1f} | {replay_s:.1f} |")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--draws", type=int, default=100)
    main(parser.parse_args().draws)
