"""CHOLMOD numeric factorisation with one OpenBLAS thread against all cores, by system size.

The LPS stiffness of experiments/demo.py's plate at several spacings (delta = 3 h), free dofs
only; each size factorised with ``linalg.settings(factor_threads=...)`` 1 and None (OpenBLAS's
setting: all cores unless OPENBLAS_NUM_THREADS lowers it), interleaved, best of ``--repeat``
each, after the symbolic analysis. Prints dofs, factor entries, both times and their ratio:
the table behind the default factor_threads = None.

    python benchmarks/factor_threads.py [--h 2 1 0.5 0.4 0.25] [--repeat 7]
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "experiments"))
import demo  # noqa: E402  (one torch thread; the repository root on sys.path)

from bayespd import linalg  # noqa: E402
from bayespd.linalg import sparse  # noqa: E402
from timing import best  # noqa: E402


def free_system(h: float):
    scene = demo.plate(h, 3 * h)
    p = {"K": torch.tensor(demo.TRUTH["K"]), "G": torch.tensor(demo.TRUTH["G"]), "delta": torch.tensor(2.5 * h)}
    c = scene.constraints
    return c.pattern, c.free_values(scene.material.numeric_stiffness(p))


def timed(pattern, values, threads, repeat):
    with linalg.settings(factor_threads=threads):
        return best(lambda: pattern.factorize(values, "cholmod"), repeat)


def main(hs, repeat):
    print(f"{'h':>6} {'dofs':>8} {'L entries':>11} {'1 thread':>10} {'all cores':>10} {'all / 1':>8}")
    for h in hs:
        pattern, values = free_system(h)
        entries = pattern.factorize(values, "cholmod").cholmod.L().nnz
        one, every = [], []
        for _ in range(2):  # interleaved: the machine's load hits both alike
            one.append(timed(pattern, values, 1, repeat))
            every.append(timed(pattern, values, None, repeat))
        one, every = min(one), min(every)
        print(f"{h:6.2f} {pattern.n:8d} {entries:11d} {one * 1e3:8.2f}ms {every * 1e3:8.2f}ms {every / one:8.2f}", flush=True)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--h", type=float, nargs="+", default=[2.0, 1.0, 0.5, 0.4, 0.25])
    parser.add_argument("--repeat", type=int, default=7)
    args = parser.parse_args()
    if sparse.default_backend() != "cholmod":
        sys.exit("needs the CHOLMOD backend: make fast")
    main(args.h, args.repeat)
