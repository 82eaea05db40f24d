"""K_b = sum_t A_t^T diag(w_t) A_t over the two-particle rows, assembled by compiled loops (numba,
where installed) straight into its CSR on the free dofs: the AMG path's bond operator
(``bayespd.linalg.amg.pair_operator``).

scipy forms it as a sparse product after restricting and transposing each A_t, several copies
of the bond operator's entries (at 160k particles, m = 2: 6.4 M entries each) and a product whose
output is faulted in afresh; here one pass over the rows writes each bond's four b x b blocks,

    (p, p) += w a a^T,   (p, q) += w a c^T,   (q, p) += w c a^T,   (q, q) += w c c^T,

a and c the row's data on its particles p and q, into a pattern built once from the pairs (the
particles' neighbour lists, each sorted, the particle itself included: every diagonal block is
in it, as in the product). Entries at constrained dofs are left out, so the rows and columns
are the free dofs, in their order, with sorted indices; entries that sum to exactly 0 are
dropped, as scipy's product drops them (an axis-aligned bond's n n^T has three: at 160k
particles, m = 2, they would add 40 % to the entries every smoothing sweep reads). Each entry is
summed over the bonds in row order, where scipy's product sums in another: the two agree to
rounding (tested).
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from bayespd.bond_loops import numba


class PairPattern:
    """K_b's pattern on the free dofs for the two-particle ``rows`` of each term's gram (the
    particles' neighbour lists, the row layout and the column indices before exact zeros are
    dropped): what depends on the pairs alone, built once and kept while only the weights
    change (``Assembly.amg``)."""

    def __init__(self, terms, free_index: np.ndarray, n_dofs: int):
        self.block = terms[0][0].block
        self.pairs = [_pair_rows(g, rows) for g, _, _, rows in terms]
        nodes = n_dofs // self.block
        self.neighbour_ptr, self.neighbours = _neighbours(np.concatenate([p for p, _ in self.pairs]),
                                                          np.concatenate([q for _, q in self.pairs]), nodes)
        self.rank = np.full(n_dofs, -1, dtype=np.int64)
        self.rank[free_index] = np.arange(len(free_index))
        self.size = len(free_index)
        self.indptr, self.offsets = _free_rows(self.neighbour_ptr, self.neighbours, self.rank, self.block)
        self.index = np.int32 if self.indptr[-1] < 2**31 - 1 else np.int64
        self.indices = np.empty(self.indptr[-1], dtype=self.index)
        _free_columns(self.neighbour_ptr, self.neighbours, self.rank, self.block, self.indptr, self.indices)

    def assemble(self, terms) -> sp.csr_matrix:
        """K_b of ``terms`` (the rows this pattern was built for, any weights): one pass over
        the rows writing each one's four blocks, then the exact zeros dropped."""
        data = np.zeros(len(self.indices))
        for (g, d, w, rows), (p, q) in zip(terms, self.pairs):
            _, ptr = g.block_parts()
            values = g.ordered(np.asarray(d, dtype=np.float64)).reshape(-1, self.block)
            _scatter(p, q, values, ptr[rows], np.asarray(w, dtype=np.float64)[rows], self.neighbour_ptr,
                     self.neighbours, self.offsets, self.rank, self.indptr, data)
        indptr, indices, data = _without_zeros(self.indptr, self.indices.copy(), data)
        K = sp.csr_matrix((data, indices, indptr.astype(self.index)), shape=(self.size,) * 2)
        K.has_sorted_indices = True
        return K


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

    @numba.njit(cache=True)
    def _free_rows(neighbour_ptr, neighbours, rank, block):  # pragma: no cover - compiled
        """(indptr, offsets) of K_b's CSR on the free dofs (``rank``: a dof's free index, -1 for
        a constrained one): every free dof of a particle has the same row layout, the free dofs
        of its neighbours in order; ``offsets[k]``: where neighbour k's dofs start in such a row."""
        nodes = len(neighbour_ptr) - 1
        free = np.zeros(nodes, dtype=np.int64)
        for i in range(nodes):
            for a in range(block):
                if rank[i * block + a] >= 0:
                    free[i] += 1
        offsets = np.empty(len(neighbours), dtype=np.int64)
        indptr = np.zeros(free.sum() + 1, dtype=np.int64)
        for i in range(nodes):
            width = 0
            for k in range(neighbour_ptr[i], neighbour_ptr[i + 1]):
                offsets[k] = width
                width += free[neighbours[k]]
            for a in range(block):
                if rank[i * block + a] >= 0:
                    indptr[rank[i * block + a] + 1] = width
        for r in range(len(indptr) - 1):
            indptr[r + 1] += indptr[r]
        return indptr, offsets

    @numba.njit(cache=True)
    def _free_columns(neighbour_ptr, neighbours, rank, block, indptr, indices):  # pragma: no cover - compiled
        """Fill ``indices`` of the rows ``_free_rows`` laid out."""
        for i in range(len(neighbour_ptr) - 1):
            for a in range(block):
                row = rank[i * block + a]
                if row < 0:
                    continue
                n = indptr[row]
                for k in range(neighbour_ptr[i], neighbour_ptr[i + 1]):
                    for c in range(block):
                        col = rank[neighbours[k] * block + c]
                        if col >= 0:
                            indices[n] = col
                            n += 1

    @numba.njit(cache=True, inline="always")
    def _where(neighbour_ptr, neighbours, i, j):  # pragma: no cover - compiled
        """The position k of neighbour j in particle i's sorted list."""
        lo, hi = neighbour_ptr[i], neighbour_ptr[i + 1]
        while hi - lo > 1:
            mid = (lo + hi) // 2
            if neighbours[mid] <= j:
                lo = mid
            else:
                hi = mid
        return lo

    @numba.njit(cache=True, inline="always")
    def _add_block(data, indptr, rank, offsets, block, i, k, j, left, right, w):  # pragma: no cover - compiled
        """data[(i, a), (j, c)] += w left[a] right[c] over the free dofs of i and j, neighbour k
        of i being j."""
        for a in range(block):
            row = rank[i * block + a]
            if row < 0:
                continue
            n = indptr[row] + offsets[k]
            for c in range(block):
                if rank[j * block + c] >= 0:
                    data[n] += w * left[a] * right[c]
                    n += 1

    @numba.njit(cache=True)
    def _scatter(p, q, values, first, w, neighbour_ptr, neighbours, offsets, rank, indptr, data):  # pragma: no cover - compiled
        """Add each row's four blocks (module docstring); row r's data on p is values[first[r]],
        on q values[first[r] + 1]."""
        block = values.shape[1]
        for r in range(len(p)):
            i, j = p[r], q[r]
            a, c = values[first[r]], values[first[r] + 1]
            _add_block(data, indptr, rank, offsets, block, i, _where(neighbour_ptr, neighbours, i, i), i, a, a, w[r])
            _add_block(data, indptr, rank, offsets, block, i, _where(neighbour_ptr, neighbours, i, j), j, a, c, w[r])
            _add_block(data, indptr, rank, offsets, block, j, _where(neighbour_ptr, neighbours, j, i), i, c, a, w[r])
            _add_block(data, indptr, rank, offsets, block, j, _where(neighbour_ptr, neighbours, j, j), j, c, c, w[r])

    @numba.njit(cache=True)
    def _without_zeros(indptr, indices, data):  # pragma: no cover - compiled
        """The CSR arrays without the entries equal to 0 (compacted in place; the data copied)."""
        keep = 0
        out_ptr = np.zeros(len(indptr), dtype=np.int64)
        for r in range(len(indptr) - 1):
            for k in range(indptr[r], indptr[r + 1]):
                if data[k] != 0.0:
                    indices[keep], data[keep] = indices[k], data[k]
                    keep += 1
            out_ptr[r + 1] = keep
        return out_ptr, indices[:keep], data[:keep].copy()
