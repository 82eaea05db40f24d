"""Forward and adjoint cost of a 2D LPS plate (plane stress) per sparse backend.

For each particle count and backend: bond search + set-up, numeric assembly, factorisation,
solve, and the gradient of a scalar of u with respect to (K, G, delta) (one adjoint solve with
the same factor plus the matrix-free form derivative); peak resident memory of the run.
Each configuration runs in its own process so that peak memory is its own.

    python benchmarks/forward.py [--sizes 10000 40000] [--m 3]
"""
from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time

import numpy as np


def run_one(n: int, m: float, backend: str) -> dict:
    import torch

    import bayespd as bp
    from bayespd import sparse

    torch.set_num_threads(1)
    side = int(round(np.sqrt(n)))
    h = 1.0
    t0 = time.perf_counter()
    p = bp.grid_2d(side * h, side * h, h)
    mat = bp.LPS(p, bp.find_bonds(p, m * h), plane="stress")
    scene = bp.Scene(mat, [bp.Dirichlet.layer(p, "left", m * h)], [bp.Load(p.layer("right", h), (1.0, 0.0))])
    _ = mat.pattern
    setup = time.perf_counter() - t0
    params = {"K": torch.tensor(3333.0, requires_grad=True), "G": torch.tensor(1538.0, requires_grad=True),
              "delta": torch.tensor(m * h, requires_grad=True)}
    c = scene.constraints
    t0 = time.perf_counter()
    values = c.free_values(mat.numeric_stiffness(params, params["delta"]))
    assemble = time.perf_counter() - t0
    t0 = time.perf_counter()
    factor = c.pattern.factorize(values, backend)
    factorise = time.perf_counter() - t0
    t0 = time.perf_counter()
    factor.solve(c.free(scene.force).numpy())
    solve = time.perf_counter() - t0
    sparse.default_backend = lambda: backend
    t0 = time.perf_counter()
    u = scene.solve(params)
    forward = time.perf_counter() - t0
    t0 = time.perf_counter()
    u[:, 0].sum().backward()
    gradient = time.perf_counter() - t0
    return {"particles": p.n, "dofs": c.pattern.n, "nnz": c.pattern.nnz, "m": m, "backend": backend,
            "setup_s": setup, "assemble_s": assemble, "factorise_s": factorise, "solve_s": solve,
            "forward_total_s": forward, "gradient_s": gradient,
            "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[10_000, 40_000])
    parser.add_argument("--m", type=float, nargs="+", default=[3.0])
    parser.add_argument("--backends", nargs="+", default=["cholmod", "splu"])
    parser.add_argument("--one", nargs=3, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.one:
        print(json.dumps(run_one(int(args.one[0]), float(args.one[1]), args.one[2])))
        return
    from bayespd import sparse
    backends = [b for b in args.backends if b != "cholmod" or sparse.cholmod is not None]
    header = f"{'particles':>9} {'m':>3} {'backend':>8} {'nnz':>10} {'setup':>7} {'assemble':>8} " \
             f"{'factor':>7} {'solve':>7} {'forward':>8} {'gradient':>8} {'peak MB':>8}"
    print(header)
    for n in args.sizes:
        for m in args.m:
            for b in backends:
                out = subprocess.run([sys.executable, __file__, "--one", str(n), str(m), b],
                                     capture_output=True, text=True, check=True)
                r = json.loads(out.stdout.strip().splitlines()[-1])
                print(f"{r['particles']:>9} {r['m']:>3g} {b:>8} {r['nnz']:>10} {r['setup_s']:>7.2f} "
                      f"{r['assemble_s']:>8.3f} {r['factorise_s']:>7.3f} {r['solve_s']:>7.3f} "
                      f"{r['forward_total_s']:>8.3f} {r['gradient_s']:>8.3f} {r['peak_rss_mb']:>8.0f}", flush=True)


if __name__ == "__main__":
    main()
