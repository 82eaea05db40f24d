"""Many damage laws on one small sheet: ``learn.forward_runs`` (batches of disjoint copies, side by
side on threads) against one ``learn.forward_run`` per law. The scene is md_learning's size: a
19 x 19 node LPS sheet (h = 5 A, delta = 2.5 h, plane strain, the graphene sheet's moduli) with a
25 A edge slit, pulled apart at its side columns over 41 frames (2 ps), at ``--runs`` (s0, eta / s0)
pairs. Prints seconds per run (wall and this process's CPU) for each batch size and thread count,
each the best of ``--repeat`` rounds, with the load average at the start.

    python benchmarks/batched_runs.py [--runs 64] [--batch 8 16 32 64] [--threads 1 2] [--repeat 3]
"""
from __future__ import annotations

import argparse
import os

import numpy as np
import torch

from timing import best_with_cpu

H, DELTA = 5.0, 12.5


def scene():
    """(material, params, rho, frames, prescribed, moving): the docstring's sheet."""
    from bayespd.bonds import find_bonds, precrack
    from bayespd.discretize import from_points
    from bayespd.influence import Bernstein
    from bayespd.learn.kernel import lps_params
    from bayespd.materials.lps import LPS
    g = np.arange(19) * H - 45.0
    x = np.stack(np.meshgrid(g, g, indexing="ij"), -1).reshape(-1, 2)
    p = from_points(x, np.full(len(x), H * H), h=H)
    material = LPS(p, precrack(p, find_bonds(p, DELTA), [[-2.5, -50.0], [-2.5, -20.0]]), plane="strain",
                   influence=Bernstein(3))
    pulled = np.abs(x[:, 0]) > 45.0 - H / 2
    side = np.sign(x[:, 0])[:, None] * np.array([1.0, 0.0])
    return (material, lps_params(6.76, 5.40, [1.0, 2.0, 1.5, 0.5], DELTA), 4.6, np.linspace(0.0, 2.0, 41), pulled,
            lambda t: 2.0 * t * side)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=64)
    parser.add_argument("--batch", type=int, nargs="+", default=[8, 16, 32, 64])
    parser.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    from bayespd.learn.forward import forward_run, forward_runs
    material, params, rho, frames, pulled, moving = scene()
    s0s = np.geomspace(0.05, 0.2, args.runs)
    widths = np.resize([0.05, 0.1, 0.2, 0.4, 0.8], args.runs)
    print(f"load {os.getloadavg()[0]:.2f}; {material.particles.n} nodes, {len(material.i)} bonds, {args.runs} runs")
    torch.set_num_threads(1)
    wall, cpu = np.divide(best_with_cpu(lambda: [forward_run(material, params, rho, frames, s, pulled, moving, eta_over_s0=w)
                                                 for s, w in zip(s0s, widths)], args.repeat), args.runs)
    print(f"one forward_run each            wall {wall:.4f} s/run  CPU {cpu:.4f} s/run")
    for threads in args.threads:
        for batch in args.batch:
            wall, cpu = np.divide(best_with_cpu(lambda: forward_runs(material, params, rho, frames, s0s, widths, pulled,
                                                                     moving, batch=batch, threads=threads), args.repeat),
                                  args.runs)
            print(f"forward_runs batch {batch:3d} threads {threads}  wall {wall:.4f} s/run  CPU {cpu:.4f} s/run")


if __name__ == "__main__":
    main()
