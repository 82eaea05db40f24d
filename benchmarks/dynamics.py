"""Explicit dynamics and Langevin throughput: velocity Verlet steps per second and time per
particle-step for a 2D bond-based (PMB, plane stress) plate, or with ``--dim 3`` a cube, with
the geometrically exact force of ``bayespd.nonlinear`` (float64 and float32), and overdamped
Langevin steps per second (2D; Dodwell 2019 eq 4; Euler-Maruyama and the semi-implicit theta = 1
scheme, linearised force, white noise, one chain).

Each explicit timing is taken at every thread count of ``--threads`` in turn, ``--repeat``
rounds (the counts interleaved within a round, so that they share the machine's load) of
``--steps`` steps after a warm-up; min and median are printed (the machine is shared: the min
is the least disturbed run), with the load average at the start and at the end of each size.

    python benchmarks/dynamics.py [--sizes 10000 100000] [--dim 2] [--m 3] [--threads 1 2] [--steps 50] [--repeat 5]
"""
from __future__ import annotations

import argparse
import math
import os
import statistics
import time

import torch

from timing import best


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[10000, 100000])
    parser.add_argument("--dim", type=int, default=2, choices=[2, 3], help="plate (2) or cube (3)")
    parser.add_argument("--m", type=float, default=3.0)
    parser.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--steps", type=int, default=50)
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--langevin-size", type=int, default=10000)
    args = parser.parse_args()

    import bayespd as bp
    from bayespd.nonlinear import NonlinearBonds
    from bayespd.solvers import Langevin, critical_time_step, linear_elastic, lumped_mass, velocity_verlet, white_noise

    print(f"{args.dim}D, threads {args.threads}, m = {args.m:g}, {args.steps} steps, {args.repeat} rounds; "
          f"load {os.getloadavg()[0]:.2f}")
    print(f"{'particles':>9} {'bonds':>9} {'dtype':>7} {'threads':>7} {'force ms min/med':>17} "
          f"{'step ms min/med':>16} {'us/pt-step min/med':>19}")
    dt = None
    for size in args.sizes:
        side = float(round(size ** (1 / args.dim)))
        p = bp.grid_2d(side, side, 1.0) if args.dim == 2 else bp.grid_3d(side, side, side, 1.0)
        mat = bp.BondBased(p, bp.find_bonds(p, args.m))
        kin = NonlinearBonds(mat)
        M = lumped_mass(p, 1.0)
        if dt is None:  # same h, m and material at every size: the same stable step
            dt = 0.5 * critical_time_step(linear_elastic(mat, {"K": 1.0, "delta": args.m}).matrix, M)
        u0 = torch.zeros(p.n, args.dim)
        u0[:, 0] = 1e-4 * torch.as_tensor(p.x[:, 1])  # a shear: every bond loaded
        for dtype in (torch.float64, torch.float32):
            coef = kin.at({"K": 1.0, "delta": args.m}, dtype)
            u = u0.to(dtype)

            def force(v, coef=coef, shape=u0.shape):
                return coef.force(v.view(shape)).view(-1)

            runs = {"force": lambda: coef.force(u),
                    "step": lambda: velocity_verlet(force, M, u.reshape(-1), dt, args.steps)}
            times = interleaved(runs, args.threads, args.repeat)
            for threads in args.threads:
                t_force, t_run = times["force", threads], [t / args.steps for t in times["step", threads]]
                print(f"{p.n:>9} {mat.bonds.n:>9} {str(dtype)[6:]:>7} {threads:>7} "
                      f"{1e3 * min(t_force):>8.2f}/{1e3 * statistics.median(t_force):<8.2f} "
                      f"{1e3 * min(t_run):>7.2f}/{1e3 * statistics.median(t_run):<8.2f} "
                      f"{1e6 * min(t_run) / p.n:>9.3f}/{1e6 * statistics.median(t_run) / p.n:<9.3f}", flush=True)
        print(f"  (load {os.getloadavg()[0]:.2f})")
    torch.set_num_threads(args.threads[-1])

    side = round(math.sqrt(args.langevin_size))
    p = bp.grid_2d(float(side), float(side), 1.0)
    F = linear_elastic(bp.BondBased(p, bp.find_bonds(p, args.m)), {"K": 1.0, "delta": args.m}, eps=1e-3)
    L = Langevin(F, white_noise(1.0, F.n), 1.0, operator=F.matrix)
    dt_em = 0.5 * L.explicit_limit()
    u = torch.zeros(F.n)
    print(f"\nLangevin, {p.n} particles ({F.n} dofs), linearised PMB + eps I, C = I, one chain")
    for name, run in (("Euler-Maruyama (dt = 0.5 limit)", lambda: L.euler_maruyama(u, dt_em, args.steps, generator=0)),
                      ("semi-implicit theta = 1 (dt = 100 limit)",
                       lambda: L.semi_implicit(u, 200 * dt_em, args.steps, theta=1.0, generator=0))):
        step = best(run, args.repeat) / args.steps
        print(f"  {name:<42} {1e3 * step:8.2f} ms/step {1 / step:8.1f} steps/s {1e6 * step / p.n:8.3f} us/pt-step")


def interleaved(runs: dict, thread_counts: list, repeat: int) -> dict:
    """{(name, threads): seconds of each of ``repeat`` rounds}: in a round every run at every
    thread count once, after one warm-up call of each."""
    times = {}
    for rnd in range(repeat + 1):
        for threads in thread_counts:
            torch.set_num_threads(threads)
            for name, run in runs.items():
                t0 = time.perf_counter()
                run()
                if rnd:
                    times.setdefault((name, threads), []).append(time.perf_counter() - t0)
    return times


if __name__ == "__main__":
    main()
