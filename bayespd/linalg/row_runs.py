"""A CSR matrix cut into runs of rows and applied on two threads (numba, where installed): its
product, and the hybrid Gauss-Seidel sweeps that smooth the V-cycle of ``bayespd.linalg.amg``.

scipy's product runs on one thread, and pyamg's Gauss-Seidel sweep holds the GIL throughout,
so a PCG iteration used one core. Here the rows are cut into at most ``RUNS`` runs, each
computed by a compiled loop that releases the GIL into an output of its own from read-only
inputs, so the runs can go to any thread in any order (``bond_loops.claimed``) and the result
is the same bits on one thread or two.

The smoother is Gauss-Seidel inside each run and Jacobi between runs, with each pivot raised by
the absolute sum of its row's entries outside the run: the l1 hybrid Gauss-Seidel of Baker,
Falgout, Kolev & Yang 2011 (section 5), M = blockdiag(D + D_l1 + L). The pre-smoother is
x = M^-1 b from zero, the post-smoother x + M^-T (b - A x), so the cycle is symmetric
(x . C y = y . C x), and M + M^T - A is positive definite for every SPD A (their Theorem 6.2),
so the smoother converges and the cycle preconditions CG. Without the l1 term a finite-element
stiffness (scikit-fem's Q2 cantilever of ``fe_convergence``) made the cycle indefinite and CG
diverge; on PD bond operators only the rows next to a run's ends change. The sweeps read A's
entries rounded to single precision A_s (vectors and sums in double): two thirds of the bytes a
sweep moves, and the cycle stays SPD, since M + M^T - A_s = D + 2 D_l1 - (A_s's entries outside
the runs) is diagonally dominant for any symmetric A_s with a positive diagonal, and the coarse
levels are the Galerkin products of A (160k-particle plate: 19 PCG iterations either way, the
sweeps 1.6x faster). A smoother's run spans
at least three bandwidths of A, so that few couplings cross between runs: on the 3D cantilever of
``fe_convergence`` (20k particles, m = 2, bandwidth 7,541 rows of 59,904) 8 runs took 20 PCG
iterations, 2 runs 15, pyamg's sweep 13; on the 2D plate at 160k (bandwidth 1,599 of 320k rows) 8
runs take pyamg's 17. The run count is fixed by the rows, not by the threads: one thread computes
what two would.

The loops sum a row in whatever order LLVM vectorises it (``fastmath`` reassociation and fused
multiply-adds) over unsigned indices (numba checks a signed index for wrap-around): a CSR
product 1.6x and 2x faster than without them, faster than scipy's (benchmarks/README.md, issue
31, sixth pass); the last bits depend on the CPU's vector width, not on the run. The sweeps
need sorted indices (a copy is sorted where they are not). A row whose diagonal is 0 (a dof no
bond reaches) keeps its value, as in pyamg's sweep.
"""
from __future__ import annotations

import os
import threading

import numpy as np
import scipy.sparse as sp
import torch

from bayespd import bond_loops
from bayespd.bond_loops import numba

RUNS = 8  # runs of rows (fixed: the results do not depend on the thread count)
MIN_ROWS = 4096  # rows per run below which the matrix is one run
BANDWIDTHS = 3  # a smoother's runs span at least this many bandwidths (the module docstring)
NONE = np.iinfo(np.uint64).max  # a row without a diagonal entry
SINGLE_RANGE = (1e-30, 1e30)  # a diagonal within which a smoother's entries are read in single precision


def usable() -> bool:
    """True when the compiled loops can run (numba installed, ``bond_loops.ENABLED``)."""
    return bond_loops.usable()


def warm_up() -> None:
    """Load the compiled loops in a background thread, once per process: numba's first call in
    a process costs ~0.25 s (its compiler's set-up, before the cached code loads), which a
    stiffness ``Assembly`` (made before its terms) and the AMG set-up that call this hide on a
    free core. A fork waits for it (a child must not
    inherit numba's compiler lock held by a thread it does not have)."""
    if usable() and not _WARM:
        _WARM.append(threading.Thread(target=_load, name="bayespd-row-runs", daemon=True))
        _WARM[0].start()


_WARM: list = []
os.register_at_fork(before=lambda: _WARM and _WARM[0].join(), after_in_child=_WARM.clear)


def _load():
    identity, b = sp.identity(2, format="csr"), np.ones(2)
    runs = RowRuns.smoother(identity)  # single-precision entries (the sweeps, rho's products)
    x = runs.pre(runs.product(b))
    runs.post(x, runs.residual_after_pre(x, RowRuns(identity).product(b)))


class RowRuns:
    """A CSR matrix A (n x m) in runs of rows (at most ``RUNS``, each at least ``MIN_ROWS`` and
    ``shortest`` rows long): ``product``, and for ``smoother``'s runs the sweeps ``pre``,
    ``residual_after_pre``, ``post``; ``single``: its entries read in single precision where
    A's diagonal lies in single's range (``SINGLE_RANGE``; vectors and sums stay double)."""

    def __init__(self, A, shortest: int | None = None, single: bool = False):
        self.A = A
        # unsigned views of the index arrays (the module docstring)
        unsigned = np.uint32 if A.indices.dtype == np.int32 else np.uint64
        self.indptr, self.indices = A.indptr.view(unsigned), A.indices.view(unsigned)
        self.data = A.data
        if single:  # where the diagonal lies in single's range (a square A's: its entries are bounded by it)
            d = np.abs(A.diagonal())
            if d.max(initial=0.0) < SINGLE_RANGE[1] and d[d > 0].min(initial=np.inf) > SINGLE_RANGE[0]:
                self.data = A.data.astype(np.float32)
        n = A.shape[0]
        count = max(1, min(RUNS, n // max(MIN_ROWS, shortest or 0)))
        cuts = [n * t // count for t in range(count + 1)]
        self.runs = list(zip(cuts[:-1], cuts[1:]))

    @classmethod
    def smoother(cls, A, single: bool = True) -> RowRuns:
        """The runs of A with sorted indices (A itself when sorted), each ``BANDWIDTHS`` of A's
        bandwidths long at least, its diagonal located and the l1 pivots computed; by default
        its entries read in single precision."""
        A = A if A.has_sorted_indices else A.sorted_indices()
        filled = np.flatnonzero(np.diff(A.indptr))
        reach = int(np.max(A.indices[A.indptr[filled + 1] - 1] - filled, initial=0))  # sorted: a row's last column
        runs = cls(A, BANDWIDTHS * reach, single)
        runs.diagonal = np.empty(A.shape[0], dtype=np.uint64)  # each row's diagonal entry (NONE: none)
        runs.pivot = np.zeros(A.shape[0])  # the l1 pivots a_ii + sum of |a_ij| outside the run
        cuts = np.array([lo for lo, _ in runs.runs] + [A.shape[0]], dtype=np.uint64)
        _pivots(runs.indptr, runs.indices, runs.data, cuts, runs.diagonal, runs.pivot)
        return runs

    def _each_run(self, kernel, *vectors) -> np.ndarray:
        """kernel(indptr, indices, data, *vectors, lo, hi, out) over the runs, joined."""
        def run(t):
            lo, hi = self.runs[t]
            out = np.empty(hi - lo)
            kernel(self.indptr, self.indices, self.data, *vectors, np.uint64(lo), np.uint64(hi), out)
            return out

        threads = torch.get_num_threads() if len(self.runs) > 1 else 1
        return np.concatenate(bond_loops.claimed(run, len(self.runs), threads))

    def product(self, x: np.ndarray) -> np.ndarray:
        """A x for x of shape (m,) or (m, k) (k columns one after another)."""
        if x.ndim == 2:
            return np.stack([self.product(np.ascontiguousarray(c)) for c in x.T], axis=1)
        return self._each_run(_product, x)

    def pre(self, b: np.ndarray) -> np.ndarray:
        """M^-1 b: a forward sweep from x = 0."""
        return self._each_run(_forward_from_zero, self.diagonal, self.pivot, b)

    def residual_after_pre(self, x: np.ndarray, b: np.ndarray) -> np.ndarray:
        """b - A x for x = ``pre(b)``: in a run, b_i - sum_{lo <= j < i} a_ij x_j = p_i x_i (the
        forward sweep), so the row's entries from the run's start to its diagonal are not read
        again (half of each row)."""
        return self._each_run(_residual_after_pre, self.diagonal, self.pivot, x, b)

    def post(self, x: np.ndarray, b: np.ndarray) -> np.ndarray:
        """x + M^-T (b - A x): a backward sweep from x."""
        return self._each_run(_backward, self.diagonal, self.pivot, x, b)


if numba is not None:
    @numba.njit(nogil=True, cache=True)
    def _pivots(indptr, indices, data, cuts, diagonal, pivot):  # pragma: no cover - compiled
        """Each row's diagonal entry (NONE: none) and l1 pivot, over the runs [cuts[t], cuts[t + 1])."""
        for t in range(len(cuts) - 1):
            lo, hi = cuts[t], cuts[t + 1]
            for i in range(lo, hi):
                diagonal[i] = NONE
                pivot[i] = 0.0
                for k in range(indptr[i], indptr[i + 1]):
                    j = indices[k]
                    if j == i:
                        diagonal[i] = k
                        pivot[i] += data[k]
                    elif j < lo or j >= hi:
                        pivot[i] += abs(data[k])

    @bond_loops.fast_kernel
    def _forward_from_zero(indptr, indices, data, diagonal, pivot, b, lo, hi, out):  # pragma: no cover - compiled
        for r in range(hi - lo):
            i, d = lo + r, diagonal[lo + r]
            if d == NONE or data[d] == 0.0:
                out[r] = 0.0
                continue
            acc, first = b[i], indptr[i]
            while indices[first] < lo:  # columns left of the run: x = 0 there
                first += 1
            for k in range(first, d):
                acc -= data[k] * out[indices[k] - lo]
            out[r] = acc / pivot[i]

    @bond_loops.fast_kernel
    def _backward(indptr, indices, data, diagonal, pivot, x, b, lo, hi, out):  # pragma: no cover - compiled
        for r in range(hi - lo):
            out[r] = x[lo + r]
        for s in range(hi - lo):
            r = hi - lo - 1 - s
            i, d = lo + r, diagonal[lo + r]
            if d == NONE or data[d] == 0.0:
                continue
            start, end = indptr[i], indptr[i + 1]
            acc = b[i]
            if indices[start] >= lo and indices[end - 1] < hi:  # the whole row inside the run
                for k in range(start, d):
                    acc -= data[k] * out[indices[k] - lo]
                for k in range(d + 1, end):
                    acc -= data[k] * out[indices[k] - lo]
            else:
                for k in range(start, end):
                    j = indices[k]
                    if j != i:
                        acc -= data[k] * (out[j - lo] if lo <= j < hi else x[j])
            out[r] = (acc + (pivot[i] - data[d]) * x[i]) / pivot[i]  # x + M^-T (b - A x), M's l1 term on x

    @bond_loops.fast_kernel
    def _residual_after_pre(indptr, indices, data, diagonal, pivot, x, b, lo, hi, out):  # pragma: no cover - compiled
        for r in range(hi - lo):
            i, d = lo + r, diagonal[lo + r]
            start, end = indptr[i], indptr[i + 1]
            if d == NONE or data[d] == 0.0:  # no sweep on this row: all of it
                acc = b[i]
                for k in range(start, end):
                    acc -= data[k] * x[indices[k]]
                out[r] = acc
                continue
            acc = (pivot[i] - data[d]) * x[i]
            k = start
            while indices[k] < lo:  # columns left of the run
                acc -= data[k] * x[indices[k]]
                k += 1
            for k in range(d + 1, end):
                acc -= data[k] * x[indices[k]]
            out[r] = acc

    @bond_loops.fast_kernel
    def _product(indptr, indices, data, x, lo, hi, out):  # pragma: no cover - compiled
        for r in range(hi - lo):
            i = lo + r
            acc = 0.0
            for k in range(indptr[i], indptr[i + 1]):
                acc += data[k] * x[indices[k]]
            out[r] = acc
