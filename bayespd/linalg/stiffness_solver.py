"""Factorisations of a Gram-sum stiffness on the free dofs: direct (CHOLMOD / SuperLU on the
assembled K_ff) or matrix-free preconditioned conjugate gradients (K never assembled), behind
one ``Factor`` interface. See ``Assembly`` and benchmarks/README.md for when each wins.
"""
from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from functools import cached_property

import numpy as np
import scipy.sparse as sp
import torch

from bayespd.linalg import row_runs
from bayespd.linalg.amg import amg_preconditioner, pair_operator, pair_pattern, pair_rows
from bayespd.linalg.assembly import Gram, numeric_values, to_numpy, union_pattern
from bayespd.linalg.config import current_settings
from bayespd.linalg.row_runs import RowRuns
from bayespd.linalg.sparse import (NotPositiveDefiniteError, Pattern, PCGFactor, blas_threads, cholmod,
                            default_backend)


class Assembly:
    """Factorisations of K = sum_t A_t^T diag(w_t) A_t restricted to the free dofs.

    ``Assembly(grams, free)`` caches what does not change with the parameters (pattern, its
    free-dof restriction, symbolic analysis); ``factorize(terms, method)`` returns a
    ``Factor`` of K_ff for the (gram, data, w) triples of one parameter value.

    * ``method="direct"``: K's values on the union pattern (``numeric_values``), restricted,
      factorised by ``Pattern.factorize`` (CHOLMOD or SuperLU).
    * ``method="pcg"``: K is never assembled. Conjugate gradients with the matrix-free product
      sum_t A_t^T (w_t (A_t x)) (scipy CSR, O(entries of A) per product), preconditioned by a
      Cholesky factor of the graph Laplacian of the two-particle rows (the bonds) with
      non-negative weights, one copy per displacement component. ``precondition_rows`` maps a
      Gram to a boolean mask of the rows (bonds) the preconditioner keeps: keeping only the
      nearest bonds (|xi| <= 1.5 h) gives a factor much cheaper than K's at the price of more
      iterations (benchmarks/README.md). Converges to ``rtol`` or raises ``ConvergenceError``.
    * ``method="amg"``: the same matrix-free PCG preconditioned by a smoothed-aggregation
      V-cycle on the bond part of K with the rigid-body modes of ``positions`` (N, dim) as
      near-null space (``bayespd.linalg.amg``): no factorisation, nothing from CHOLMOD. The
      hierarchy and K_b are kept and reused while K_b only changes by a factor (``amg``).
    """

    def __init__(self, grams: list[Gram], free: np.ndarray | None = None,
                 pattern: Pattern | None = None):
        self.grams = list(grams)
        self.n = self.grams[0].shape[1]
        self.free = np.ones(self.n, dtype=bool) if free is None else np.asarray(free, dtype=bool)
        if self.free.shape != (self.n,):
            raise ValueError(f"free must be a boolean mask of the {self.n} dofs")
        self.free_index = np.flatnonzero(self.free)
        row_runs.warm_up()  # numba's start-up on a free core while the caller makes its terms
        self._given_pattern = pattern
        self._kept, self.amg_builds = None, 0  # the latest K_b and AMG hierarchy (``amg``)
        self.reuse_hierarchy = True  # a kept hierarchy may serve new weights (``amg``)

    @cached_property
    def pattern(self) -> Pattern:
        return self._given_pattern if self._given_pattern is not None else union_pattern(self.grams)

    @cached_property
    def _restricted(self):
        if self.free.all():
            return self.pattern, None
        return self.pattern.restrict(self.free)

    @property
    def free_pattern(self) -> Pattern:
        return self._restricted[0]

    def values(self, terms) -> torch.Tensor:
        """K_ff's values on ``free_pattern``."""
        values = numeric_values(self.pattern, terms)
        entries = self._restricted[1]
        return values if entries is None else values[torch.as_tensor(entries)]

    def factorize(self, terms, method: str = "direct", backend: str | None = None,
                  rtol: float = 1e-10, maxiter: int | None = None, precondition_rows=None,
                  positions: np.ndarray | None = None):
        if method == "direct":
            return self.free_pattern.factorize(self.values(terms), backend)
        if method not in ("pcg", "amg"):
            raise ValueError(f"unknown method {method!r}: use 'direct', 'pcg' or 'amg'")
        terms = [(g, to_numpy(d), to_numpy(w)) for g, d, w in terms]
        if method == "pcg":
            precondition = self.laplacian_preconditioner(terms, precondition_rows, backend)
        elif positions is None:
            raise ValueError("method='amg' needs the particles' positions (N, dim) for the "
                             "rigid-body modes: pass positions=particles.x")
        else:
            pair, precondition = self.amg(terms, positions)
            kept = self._kept
            renew = (kept.limit(), self._rebuild(kept, terms, positions)) if kept.base is not None else None
            return PCGFactor(self.operator(terms, pair=pair), precondition, len(self.free_index),
                             rtol=rtol, maxiter=maxiter, log=kept.iterations, renew=renew)
        return PCGFactor(self.operator(terms), precondition, len(self.free_index),
                         rtol=rtol, maxiter=maxiter)

    def amg(self, terms, positions: np.ndarray):
        """(K_b, V-cycle) of ``terms``. When the operators of K_b's rows (``pair_rows``) hold
        the data of the kept K_b and their weights are c > 0 times the kept ones (to 1e-13
        relative each: only moduli changed, e.g. a homogeneous shear modulus; LPS's bulk
        modulus is not in K_b), K_b is the kept one times c, not reassembled, and the kept
        hierarchy is reused divided by c: smoothed aggregation is scale-invariant
        (V-cycle(c A) = V-cycle(A) / c). When only the weights changed otherwise (a new
        horizon or a modulus field) and ``reuse_hierarchy`` is on, K_b is assembled anew and
        the kept hierarchy smooths on it (``VCycle.with_finest``): at 40k particles, m = 3, a
        hierarchy built at delta = 2h took 16-17 iterations for delta from 2h to 3h where a
        fresh one took 16-20 (benchmarks/README.md, issue 31, seventh pass), and the set-up is
        saved. Its solves may take ``REUSE_SLACK`` times the iterations of the solves of the
        K_b it was built for, plus one (``_KeptPair.limit``): a solve that reaches that builds
        the hierarchy anew and goes on with it (``PCGFactor``'s renew; a modulus field 10x
        steeper than the kept one's took 28 iterations against 13), and the reuse is then
        switched off for this Assembly. Otherwise (new positions, operators or rows, no solve
        yet) both are built anew; ``amg_builds`` counts the builds. K_b's pattern
        (``amg.pair_pattern``) is kept with the hierarchy: a new K_b of the same rows only sums
        its values."""
        positions = np.asarray(positions, dtype=np.float64)
        kept, previous = _KeptPair(terms, positions), self._kept
        c = kept.scale(previous) if previous is not None else None
        if c is not None:
            K, cycle = previous.K, previous.cycle
            if c == 1.0:
                return K, cycle
            return (sp.csr_matrix((c * K.data, K.indices, K.indptr), shape=K.shape, copy=False),
                    lambda r: cycle(r) / c)
        self._kept = None
        if previous is not None and not (self.reuse_hierarchy and previous.serves(kept)):
            previous = None  # not kept alive beside the new one (peak memory)
        kept.positions = positions.copy()  # the caller's array may change in place
        kept.pattern = previous.pattern if previous is not None else pair_pattern(terms, self.free_index)
        kept.K = pair_operator(terms, self.free_index, kept.pattern)
        kept.cycle = previous.cycle.with_finest(kept.K) if previous is not None else None
        if kept.cycle is None:
            kept.cycle = amg_preconditioner(terms, self.free_index, positions, pair=kept.K)
            self.amg_builds += 1
        else:
            kept.base = previous.first_iterations()
        self._kept = kept
        return kept.K, kept.cycle

    def _rebuild(self, kept: "_KeptPair", terms, positions):
        """make() for ``PCGFactor``'s renew: the hierarchy built for ``kept``'s K_b in place of
        the reused one; the reuse is switched off (these operators move too far between calls)."""
        def make():
            kept.cycle = amg_preconditioner(terms, self.free_index, positions, pair=kept.K)
            kept.base = None
            self.amg_builds += 1
            self.reuse_hierarchy = False
            return kept.cycle

        return make

    def operator(self, terms, threads: int | None = None, pair: sp.csr_matrix | None = None):
        """x -> K_ff x matrix-free (numpy, x of shape (n_free,) or (n_free, k)).

        The operators are stacked into one CSR matrix C (rows: bonds, then particles, ...)
        with weights W, K = C^T W C (plus the factored terms, ``_factored``), split into
        ``threads`` row blocks of equal size that are applied in parallel (scipy's sparse
        products release the GIL; default: the settings' ``matvec_threads``, None there
        meaning all cores). ``pair``: K_b of these terms
        (``amg.pair_operator``, assembled for the AMG anyway); on one thread the product is
        then K_b x plus the other rows' C_r^T (W_r (C_r x)), each a CSR product on the free
        dofs (``_split_operator``: 2-3x faster than the stacked C and its transpose)."""
        threads = max(1, int(threads or current_settings().matvec_threads or os.cpu_count() or 1))
        if pair is not None and threads == 1:
            return self._split_operator(terms, pair)
        factored = self._factored(terms)
        terms = [t for t in terms if not t[0].factored]
        C = sp.vstack([g.operator(to_numpy(d)) for g, d, _ in terms], format="csr")
        W = np.concatenate([np.asarray(to_numpy(w), dtype=np.float64) for _, _, w in terms])
        cuts = np.searchsorted(C.indptr, np.linspace(0, C.nnz, threads + 1)[1:-1])
        bounds = [0, *cuts.tolist(), C.shape[0]]
        parts = [(C[a:b], W[a:b]) for a, b in zip(bounds[:-1], bounds[1:]) if b > a]
        idx, n = self.free_index, self.n
        pool = _pool(len(parts)) if len(parts) > 1 else None

        def part(Ci, Wi, full):
            return Ci.T @ (Wi.reshape(-1, *([1] * (full.ndim - 1))) * (Ci @ full))

        def matvec(x):
            full = np.zeros((n,) + x.shape[1:])
            full[idx] = x
            if pool is None:
                y = part(*parts[0], full)
            else:
                futures = [pool.submit(part, Ci, Wi, full) for Ci, Wi in parts[1:]]
                y = part(*parts[0], full)
                for f in futures:
                    y += f.result()
            return factored(x, y[idx])

        return matvec

    def _factored(self, terms, bond_term=None):
        """(x, y) -> y + sum A^T (w A x) over the factored terms (``BondSums``: the LPS
        dilatation), each by its own ``normal_product`` on the free dofs; ``bond_term``: the
        (B, data, k) term of the bonds a factored term sums, applied in its passes."""
        products = [g.normal_product(d, w, self.free_index,
                                     bond_term[2] if bond_term is not None and bond_term[0] is g.bonds else None)
                    for g, d, w in terms if g.factored]

        def add(x, y):
            for normal in products:
                y += normal(x) if x.ndim == 1 else np.stack([normal(c) for c in x.T], axis=1)
            return y

        return add

    def _split_operator(self, terms, pair: sp.csr_matrix):
        """x -> K_b x + C_r^T (W_r (C_r x)) + sum A^T (w A x): K_b = ``pair`` (the
        ``amg.pair_rows`` of every term), C_r the remaining rows of the Grams (multi-particle
        rows, negative weights) on the free columns, its transpose stored as CSR (a gather, not
        a scatter), each product in runs of rows on two threads where numba is installed
        (``row_runs``); the factored terms by ``_factored``."""
        fused = _fused_bond_term(terms)
        if fused is not None:  # K = B^T diag(k) B + the factored terms: all in their passes, K_b unused
            factored = self._factored(terms, fused)
            return lambda x: factored(x, np.zeros_like(x))
        rest, factored = [], self._factored(terms)
        for g, d, w in terms:
            if g.factored:
                continue
            w = np.asarray(to_numpy(w), dtype=np.float64)
            keep = np.ones(g.shape[0], dtype=bool)
            keep[pair_rows(g, w)] = False
            if keep.any():
                rows = np.flatnonzero(keep)
                A = g.operator(to_numpy(d))
                rest.append(((A[rows] if len(rows) < A.shape[0] else A)[:, self.free_index], w[rows]))
        C = (rest[0][0] if len(rest) == 1 else sp.vstack([A for A, _ in rest], format="csr")) if rest else None
        CT = C.T.tocsr() if rest else None
        W = np.concatenate([w for _, w in rest]) if rest else None

        product = (lambda M: RowRuns(M).product) if row_runs.usable() else (lambda M: M.__matmul__)
        K_b = product(pair)
        C_x, CT_x = (product(C), product(CT)) if rest else (None, None)

        def matvec(x):
            y = K_b(x)
            if C is not None:
                y += CT_x(W.reshape(-1, *([1] * (x.ndim - 1))) * C_x(x))
            return factored(x, y)

        return matvec

    def laplacian_preconditioner(self, terms, rows=None, backend=None):
        """r -> P^-1 r with P = (L kron I_b) on the free dofs, L the weighted graph Laplacian
        of the rows of A that touch two particles (weight w_r |a_r|^2 / (2 b))."""
        b = self.grams[0].block
        if b == 1 or not all(g.block == b for g, _, _ in terms):
            raise ValueError("the PCG preconditioner needs operators on whole particles (blocks)")
        nodes = self.n // b
        pi, pj, pw = [], [], []
        for g, d, w in terms:
            two = g.two_block_rows
            if rows is not None and g in rows:
                two = two[np.asarray(rows[g], dtype=bool)[two]]
            if len(two) == 0:
                continue
            ind, ptr = g.block_parts()
            blocks = g.ordered(np.asarray(d, dtype=np.float64)).reshape(-1, b)
            strength = 0.5 * (blocks[ptr[two]] ** 2 + blocks[ptr[two] + 1] ** 2).sum(axis=1) / b
            weight = np.maximum(np.asarray(w, dtype=np.float64)[two], 0.0) * strength
            pi.append(ind[ptr[two]]), pj.append(ind[ptr[two] + 1]), pw.append(weight)
        if not pi:
            raise ValueError("no two-particle rows (bonds) to build the PCG preconditioner from")
        i, j, w = np.concatenate(pi), np.concatenate(pj), np.concatenate(pw)
        L = sp.coo_matrix((np.concatenate([-w, -w, w, w]),
                           (np.concatenate([i, j, i, j]), np.concatenate([j, i, i, j]))),
                          shape=(nodes, nodes)).tocsc()
        free = self.free.reshape(nodes, b)
        groups = {}  # components with the same free particles share one factor
        for c in range(b):
            groups.setdefault(free[:, c].tobytes(), []).append(c)
        solvers = []
        for key, comps in groups.items():
            mask = free[:, comps[0]]
            solvers.append((mask, comps, _spd_factor(L[mask][:, mask], backend)))
        idx, n = self.free_index, self.n

        def precondition(r):
            full = np.zeros((n,) + r.shape[1:])
            full[idx] = r
            R = full.reshape((nodes, b) + r.shape[1:])
            Z = np.zeros_like(R)
            for mask, comps, solve in solvers:
                block = R[mask][:, comps]
                Z[np.ix_(mask, comps)] = solve(block.reshape(len(block), -1)).reshape(block.shape)
            return Z.reshape((n,) + r.shape[1:])[idx]

        return precondition


def _fused_bond_term(terms):
    """The (B, data, k) term that a factored term's passes can apply (``BondSums.normal_product``
    with ``bond_weights``) when K is that term and factored terms over the same B alone, with
    k >= 0 (so that it is the whole of K_b): LPS without a negative bond weight; else None."""
    explicit = [t for t in terms if not t[0].factored]
    factored = [g for g, _, _ in terms if g.factored]
    if len(explicit) != 1 or not factored or any(g.bonds is not explicit[0][0] for g in factored):
        return None
    g, d, w = explicit[0]
    w = np.asarray(to_numpy(w))
    return explicit[0] if len(g.two_block_rows) == g.shape[0] and bool((w >= 0).all()) else None


REUSE_SLACK = 1.25  # a kept hierarchy serves while a solve takes at most this x those it was built for (+1)


class _KeptPair:
    """What K_b was assembled from: the data and pair-row weights of the terms that have
    pair rows, and the positions of the rigid-body modes; ``K``, its ``pattern`` and ``cycle``,
    ``iterations`` of the solves made with them, ``base``: ``first_iterations`` of the K_b the
    hierarchy was built for, when that was an earlier one."""

    def __init__(self, terms, positions: np.ndarray):
        self.positions, self.K, self.cycle, self.pattern = positions, None, None, None
        self.iterations, self.base = [], None
        self.parts = []
        for g, d, w in terms:
            w = np.asarray(w, dtype=np.float64)
            rows = pair_rows(g, w)
            if len(rows):
                self.parts.append((g, np.asarray(d), rows, w[rows]))

    def same_structure(self, kept: "_KeptPair") -> bool:
        """The same operators, data, rows and positions as ``kept`` (the weights may differ)."""
        if len(self.parts) != len(kept.parts) or not self.parts or not np.array_equal(
                self.positions, kept.positions):
            return False
        return all(g is g0 and (_same_buffer(d, d0) or np.array_equal(d, d0)) and np.array_equal(rows, rows0)
                   for (g, d, rows, _), (g0, d0, rows0, _) in zip(self.parts, kept.parts))

    def first_iterations(self) -> int | None:
        """The most iterations a solve took with the K_b the hierarchy was built for (forward
        and adjoint: their right-hand sides differ; None: none yet)."""
        return self.base if self.base is not None else max(self.iterations, default=None)

    def limit(self) -> int:
        """The iterations a solve with a reused hierarchy may take: ``REUSE_SLACK`` x
        ``first_iterations``, plus one."""
        return int(REUSE_SLACK * self.first_iterations()) + 1

    def serves(self, new: "_KeptPair") -> bool:
        """Whether this hierarchy may smooth on ``new``'s K_b: the same structure, a first solve
        to measure it by, and no solve of this K_b beyond ``limit``."""
        return (new.same_structure(self) and self.first_iterations() is not None
                and max(self.iterations, default=0) <= self.limit())

    def scale(self, kept: "_KeptPair") -> float | None:
        """c > 0 with these weights = c x ``kept``'s (to 1e-13 relative each), the same
        operators, data, rows and positions; else None."""
        if not self.same_structure(kept):
            return None
        w0 = kept.parts[0][3]
        k = int(np.argmax(np.abs(w0)))
        c = float(self.parts[0][3][k] / w0[k])
        if not (c > 0 and np.isfinite(c)):
            return None
        for (*_, w), (*_, w0) in zip(self.parts, kept.parts):
            if not np.all(np.abs(w - c * w0) <= 1e-13 * np.abs(w)):
                return None
        return c


def _same_buffer(a: np.ndarray, b: np.ndarray) -> bool:
    """a and b view the same memory alike (b is kept alive, so its buffer is not reused; an
    operator's data, e.g. a material's bond directions, are never written in place)."""
    return (a.shape == b.shape and a.dtype == b.dtype and a.strides == b.strides
            and a.__array_interface__["data"][0] == b.__array_interface__["data"][0])


_POOLS: dict = {}


def _pool(n: int) -> ThreadPoolExecutor:
    if n not in _POOLS:
        _POOLS[n] = ThreadPoolExecutor(max_workers=n - 1, thread_name_prefix="bayespd-matvec")
    return _POOLS[n]


_NOT_SPD = (NotPositiveDefiniteError,) + (
    (cholmod.CholmodNotPositiveDefiniteError,) if cholmod is not None else ())


def _spd_factor(L: sp.csc_matrix, backend=None):
    """solve(B) with L (plus a tiny diagonal shift, so that a free cluster without a
    constrained particle still gives an SPD preconditioner)."""
    diag = L.diagonal()
    scale = float(diag[diag > 0].mean()) if np.any(diag > 0) else 1.0
    for eps in (1e-12, 1e-6):
        shift = np.where(diag > 0, eps * scale, scale)
        A = (L + sp.diags(shift)).tocsc()
        A.sort_indices()
        backend = backend or default_backend()
        try:
            if backend == "cholmod":
                with blas_threads(None):
                    f = cholmod.cholesky(A, mode="supernodal", ordering_method="amd")
                return f.solve_A
            pattern = Pattern(A.indices.astype(np.int64),
                              np.repeat(np.arange(A.shape[0]), np.diff(A.indptr)), A.shape[0])
            return pattern.factorize(torch.as_tensor(A.data), backend).solve
        except _NOT_SPD:
            continue
    raise NotPositiveDefiniteError("the PCG preconditioner (bond-graph Laplacian) is singular")
