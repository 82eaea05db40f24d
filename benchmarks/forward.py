"""Forward cost of a 2D plate (plane stress) per material, horizon and solver.

For each particle count, m = delta/h, material (LPS or bond-based PMB) and solver:

* set-up: grid, bond search, material, and what the solver caches (pattern and its
  free-dof restriction for a direct solver; nothing for PCG);
* assemble: K's values on the free pattern (direct), or the matrix-free operator (PCG; for
  ``amg`` also the bond operator K_b that the AMG set-up and the product share);
* factorise: CHOLMOD / SuperLU (direct, analysis included: it is a one-off solve), or the
  Cholesky factor of the preconditioner (PCG);
* solve: one right-hand side (PCG: the iterations, to the relative residual a Scene stops
  at, ``SCENE_RTOL`` = 1e-8);
* total = the four (wall), and the process's CPU seconds over them (``cpu``: both threads,
  system time included; steadier than wall on a shared host); peak resident memory of the
  process; relative residual ||K u - f||/||f||.

Each configuration runs in its own process so that peak memory is its own.

    python benchmarks/forward.py [--sizes 10000 40000 160801] [--m 2 3]
        [--materials lps pmb] [--solvers cholmod splu pcg pcg-short amg] [--threads 2]

Solvers: ``cholmod``/``splu`` = direct on the assembled K; ``pcg`` = matrix-free conjugate
gradients preconditioned by the Cholesky factor of the bond-graph Laplacian (all bonds);
``pcg-short`` = the same with only the nearest bonds (|xi| <= 1.5 h) in the preconditioner;
``amg`` = the same PCG preconditioned by a smoothed-aggregation V-cycle on the bond operator
with the rigid-body modes (``bayespd.linalg.amg``; "factorise" is the AMG set-up).
``--scene`` also times the differentiable ``Scene.solve`` (forward: set-up + one solve) and its
gradient (the adjoint: one more solve with the same factor or preconditioner); with
``--evaluations k``, k more of them on the same scene at horizons 4 %, 8 %, ... smaller (a
calibration's evaluations: the AMG path keeps its hierarchy across them).
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time

import numpy as np


def run_one(n: int, m: float, material: str, solver: str, threads: int, scene: bool, evaluations: int = 0,
            fresh: bool = False) -> dict:
    import torch

    import bayespd as bp
    from bayespd import linalg
    from bayespd.linalg import sparse
    from bayespd.linalg.amg import amg_preconditioner, pair_operator
    from bayespd.linalg.stiffness_solver import Assembly
    from bayespd.problem import SCENE_RTOL

    torch.set_num_threads(threads)
    linalg.set_defaults(factor_threads=threads)
    side = int(round(np.sqrt(n)))
    h = 1.0
    out = {"particles": side * side, "m": m, "material": material, "solver": solver,
           "threads": threads, "load": os.getloadavg()[0]}
    t_all, cpu_all = time.perf_counter(), time.process_time()
    t0 = time.perf_counter()
    p = bp.grid_2d(side * h, side * h, h)
    bonds = bp.find_bonds(p, m * h)
    cls = bp.LPS if material == "lps" else bp.BondBased
    mat = cls(p, bonds, plane="stress")
    clamp = np.repeat(p.layer("left", m * h), 2)
    params = {"K": torch.tensor(3333.0), "G": torch.tensor(1538.0), "delta": torch.tensor(m * h)}
    grams = mat.grams()
    direct = solver in ("cholmod", "splu")
    asm = Assembly(grams, ~clamp, pattern=mat.pattern if direct else None)
    if direct:
        _ = asm.free_pattern
    out["setup_s"] = time.perf_counter() - t0
    out["bonds"] = bonds.n
    out["dofs"] = int((~clamp).sum())

    t0 = time.perf_counter()
    terms = mat.terms(params)
    f = np.zeros((p.n, 2))
    f[p.layer("right", h), 0] = 1.0
    f = f.reshape(-1)[~clamp]
    if direct:
        values = asm.values(terms)
        out["nnz"] = asm.free_pattern.nnz
        out["assemble_s"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        factor = asm.free_pattern.factorize(values, solver)
        out["factorise_s"] = time.perf_counter() - t0
    else:
        rows = {grams[0]: bonds.length <= 1.5 * h + 1e-9} if solver == "pcg-short" else None
        num_terms = [(g, d.detach().numpy(), w.detach().numpy()) for g, d, w in terms]
        pair = pair_operator(num_terms, asm.free_index) if solver == "amg" else None
        matvec = asm.operator(num_terms, pair=pair)
        out["assemble_s"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        if solver == "amg":
            precondition = amg_preconditioner(num_terms, asm.free_index, p.x, pair=pair)
        else:
            precondition = asm.laplacian_preconditioner(num_terms, rows)
        out["factorise_s"] = time.perf_counter() - t0
        factor = sparse.PCGFactor(matvec, precondition, len(f), rtol=SCENE_RTOL)
    t0 = time.perf_counter()
    u = factor.solve(f)
    out["solve_s"] = time.perf_counter() - t0
    out["total_s"] = time.perf_counter() - t_all
    out["total_cpu_s"] = time.process_time() - cpu_all
    if not direct:
        out["iterations"] = factor.iterations
    check = asm.operator([(g, d.detach().numpy(), w.detach().numpy()) for g, d, w in terms])
    out["rel_residual"] = float(np.linalg.norm(check(u) - f) / np.linalg.norm(f))
    if scene:
        if direct:
            sparse.default_backend = lambda: solver
        kind = {"cholmod": "direct", "splu": "direct", "pcg": "pcg", "pcg-short": "pcg"}.get(solver, solver)
        sc = bp.Scene(mat, [bp.Dirichlet.layer(p, "left", m * h)], [bp.Load(p.layer("right", h), (1.0, 0.0))],
                      solver=kind, precondition_radius=None if solver == "pcg" else 1.5)
        q = {"K": torch.tensor(3333.0, requires_grad=True), "G": torch.tensor(1538.0, requires_grad=True),
             "delta": torch.tensor(m * h, requires_grad=True)}
        q = {k: q[k] for k in sc.param_names}
        t0, c0 = time.perf_counter(), time.process_time()
        us = sc.solve(q)
        out["scene_solve_s"], out["scene_solve_cpu_s"] = time.perf_counter() - t0, time.process_time() - c0
        t0, c0 = time.perf_counter(), time.process_time()
        us[:, 0].sum().backward()
        out["gradient_s"], out["gradient_cpu_s"] = time.perf_counter() - t0, time.process_time() - c0
        if evaluations:  # a calibration's next evaluations: smaller horizons, the same scene
            if fresh and sc._assembly is not None:
                sc._assembly.reuse_hierarchy = False
            t0 = time.perf_counter()
            for k in range(1, evaluations + 1):
                q = {name: torch.tensor(v.item() * (1 - 0.04 * k if name == "delta" else 1), requires_grad=True)
                     for name, v in q.items()}
                sc.solve(q)[:, 0].sum().backward()
            out["evaluation_s"] = (time.perf_counter() - t0) / evaluations
            out["amg_builds"] = sc._assembly.amg_builds if sc._assembly is not None else None
    out["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    return out


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[10_000, 40_000, 160_801])
    parser.add_argument("--m", type=float, nargs="+", default=[2.0, 3.0])
    parser.add_argument("--materials", nargs="+", default=["lps"], choices=["lps", "pmb"])
    parser.add_argument("--solvers", nargs="+", default=["cholmod", "pcg-short"],
                        choices=["cholmod", "splu", "pcg", "pcg-short", "amg"])
    parser.add_argument("--threads", type=int, default=2, help="torch and OpenBLAS threads")
    parser.add_argument("--scene", action="store_true", help="also time Scene.solve + gradient")
    parser.add_argument("--evaluations", type=int, default=0, help="with --scene: this many more "
                        "Scene.solve + gradient on the same scene at horizons 4, 8, ... %% smaller "
                        "(a calibration's evaluations); their mean time is printed")
    parser.add_argument("--fresh-hierarchy", action="store_true", help="with --evaluations: build "
                        "the AMG hierarchy anew at each (Assembly.reuse_hierarchy = False)")
    parser.add_argument("--timeout", type=float, default=900, help="seconds per configuration")
    parser.add_argument("--repeat", type=int, default=1, help="runs per configuration; the "
                        "fastest (total) is printed (the machine is shared: load varies)")
    parser.add_argument("--wait-load", type=float, default=None, help="before each run, wait "
                        "(up to --max-wait s) until the 1-minute load average is below this")
    parser.add_argument("--max-wait", type=float, default=180)
    parser.add_argument("--json", help="append each result to this JSON-lines file")
    parser.add_argument("--one", nargs=4, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.one:
        n, m, material, solver = args.one
        print(json.dumps(run_one(int(n), float(m), material, solver, args.threads, args.scene, args.evaluations,
                                 args.fresh_hierarchy)))
        return
    from bayespd.linalg import sparse
    solvers = [s for s in args.solvers if s != "cholmod" or sparse.cholmod is not None]
    print(f"{'particles':>9} {'m':>3} {'mat':>4} {'solver':>9} {'nnz':>10} {'setup':>6} {'assem':>6} "
          f"{'factor':>7} {'solve':>6} {'total':>7} {'cpu':>6} {'its':>4} {'resid':>8} {'peak MB':>8} {'load':>5}")
    for n in args.sizes:
        for m in args.m:
            for material in args.materials:
                for s in solvers:
                    cmd = [sys.executable, __file__, "--one", str(n), str(m), material, s,
                           "--threads", str(args.threads), "--evaluations", str(args.evaluations)] + (
                               ["--scene"] if args.scene else []) + (["--fresh-hierarchy"] if args.fresh_hierarchy else [])
                    runs = []
                    for _ in range(args.repeat):
                        if args.wait_load is not None:
                            t_wait = time.time()
                            while os.getloadavg()[0] >= args.wait_load and time.time() - t_wait < args.max_wait:
                                time.sleep(5)
                        try:
                            res = subprocess.run(cmd, capture_output=True, text=True, timeout=args.timeout)
                        except subprocess.TimeoutExpired:
                            print(f"{n:>9} {m:>3g} {material:>4} {s:>9}  timed out after {args.timeout:g} s", flush=True)
                            break
                        if res.returncode != 0:
                            print(f"{n:>9} {m:>3g} {material:>4} {s:>9}  failed: {res.stderr.strip().splitlines()[-1:]}", flush=True)
                            break
                        runs.append(json.loads(res.stdout.strip().splitlines()[-1]))
                        if args.json:
                            with open(args.json, "a") as fh:
                                fh.write(json.dumps(runs[-1]) + "\n")
                    if not runs:
                        continue
                    r = min(runs, key=lambda x: x["total_s"])
                    extra = ""
                    if "scene_solve_s" in r:
                        extra = (f"  scene {r['scene_solve_s']:.2f} grad {r['gradient_s']:.2f} "
                                 f"(ratio {r['gradient_s'] / r['scene_solve_s']:.2f}, CPU "
                                 f"{r['gradient_cpu_s'] / r['scene_solve_cpu_s']:.2f})")
                        if "evaluation_s" in r:
                            extra += f"  next evaluations {r['evaluation_s']:.2f} each (AMG builds {r['amg_builds']})"
                    print(f"{r['particles']:>9} {m:>3g} {material:>4} {s:>9} {r.get('nnz', 0):>10} "
                          f"{r['setup_s']:>6.2f} {r['assemble_s']:>6.2f} {r['factorise_s']:>7.2f} "
                          f"{r['solve_s']:>6.2f} {r['total_s']:>7.2f} {r['total_cpu_s']:>6.2f} {r.get('iterations', ''):>4} "
                          f"{r['rel_residual']:>8.1e} {r['peak_rss_mb']:>8.0f} {r['load']:>5.2f}{extra}", flush=True)


if __name__ == "__main__":
    main()
