"""One stochastic fracture realisation of the crack-ensemble plate (seed 002 eq 4 with
damage, ``bayespd.infer.ensemble_plate``): wall time with the operator updated by Woodbury
(``max_rank``, default 512) against a fresh factorisation at every change of the intact
bonds (``max_rank=0``), and where the time goes (factorisations, steps, bonds broken).

Both runs take the same steps and break the same bonds (conjugate gradients solve the same
exact tangent to 1e-8); the output checks it. One torch thread and one BLAS thread, as a
worker of the ensemble runs it.

    python benchmarks/fracture.py [--side 100] [--max-rank 512 0]
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np
import torch
from threadpoolctl import threadpool_limits

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bayespd import sparse  # noqa: E402
from bayespd.infer.ensemble_plate import notched_plate  # noqa: E402
from bayespd.solvers import fracture  # noqa: E402


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--side", type=float, default=100.0, help="plate side in mm (h = 1 mm): 100 -> 10k particles")
    parser.add_argument("--max-rank", type=int, nargs="+", default=[512, 0])
    args = parser.parse_args()
    torch.set_num_threads(1)
    sparse.FACTOR_THREADS = 1
    scene = notched_plate(side=args.side, h=1.0, steps=50, sigma=1500.0)
    driver = scene.build({"K": 2886.0, "s0": 0.0094})
    counted = {"n": 0}
    factorised = fracture.StochasticFracture._factorised

    def counting(self, *a):
        counted["n"] += 1
        return factorised(self, *a)

    fracture.StochasticFracture._factorised = counting
    print(f"load average {os.getloadavg()[0]:.2f}; {len(scene.x)} particles; backend {sparse.default_backend()}")
    runs = []
    with threadpool_limits(1):
        for rank in args.max_rank:
            counted["n"] = 0
            start = time.perf_counter()
            run = driver.run(scene.load_factors, scene.dt, seed=3, max_rank=rank)
            wall = time.perf_counter() - start
            runs.append(run)
            print(f"max_rank {rank}: {wall:.1f} s, {len(run.t)} steps ({1e3 * wall / len(run.t):.0f} ms each), "
                  f"{counted['n']} factorisations, {run.broken[-1]} bonds broken", flush=True)
    same = all(np.array_equal(r.intact < 0.5, runs[0].intact < 0.5) and len(r.t) == len(runs[0].t) for r in runs)
    print(f"same steps and broken bonds in every run: {same}")


if __name__ == "__main__":
    main()
