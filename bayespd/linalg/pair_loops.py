"""K_b = sum_t A_t^T diag(w_t) A_t over the two-particle rows, assembled by compiled loops (numba,
where installed) straight into its CSR on the free dofs: the AMG path's bond operator
(``bayespd.linalg.amg.pair_operator``).

scipy forms it as a sparse product after restricting and transposing each A_t, several copies
of the bond operator's entries (at 160k particles, m = 2: 6.4 M entries each) and a product whose
output is faulted in afresh. Here each particle's rows of K_b are summed from the bond rows that
touch it (its incidences, in row order) into one b x b block per neighbour,

    (p, p) += w a a^T,   (p, q) += w a c^T      (and at q: (q, q) += w c c^T, (q, p) += w c a^T),

a and c the row's data on its particles p and q, and written out once without the entries that
sum to exactly 0, as scipy's product drops them (an axis-aligned bond's n n^T has three: at 160k
particles, m = 2, they would add 40 % to the entries every smoothing sweep reads). The particles
are cut into runs, each counted, then written into its place in K_b's arrays, by a compiled loop
on two threads (``bond_loops.claimed``): K_b's entries are written once, where a scatter over the
bond rows into the whole pattern wrote (and faulted in) a zeroed buffer 1.4x K_b's size and
copied it twice to drop the zeros. The pattern (each particle's neighbours, sorted, itself
included, and each incidence's place among them) depends on the pairs alone and is built once.
Each entry is summed over the bonds in row order, where scipy's product sums in another: the two
agree to rounding (tested); the runs and threads change no bit.
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import torch

from bayespd import bond_loops
from bayespd.bond_loops import numba

RUNS = 8  # runs of particles (fixed: the result does not depend on the thread count)
MIN_INCIDENCES = 1 << 15  # bond ends per run below which the particles are one run


class PairPattern:
    """K_b's pattern on the free dofs for the two-particle ``rows`` of each term's gram: the
    particles' neighbour lists and incidences, and the runs of particles: what depends on the
    pairs alone, built once and kept while only the weights change (``Assembly.amg``)."""

    def __init__(self, terms, free_index: np.ndarray, n_dofs: int):
        self.block = b = terms[0][0].block
        free_index = np.asarray(free_index, dtype=np.int64)
        if np.any(np.diff(free_index) <= 0):
            raise ValueError("free_index must be increasing (np.flatnonzero of the free-dof mask)")
        pairs = [_pair_rows(g, rows) for g, _, _, rows in terms]
        p, q = np.concatenate([p for p, _ in pairs]), np.concatenate([q for _, q in pairs])
        nodes = n_dofs // b
        self.neighbour_ptr, self.neighbours = _neighbours(p, q, nodes)
        self.incidence_ptr, self.incidence, self.slot = _incidences(p, q, self.neighbour_ptr, self.neighbours)
        self.rank = np.full(n_dofs, -1, dtype=np.int64)
        self.rank[free_index] = np.arange(len(free_index))
        self.size = len(free_index)
        self.index = np.int32 if b * b * len(self.neighbours) < 2**31 - 1 else np.int64
        count = max(1, min(RUNS, int(self.incidence_ptr[-1]) // MIN_INCIDENCES))
        cuts = np.searchsorted(self.incidence_ptr, self.incidence_ptr[-1] * np.arange(1, count) // count)
        cuts = np.unique(np.concatenate([[0], cuts, [nodes]]))
        first_row = np.searchsorted(free_index, cuts * b)  # the free rows of particles [lo, hi): [first_row[lo], ...)
        self.runs = [(int(lo), int(hi), int(r0), int(r1))
                     for lo, hi, r0, r1 in zip(cuts[:-1], cuts[1:], first_row[:-1], first_row[1:])]

    def assemble(self, terms) -> sp.csr_matrix:
        """K_b of ``terms`` (the rows this pattern was built for, any weights)."""
        values, first, w = self._rows(terms)
        shared = (self.incidence_ptr, self.incidence, self.slot, self.neighbour_ptr, self.neighbours, self.rank,
                  values, first, w)

        def count(t):
            lo, hi, r0, r1 = self.runs[t]
            counts = np.empty(r1 - r0, dtype=np.int64)
            return counts, _sum_rows(*shared, lo, hi, r0, counts, np.empty(0, dtype=self.index), np.empty(0), False)

        threads = torch.get_num_threads() if len(self.runs) > 1 else 1
        counts = bond_loops.claimed(count, len(self.runs), threads)
        indptr = np.zeros(self.size + 1, dtype=self.index)
        np.cumsum(np.concatenate([c for c, _ in counts]), out=indptr[1:])
        indices, data = np.empty(indptr[-1], dtype=self.index), np.empty(indptr[-1])
        ends = np.cumsum([0] + [n for _, n in counts])

        def write(t):
            lo, hi, r0, _ = self.runs[t]
            part = slice(ends[t], ends[t + 1])
            _sum_rows(*shared, lo, hi, r0, counts[t][0], indices[part], data[part], True)

        bond_loops.claimed(write, len(self.runs), threads, redo=False)  # into K_b's arrays: each run once
        K = sp.csr_matrix((data, indices, indptr), shape=(self.size,) * 2)
        K.has_sorted_indices = True
        return K

    def _rows(self, terms):
        """(values, first, w): row r's data on its particle p is values[first[r]], on q
        values[first[r] + 1], its weight w[r] (rows in term order); one term's own data, the
        ends of several gathered."""
        parts = []
        for g, d, w, rows in terms:
            _, ptr = g.block_parts()
            parts.append((g.ordered(np.asarray(d, dtype=np.float64)).reshape(-1, self.block), ptr[rows],
                          np.asarray(w, dtype=np.float64)[rows]))
        if len(parts) == 1:
            return parts[0]
        ends = np.concatenate([np.stack([v[f], v[f + 1]], axis=1).reshape(-1, self.block) for v, f, _ in parts])
        return ends, np.arange(0, len(ends), 2), np.concatenate([w for _, _, w in parts])


def pair_operator(terms, free_index: np.ndarray, n_dofs: int, pattern: PairPattern | None = None) -> sp.csr_matrix:
    """K_b on the free dofs (``amg.pair_operator``'s contract) from ``terms`` [(gram, data, w,
    rows)]: the rows of each gram's operator that enter K_b (two particles each), on
    ``pattern`` when given (built for these rows), else on a new one."""
    return (pattern or PairPattern(terms, free_index, n_dofs)).assemble(terms)


def _pair_rows(g, rows) -> tuple[np.ndarray, np.ndarray]:
    """The particles (p, q) of the two-particle ``rows`` of a gram."""
    ind, ptr = g.block_parts()
    return ind[ptr[rows]].astype(np.int64), ind[ptr[rows] + 1].astype(np.int64)


if numba is not None:
    @numba.njit(cache=True)
    def _neighbours(p, q, nodes):  # pragma: no cover - compiled
        """(ptr, neighbours): each particle's neighbours through the pairs, itself included,
        sorted and without repeats."""
        count = np.ones(nodes, dtype=np.int64)
        for r in range(len(p)):
            count[p[r]] += 1
            count[q[r]] += 1
        ptr = np.zeros(nodes + 1, dtype=np.int64)
        ptr[1:] = np.cumsum(count)
        raw = np.empty(ptr[-1], dtype=np.int64)
        fill = ptr[:-1].copy()
        for i in range(nodes):
            raw[fill[i]] = i
            fill[i] += 1
        for r in range(len(p)):
            raw[fill[p[r]]] = q[r]
            fill[p[r]] += 1
            raw[fill[q[r]]] = p[r]
            fill[q[r]] += 1
        out_ptr = np.zeros(nodes + 1, dtype=np.int64)
        n = 0
        for i in range(nodes):
            first = n
            for k in range(ptr[i], ptr[i + 1]):  # insertion into the sorted run raw[first:n], in place
                value, at = raw[k], n
                while at > first and raw[at - 1] > value:
                    at -= 1
                if at > first and raw[at - 1] == value:
                    continue  # a repeat
                for m in range(n, at, -1):
                    raw[m] = raw[m - 1]
                raw[at] = value
                n += 1
            out_ptr[i + 1] = n
        return out_ptr, raw[:n]

    @numba.njit(cache=True, inline="always")
    def _where(neighbour_ptr, neighbours, i, j):  # pragma: no cover - compiled
        """The place of particle j in particle i's sorted neighbour list (from its start)."""
        lo, hi = neighbour_ptr[i], neighbour_ptr[i + 1]
        while hi - lo > 1:
            mid = (lo + hi) // 2
            if neighbours[mid] <= j:
                lo = mid
            else:
                hi = mid
        return lo - neighbour_ptr[i]

    @numba.njit(cache=True)
    def _incidences(p, q, neighbour_ptr, neighbours):  # pragma: no cover - compiled
        """(ptr, incidence, slot): each particle's bond ends in row order, 2 r + end (end 0: the
        particle is the row's p, 1: its q), and the other particle's place among its neighbours."""
        nodes = len(neighbour_ptr) - 1
        ptr = np.zeros(nodes + 1, dtype=np.int64)
        for r in range(len(p)):
            ptr[p[r] + 1] += 1
            ptr[q[r] + 1] += 1
        for i in range(nodes):
            ptr[i + 1] += ptr[i]
        fill = ptr[:-1].copy()
        incidence = np.empty(2 * len(p), dtype=np.int64)
        slot = np.empty(2 * len(p), dtype=np.int32)
        for r in range(len(p)):
            for end, i, j in ((0, p[r], q[r]), (1, q[r], p[r])):
                incidence[fill[i]] = 2 * r + end
                slot[fill[i]] = _where(neighbour_ptr, neighbours, i, j)
                fill[i] += 1
        return ptr, incidence, slot

    @numba.njit(nogil=True, cache=True)
    def _sum_rows(incidence_ptr, incidence, slot, neighbour_ptr, neighbours, rank, values, first, w,
                  lo, hi, row_lo, counts, indices, data, write):  # pragma: no cover - compiled
        """K_b's rows of the particles [lo, hi) (module docstring): ``counts`` of each free row
        (from ``row_lo``) and, with ``write``, its columns and entries; returns the entries."""
        block = values.shape[1]
        widest = 1
        for i in range(lo, hi):
            widest = max(widest, neighbour_ptr[i + 1] - neighbour_ptr[i])
        blocks = np.empty((widest, block, block))
        n = 0
        for i in range(lo, hi):
            start, width = neighbour_ptr[i], neighbour_ptr[i + 1] - neighbour_ptr[i]
            blocks[:width] = 0.0
            own = _where(neighbour_ptr, neighbours, i, i)
            for e in range(incidence_ptr[i], incidence_ptr[i + 1]):
                r, end, k = incidence[e] >> 1, incidence[e] & 1, slot[e]
                x, y = values[first[r] + end], values[first[r] + 1 - end]
                for a in range(block):
                    for c in range(block):
                        blocks[own, a, c] += w[r] * x[a] * x[c]
                        blocks[k, a, c] += w[r] * x[a] * y[c]
            for a in range(block):
                row = rank[i * block + a]
                if row < 0:
                    continue
                entries = n
                for k in range(width):
                    j = neighbours[start + k]
                    for c in range(block):
                        col = rank[j * block + c]
                        if col >= 0 and blocks[k, a, c] != 0.0:
                            if write:
                                indices[n], data[n] = col, blocks[k, a, c]
                            n += 1
                counts[row - row_lo] = n - entries
        return n
