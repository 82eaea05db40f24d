"""Force-evaluation throughput of the linearised operator: K u per second, in bonds per second.

For a 2D plate (plane stress) with m = delta/h, LPS and bond-based (PMB), the internal force
f = K u is evaluated by

* ``torch Gram``: matrix-free ``assembly.internal_force`` (torch gather / index_add over the
  Gram operators' entries; differentiable; what ``material.form`` costs);
* ``scipy ops``: matrix-free with the Gram operators as scipy CSR matrices
  (``Assembly.operator``, what PCG uses);
* ``scipy K``: the assembled K (CSC, ``Pattern.matrix``) times u;
* ``torch K``: the assembled K as a torch sparse CSR tensor times u.

"bonds" counts each interacting pair once (i < j), so bonds/s compares with codes that loop
over bonds. Run in one process per configuration, best of 5 after a warm-up.

    python benchmarks/throughput.py [--side 401] [--m 2 3] [--threads 1 2]
"""
from __future__ import annotations

import argparse
import os
import warnings

import numpy as np

from timing import best


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--side", type=int, default=401)
    parser.add_argument("--m", type=float, nargs="+", default=[2.0, 3.0])
    parser.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--materials", nargs="+", default=["lps", "pmb"])
    args = parser.parse_args()
    import torch

    import bayespd as bp
    from bayespd.linalg.assembly import internal_force
    from bayespd.linalg.stiffness_solver import Assembly

    torch.set_default_dtype(torch.float64)
    warnings.filterwarnings("ignore", message=".*[Ss]parse.*")
    print(f"{'particles':>9} {'m':>3} {'mat':>4} {'bonds':>9} {'K nnz':>10} {'thr':>3} "
          f"{'torch Gram':>11} {'scipy ops':>10} {'scipy K':>9} {'torch K':>9}   (bonds/s; load {os.getloadavg()[0]:.2f})")
    for m in args.m:
        p = bp.grid_2d(float(args.side), float(args.side), 1.0)
        bonds = bp.find_bonds(p, m)
        for material in args.materials:
            mat = (bp.LPS if material == "lps" else bp.BondBased)(p, bonds, plane="stress")
            terms = mat.terms({"K": torch.tensor(3333.0), "G": torch.tensor(1538.0), "delta": torch.tensor(m)})
            num = [(g, d.numpy(), w.numpy()) for g, d, w in terms]
            u = torch.randn(2 * p.n, dtype=torch.float64)
            un = u.numpy()
            ops = Assembly(mat.grams()).operator(num)
            values = mat.numeric_stiffness({"K": 3333.0, "G": 1538.0, "delta": m})
            K = mat.pattern.matrix(values)
            Kt = torch.sparse_csr_tensor(torch.as_tensor(K.indptr.astype(np.int64)),
                                         torch.as_tensor(K.indices.astype(np.int64)),
                                         torch.as_tensor(K.data), size=K.shape)  # K symmetric: CSC = CSR
            ref = K @ un
            for name, f in [("gram", lambda: internal_force(terms, u)), ("ops", lambda: ops(un)),
                            ("torchK", lambda: Kt @ u)]:
                got = f()
                got = got.numpy() if isinstance(got, torch.Tensor) else got
                assert np.allclose(got, ref, rtol=1e-9, atol=1e-9 * np.abs(ref).max()), name
            for threads in args.threads:
                torch.set_num_threads(threads)
                t = [best(lambda: internal_force(terms, u)), best(lambda: ops(un)),
                     best(lambda: K @ un), best(lambda: Kt @ u)]
                rates = " ".join(f"{bonds.n / x:>{w}.3g}" for x, w in zip(t, (11, 10, 9, 9)))
                print(f"{p.n:>9} {m:>3g} {material:>4} {bonds.n:>9} {K.nnz:>10} {threads:>3} {rates}"
                      f"   ({' '.join(f'{1e3 * x:.1f}' for x in t)} ms)", flush=True)


if __name__ == "__main__":
    main()
