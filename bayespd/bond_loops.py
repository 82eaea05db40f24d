"""Compiled loops over the bonds for the CPU paths of ``bayespd.nonlinear``, the damage index
and the fracture driver (numba, optional: ``pip install bayespd[fast]``).

torch evaluates the stretch and the PMB force of Dodwell 2019 eq 1-2 as a dozen passes over the
bond arrays, each writing a temporary; a loop reads each bond once and writes only its
result: ``stretch`` (s = e / |xi|) and ``pmb_force`` (f = -D^T (t y / |y|), t = k mu e),
each from u (the gather of u_j - u_i is cheaper than reading back stored components). They
do the torch path's operations in its order (e = eta . (y + xi) / (|y| + |xi|),
``nonlinear``), with a correctly rounded |y| where torch's sqrt and hypot are off by an ulp
now and then, except that the force takes k e / |y| as k eta . (y + xi) / ((|y| + |xi|) |y|),
one division instead of two (16 % less CPU at 100k particles): they agree with it to a few
ulp, in float64 and float32 (tests/test_nonlinear.py, tests/test_bond_loops.py).
The torch path stays for what they do not cover (``usable``): gradients, other devices, LPS.
Figures: benchmarks/README.md, "Compiled bond loops".

The work of a fracture run between its solves, each one pass where numpy, torch or scipy
take several (benchmarks/fracture_changes.py): ``tangent_change``, the entries of the
change of the bond-based tangent (``quasistatic``) over a set of bonds; ``damage_sums``,
the damage index's numerators, bit for bit torch's; ``tally``, what a damage update
changed; ``components``, the pieces of a bond graph by union-find, numbered as scipy's
connected_components numbers them (which it calls without numba).

ENABLED = False (or BAYESPD_BOND_LOOPS=0 in the environment) uses the torch, numpy and scipy
paths everywhere (the tests and benchmarks compare the two).
"""
from __future__ import annotations

import itertools
import os
import threading
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import scipy.sparse as sp
import torch
from scipy.sparse.csgraph import connected_components

try:
    import numba
except ImportError:  # the optional dependency is absent: torch does the work
    numba = None

ENABLED = os.environ.get("BAYESPD_BOND_LOOPS", "1") != "0"


def usable(*tensors) -> bool:
    """True when the loops can stand in for torch on these tensors (None: absent, ignored;
    none at all: for loops over index arrays): numba is installed and ENABLED, and they are
    on the CPU, all float64 or all float32, with no gradient to record."""
    if numba is None or not ENABLED:
        return False
    given = [t for t in tensors if t is not None]
    grad = torch.is_grad_enabled()
    return ({t.dtype for t in given} in (set(), {torch.float64}, {torch.float32})
            and all(t.device.type == "cpu" and not (grad and t.requires_grad) for t in given))


def stretch(u: torch.Tensor, ends: tuple, xi: torch.Tensor, length: torch.Tensor) -> torch.Tensor:
    """s (n_bonds,) of the bonds ``ends`` = (i, j) (int32) with xi (dim, n_bonds) and |xi|."""
    s = np.empty(len(length), dtype=length.numpy().dtype)
    _stretch(_BOND[u.shape[1]], u.detach().numpy(), *ends, xi.numpy(), length.numpy(), s)
    return torch.from_numpy(s)


def pmb_force(u: torch.Tensor, ends: tuple, xi: torch.Tensor, length: torch.Tensor, k: torch.Tensor,
              intact: torch.Tensor | None) -> torch.Tensor:
    """f (N, dim) of PMB bonds of stiffness k (n_bonds,) at the intact fractions (None: all 1),
    over ``torch.get_num_threads()`` threads when there are enough bonds (``shared``)."""
    un = u.detach().numpy()
    mu = np.ones(1, dtype=un.dtype) if intact is None else intact.detach().numpy()
    args = (_BOND[u.shape[1]], un, *ends, xi.numpy(), length.numpy(),
            np.broadcast_to(k.detach().numpy(), length.shape), mu, intact is not None)
    threads = torch.get_num_threads()
    parts = shares(ends, SHARES_PER_THREAD * threads if threads > 1 else 1)
    if len(parts) > 1:
        return torch.from_numpy(shared(_pmb_force, args, parts, un.shape, un.dtype, threads))
    f = np.zeros(un.shape, dtype=un.dtype)
    _pmb_force(*args, 0, len(length), 0, f)
    return torch.from_numpy(f)


MIN_SHARE = 1 << 15  # bonds per share below which one thread does the whole loop
SHARES_PER_THREAD = 8


def shared(kernel, args: tuple, parts: list, shape: tuple, dtype, threads: int) -> np.ndarray:
    """The sum over the ``shares`` (b0, b1, lo, hi) of ``kernel(*args, b0, b1, lo, out)``, each
    writing the rows [lo, hi) of f to an ``out`` of its own (``claimed``), added up in share
    order (the same bits whichever thread ran a share)."""
    def task(t):
        b0, b1, lo, hi = parts[t]
        out = np.zeros((hi - lo,) + tuple(shape[1:]), dtype=dtype)
        kernel(*args, b0, b1, lo, out)
        return out

    f = np.zeros(shape, dtype=dtype)
    for (_, _, lo, hi), out in zip(parts, claimed(task, len(parts), threads)):
        f[lo:hi] += out
    return f


def claimed(task, count: int, threads: int, redo: bool = True) -> list:
    """[task(0), ..., task(count - 1)]: the calling thread and ``threads - 1`` pool threads
    claim the tasks in turn; then the caller does again itself any task that no thread has
    finished: on a busy machine a pool thread that the scheduler has set aside delays nothing
    (where waiting for it costs a time slice), and the caller's extra work is at most the
    tasks that were under way elsewhere. A task may therefore run twice, once late: it must
    write nothing but its result, or the same bits to arrays of its own call. ``redo=False``:
    each task runs once and the caller waits for those the pool threads claimed (tasks that
    write into arrays the caller hands on; never from inside a task, whose pool thread it would
    wait on)."""
    results, lock, claim = [None] * count, threading.Lock(), itertools.count()

    def attempt(t):
        out = task(t)
        with lock:
            if results[t] is None:
                results[t] = (out,)

    def work():
        while (t := next(claim)) < count:
            attempt(t)

    others = [_pool(threads - 1).submit(work) for _ in range(threads - 1)]
    work()
    if redo:
        for t in range(count):
            if results[t] is None:
                attempt(t)
    else:
        for other in others:
            other.result()
    return [r[0] for r in results]


def shares(ends: tuple, count: int) -> list[tuple[int, int, int, int]]:
    """(first bond, end bond, lo, hi): ``count`` runs of consecutive bonds (at least
    MIN_SHARE each, else fewer) and the range [lo, hi) of the particles each touches; short
    ranges when the bonds are sorted by particle, as ``find_bonds`` sorts them."""
    i, j = ends
    n, count = len(i), max(1, min(count, len(i) // MIN_SHARE))
    key = (id(i), id(j), count)
    if key not in _SHARES:
        cuts = [n * t // count for t in range(count + 1)]
        parts = [(b0, b1, int(min(i[b0:b1].min(), j[b0:b1].min())), int(max(i[b0:b1].max(), j[b0:b1].max())) + 1)
                 for b0, b1 in zip(cuts[:-1], cuts[1:])]
        if len(_SHARES) > 64:
            _SHARES.clear()
        _SHARES[key] = (ends, parts)
    return _SHARES[key][1]


_SHARES: dict = {}  # (ids of i and j, count) -> ((i, j), kept alive while cached; the shares)
_POOLS: dict = {}


def _pool(workers: int) -> ThreadPoolExecutor:
    """The threads that run ``shared``'s shares beside the caller (the kernels release the
    GIL), per process: an executor's threads do not survive a fork. Between calls they wait
    on a lock, where an OpenMP pool spins (on a shared machine, in another process's time)."""
    key = (os.getpid(), workers)
    if key not in _POOLS:
        _POOLS[key] = ThreadPoolExecutor(workers, thread_name_prefix="bond_loops")
    return _POOLS[key]


def tangent_change(u_before: np.ndarray, u_after: np.ndarray, ends: tuple, xi: np.ndarray, length: np.ndarray,
                   k: np.ndarray, bonds: np.ndarray, before: np.ndarray, after: np.ndarray, local: np.ndarray):
    """(rows, cols, values): the entries of sum over ``bonds`` of after_b T_b(u_after) -
    before_b T_b(u_before), T_b the bond's tangent blocks (+H on ii and jj, -H on ij and ji,
    H = k [c I + (1 - c) n n^T], n = y / |y|, c = max(1 - |xi| / |y|, 0)), on the dofs
    ``local`` (flat dof -> its index, -1: left out); u as (N, dim) numpy arrays."""
    d = u_after.shape[1]
    size = 4 * d * d * len(bonds)
    rows, cols, values = np.empty(size, dtype=np.int64), np.empty(size, dtype=np.int64), np.empty(size)
    n = _tangent_change(_BOND[d], u_before, u_after, *ends, xi, length, np.broadcast_to(k, length.shape), bonds,
                        before, after, local, rows, cols, values)
    return rows[:n], cols[:n], values[:n]


def damage_sums(i: torch.Tensor, j: torch.Tensor, w: torch.Tensor, mu: torch.Tensor, V: torch.Tensor) -> torch.Tensor:
    """sum_j w (1 - mu) V_j over each particle's bonds (N,), the damaged ones (mu < 1) only,
    in torch's order (``DamageIndex``: first to every i, then to every j)."""
    out = np.zeros(len(V), dtype=V.numpy().dtype)
    _damage_sums(i.numpy(), j.numpy(), w.numpy(), mu.detach().numpy(), V.numpy(), out)
    return torch.from_numpy(out)


def tally(intact: torch.Tensor, operated: torch.Tensor, broken: torch.Tensor) -> tuple[float, torch.Tensor, int, bool]:
    """(max |intact - operated|, the broken mask intact < 1/2, its count, whether it differs
    from ``broken``) in one pass over the bonds."""
    now = np.empty(len(intact), dtype=np.bool_)
    moved, count, differs = _tally(intact.numpy(), operated.numpy(), broken.numpy(), now)
    return float(moved), torch.from_numpy(now), int(count), bool(differs)


def components(n: int, i: np.ndarray, j: np.ndarray, keep: np.ndarray | None = None) -> tuple[int, np.ndarray]:
    """(count, labels (n,)) of the connected pieces of the graph on n vertices with the edges
    (i, j) (those with ``keep``, default all), numbered 0, 1, ... in the order of their lowest
    vertex, as scipy's ``connected_components`` numbers them."""
    keep = np.ones(len(i), dtype=bool) if keep is None else np.asarray(keep, dtype=bool)
    if not usable():
        graph = sp.coo_matrix((np.ones(int(keep.sum())), (i[keep], j[keep])), shape=(n, n))
        return connected_components(graph, directed=False)
    labels = np.empty(n, dtype=np.int64)
    return int(_components(np.ascontiguousarray(i), np.ascontiguousarray(j), keep, labels)), labels


def _compiled(fn):
    """Compiled on first use in each process (per kernel, dimension and dtype), not
    cached on disk: a kernel that takes a compiled function as its argument misses numba's
    cache in every new process and would add a file to it each time."""
    return fn if numba is None else numba.njit(nogil=True, inline="always")(fn)


def cached_kernel(fn):
    """Compiled on first use and cached on disk (a kernel that takes no compiled function;
    also for the loops of ``solvers.verlet_loops``)."""
    return fn if numba is None else numba.njit(nogil=True, cache=True)(fn)


def fast_kernel(fn):
    """``cached_kernel`` with ``fastmath`` reassociation and contraction: a sum in whatever
    order LLVM vectorises it, with fused multiply-adds (``linalg.row_runs``, ``linalg.bond_sums``)."""
    return fn if numba is None else numba.njit(nogil=True, cache=True, fastmath={"reassoc", "contract"})(fn)


# (y, |y|, eta . (y + xi)) of bond b from particle p to q (e = that / (|y| + |xi|)), y a
# tuple: the components written out, which the compiler keeps in registers (a loop over an
# array of them, or a branch on the dimension inside one function, is slower). The kernels
# take one as their first argument and are compiled for it.

@_compiled
def _bond2(u, p, q, xi, length, b):  # pragma: no cover (compiled)
    eta0, eta1 = u[q, 0] - u[p, 0], u[q, 1] - u[p, 1]
    y0, y1 = eta0 + xi[0, b], eta1 + xi[1, b]
    r = np.sqrt(y0 * y0 + y1 * y1)
    return (y0, y1), r, eta0 * (y0 + xi[0, b]) + eta1 * (y1 + xi[1, b])


@_compiled
def _bond3(u, p, q, xi, length, b):  # pragma: no cover (compiled)
    eta0, eta1, eta2 = u[q, 0] - u[p, 0], u[q, 1] - u[p, 1], u[q, 2] - u[p, 2]
    y0, y1, y2 = eta0 + xi[0, b], eta1 + xi[1, b], eta2 + xi[2, b]
    r = np.sqrt(y0 * y0 + y1 * y1 + y2 * y2)
    num = eta0 * (y0 + xi[0, b]) + eta1 * (y1 + xi[1, b]) + eta2 * (y2 + xi[2, b])
    return (y0, y1, y2), r, num


_BOND = {2: _bond2, 3: _bond3}


@_compiled
def _stretch(bond, u, i, j, xi, length, s):  # pragma: no cover (compiled)
    for b in range(i.shape[0]):
        _, r, num = bond(u, i[b], j[b], xi, length, b)
        s[b] = num / (r + length[b]) / length[b]


@_compiled
def _pmb_force(bond, u, i, j, xi, length, k, mu, damaged, b0, b1, lo, f):  # pragma: no cover (compiled)
    for b in range(b0, b1):
        kb = k[b] * mu[b] if damaged else k[b]
        if kb == 0.0:
            continue  # a broken bond: its force is exactly zero
        p, q = i[b], j[b]
        y, r, num = bond(u, p, q, xi, length, b)
        t = kb * num / ((r + length[b]) * r)  # k e / |y|, e = num / (|y| + |xi|): one division
        for a in range(len(y)):
            fb = y[a] * t
            f[p - lo, a] += fb
            f[q - lo, a] -= fb


@cached_kernel
def _components(i, j, keep, labels):  # pragma: no cover (compiled)
    """Union-find with path halving, each root the lowest vertex of its piece; then the
    labels in vertex order (a root comes before the rest of its piece). The root of the
    first end is kept while consecutive edges share it (edges sorted by their first end:
    one find per vertex instead of one per edge)."""
    parent = np.arange(labels.shape[0])
    first, root = -1, -1
    for b in range(i.shape[0]):
        if not keep[b]:
            continue
        if i[b] != first:
            first = root = i[b]
            while parent[root] != root:
                parent[root] = parent[parent[root]]
                root = parent[root]
        q = j[b]
        while parent[q] != q:
            parent[q] = parent[parent[q]]
            q = parent[q]
        if root < q:
            parent[q] = root
        elif q < root:
            parent[root] = q
            root = q
    count = 0
    for p in range(labels.shape[0]):
        r = p
        while parent[r] != r:
            r = parent[r]
        if r == p:
            labels[p] = count
            count += 1
        else:
            labels[p] = labels[r]
    return count


@_compiled
def _tangent_change(bond, u0, u1, i, j, xi, length, k, bonds, mu0, mu1, local, rows, cols, values):  # pragma: no cover
    d, n = u1.shape[1], 0
    for t in range(bonds.shape[0]):
        b = bonds[t]
        p, q = i[b], j[b]
        y0, r0, _ = bond(u0, p, q, xi, length, b)
        y1, r1, _ = bond(u1, p, q, xi, length, b)
        c0, c1 = max(1.0 - length[b] / r0, 0.0), max(1.0 - length[b] / r1, 0.0)
        w0, w1 = k[b] * mu0[b], k[b] * mu1[b]
        for a in range(d):
            for e in range(d):
                h = (w1 * ((1.0 - c1) * (y1[a] / r1) * (y1[e] / r1) + (c1 if a == e else 0.0))
                     - w0 * ((1.0 - c0) * (y0[a] / r0) * (y0[e] / r0) + (c0 if a == e else 0.0)))
                for block in range(4):  # ii, jj: +H; ij, ji: -H
                    row = local[d * (p if block in (0, 2) else q) + a]
                    col = local[d * (p if block in (0, 3) else q) + e]
                    if row >= 0 and col >= 0:
                        rows[n], cols[n], values[n] = row, col, (h if block < 2 else -h)
                        n += 1
    return n


@cached_kernel
def _tally(intact, operated, broken, now):  # pragma: no cover (compiled)
    moved, count, differs = 0.0, 0, False
    for b in range(intact.shape[0]):
        moved = max(moved, abs(intact[b] - operated[b]))
        now[b] = intact[b] < 0.5
        count += now[b]
        differs |= now[b] != broken[b]
    return moved, count, differs


@cached_kernel
def _damage_sums(i, j, w, mu, V, out):  # pragma: no cover (compiled)
    for ends, others in ((i, j), (j, i)):
        for b in range(mu.shape[0]):
            if mu[b] < 1.0:
                out[ends[b]] += w[b] * (1.0 - mu[b]) * V[others[b]]
