"""Stiffness assembly as sums of Gram products K = sum_t A_t^T diag(w_t) A_t.

Every linearised PD stiffness has this form: A is a sparse operator of fixed structure
(bond extensions, nodal dilatations) whose entries and weights change with the parameters.
``numeric_values`` assembles numerically with scipy (fast, for factorisation);
``Gram.values`` assembles the same numbers with torch ops on entry pairs (differentiable,
more memory); ``Gram.apply`` is the matrix-free product A x.

Node blocks: an operator's entries often come in blocks of ``b`` dofs (the ``b`` components
of one node's displacement). When every Gram has this block structure, the pattern is built
at node level (b^2 fewer index pairs) and the numeric product is one scipy BSR product of all
terms stacked, ``[A_1; A_2]^T diag(w_1, w_2) [A_1; A_2]``, whose blocks are scattered into the
pattern by an index map kept in the pattern's ``NodeBlocks.maps`` (no search per call). BSR
products keep zero blocks, so the product's structure does not depend on the values and the
map stays valid.
"""
from __future__ import annotations

from functools import cached_property

import numpy as np
import scipy.sparse as sp
import torch

from bayespd.linalg.sparse import NodeBlocks, Pattern

_CHUNK = 1 << 22  # index entries handled at once when expanding node blocks to dofs


def _group_ids(counts: np.ndarray) -> np.ndarray:
    """np.repeat(np.arange(len(counts)), counts), by a cumulative sum (faster than np.repeat
    with an array of counts on large inputs)."""
    counts = np.asarray(counts, dtype=np.int64)
    out = np.zeros(int(counts.sum()), dtype=np.int64)
    ends = np.cumsum(counts)[:-1]
    np.add.at(out, ends[ends < len(out)], 1) if np.any(counts[1:] == 0) else out.__setitem__(ends, 1)
    np.cumsum(out, out=out)
    return out


def _read_only(*arrays) -> tuple:
    """Views of ``arrays`` that refuse writes (shared by every caller)."""
    views = tuple(a.view() for a in arrays)
    for a in views:
        a.flags.writeable = False
    return views


class Gram:
    """K = A^T diag(w) A for A with entries at (rows[k], cols[k]) and data given per call."""

    factored = False  # a ``BondSums`` is: its products skip the explicit operator
    _nodes = None  # a Gram made ``of_blocks``: its rows' nodes, row after row

    def __init__(self, rows: np.ndarray, cols: np.ndarray, n_rows: int, n_cols: int):
        rows = np.asarray(rows, dtype=np.int64)
        cols = np.asarray(cols, dtype=np.int64)
        key = rows * n_cols
        key += cols
        self._identity = len(key) < 2 or bool(np.all(key[1:] >= key[:-1]))
        if self._identity:  # already row-major (the bond operator is): no copies, no order
            self.order = None
            self.rows, self.cols = rows, cols
        else:
            self.order = np.argsort(key, kind="stable")  # = lexsort((cols, rows))
            self.rows, self.cols = rows[self.order], cols[self.order]
        del key
        self.shape = (n_rows, n_cols)
        self.indptr = np.zeros(n_rows + 1, dtype=np.int64)
        np.cumsum(np.bincount(self.rows, minlength=n_rows), out=self.indptr[1:])
        self._order_t = None if self._identity else torch.as_tensor(self.order)
        self._targets = {}  # per ``values``' rows (None: all): (pattern, entry pairs and their positions in it)
        self.block = self._block_size()

    @classmethod
    def of_blocks(cls, nodes: np.ndarray, n_cols: int, block: int) -> "Gram":
        """A whose row r holds one 1 x ``block`` block on each node of ``nodes[r]`` (R, k)
        (dofs block * node + a, a < block): a bond operator (k = 2). When each row's nodes
        increase, A is row-major as given and is built without the constructor's sort and
        checks, its entries' rows made on first use (at 160k particles, m = 2, the bonds' 6.4 M
        entries in 0.05 s against 0.18 s); else by the constructor."""
        nodes = np.asarray(nodes, dtype=np.int64)
        R, k = nodes.shape
        cols = (block * nodes[:, :, None] + np.arange(block)).reshape(-1)
        if k > 1 and not np.all(nodes[:, 1:] > nodes[:, :-1]):
            return cls(np.repeat(np.arange(R), k * block), cols, R, n_cols)
        g = cls.__new__(cls)
        g._identity, g.order, g._order_t, g._targets = True, None, None, {}
        g.cols, g.shape, g.block = cols, (R, n_cols), block
        g.indptr = np.arange(0, R * k * block + 1, k * block, dtype=np.int64)
        g._nodes = torch.as_tensor(nodes.reshape(-1))  # the products gather whole nodes
        g._block_parts = _read_only(nodes.reshape(-1), np.arange(0, R * k + 1, k, dtype=np.int64))  # given
        return g

    @cached_property
    def rows(self) -> np.ndarray:
        return _group_ids(np.diff(self.indptr))

    @cached_property
    def _rows_t(self) -> torch.Tensor:
        return torch.as_tensor(self.rows)

    @cached_property
    def _cols_t(self) -> torch.Tensor:
        return torch.as_tensor(self.cols)

    def _block_size(self) -> int:
        """b such that the entries come in runs (r, b q), ..., (r, b q + b - 1): then A is a
        BSR matrix of 1 x b blocks (one node's dofs); 1 when there is no such b."""
        n = len(self.cols)
        for b in (2, 3):
            if n == 0 or n % b or self.shape[1] % b:
                continue
            first, row = self.cols[0::b], self.rows[0::b]
            if not np.all(first % b == 0):
                continue
            if all(np.array_equal(self.cols[k::b] - first, np.full(len(first), k))
                   and np.array_equal(self.rows[k::b], row) for k in range(1, b)):
                return b
        return 1

    @property
    def explicit(self) -> "Gram":
        """The operator as a Gram: itself (``BondSums`` builds one)."""
        return self

    def explicit_data(self, data):
        return data

    def ordered(self, data) -> np.ndarray:
        """Entries given in the order of construction, in A's row-major order."""
        data = np.asarray(data)
        return data if self._identity else data[self.order]

    @cached_property
    def _csr_index(self):
        dtype = np.int32 if max(self.shape + (len(self.cols),)) < 2**31 - 1 else np.int64
        return self.cols.astype(dtype), self.indptr.astype(dtype)

    def operator(self, data) -> sp.csr_matrix:
        cols, indptr = self._csr_index
        return sp.csr_matrix((self.ordered(data), cols, indptr), shape=self.shape, copy=False)

    def matrix(self, data, w) -> sp.csr_matrix:
        """A^T diag(w) A numerically (data: entries of A in the order given at construction)."""
        A = self.operator(data)
        return (A.T @ sp.diags(np.asarray(w)) @ A).tocsr()

    def structure(self) -> sp.csr_matrix:
        A = self.operator(np.ones(len(self.cols)))
        return (A.T @ A).tocsr()

    @cached_property
    def _pairs(self):
        """All ordered pairs (k1, k2) of entries in the same row of A (sorted entry ids)."""
        size = np.diff(self.indptr)
        reps = np.repeat(size, size)
        k1 = np.repeat(np.arange(len(self.rows)), reps)
        offset = np.arange(len(k1)) - np.repeat(np.cumsum(reps) - reps, reps)
        k2 = self.indptr[self.rows[k1]] + offset
        return k1, k2

    def apply(self, data: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        """A x for a flat vector x (differentiable in data and x); a Gram ``of_blocks`` gathers
        its rows' nodes whole (at 160k particles, m = 2, the bonds' extensions in 50 ms against
        70 ms for the entries' scatter)."""
        if self._nodes is not None:
            b = self.block
            blocks = data.reshape(self.shape[0], -1, b)
            return (blocks * x.reshape(-1, b).index_select(0, self._nodes).reshape(blocks.shape)).sum((1, 2))
        d = data if self._identity else data[self._order_t]
        contrib = d * x[self._cols_t]
        return torch.zeros(self.shape[0], dtype=contrib.dtype).index_add(0, self._rows_t, contrib)

    def apply_transpose(self, data: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        """A^T y for a vector y over A's rows (differentiable in data and y)."""
        if self._nodes is not None:
            b = self.block
            contrib = (data.reshape(self.shape[0], -1, b) * y[:, None, None]).reshape(-1, b)
            return torch.zeros(self.shape[1] // b, b, dtype=contrib.dtype).index_add(0, self._nodes, contrib).reshape(-1)
        d = data if self._identity else data[self._order_t]
        contrib = d * y[self._rows_t]
        return torch.zeros(self.shape[1], dtype=contrib.dtype).index_add(0, self._cols_t, contrib)

    def values(self, data: torch.Tensor, w: torch.Tensor, pattern: Pattern, rows=None) -> torch.Tensor:
        """A^T diag(w) A on ``pattern`` as a differentiable torch expression; with ``rows``
        (some of K's rows), on the pattern's entries in those rows only (``pattern.in_rows``),
        from the entry pairs whose first entry's column is one of them (a periodic lattice's
        symbol needs one node's rows: at 400 nodes, 1/400 of the products)."""
        k1, k2, targets, size = self._pair_targets(pattern, rows)
        d = data if self._identity else data[self._order_t]
        contrib = w[self._rows_t[k1]] * d[k1] * d[k2]
        return torch.zeros(size, dtype=contrib.dtype).index_add(0, targets, contrib)

    def _pair_targets(self, pattern: Pattern, rows):
        """(first entries, second entries, position in ``pattern`` or in its ``in_rows(rows)``)
        of the entry pairs ``values`` sums, and the number of entries it fills; kept per ``rows``
        for the latest pattern."""
        key = None if rows is None else tuple(int(r) for r in rows)
        kept = self._targets.get(key)
        if kept is None or kept[0] is not pattern:
            k1, k2 = self._pairs
            if rows is not None:
                chosen = np.isin(self.cols[k1], key)
                k1, k2 = k1[chosen], k2[chosen]
            position, size = pattern.position(self.cols[k1], self.cols[k2]), pattern.nnz
            if rows is not None:
                entries = pattern.in_rows(rows)
                position, size = np.searchsorted(entries, position), len(entries)
            kept = self._targets[key] = (pattern, *(torch.as_tensor(a) for a in (k1, k2, position)), size)
        return kept[1:]

    # --- node-block (BSR) form, used when self.block > 1 -------------------------------------

    def block_parts(self):
        """(indices, indptr) of A as a BSR matrix of 1 x b blocks (b = self.block); kept, since
        the structure never changes (read-only: every caller shares them)."""
        return self._block_parts

    @cached_property
    def two_block_rows(self) -> np.ndarray:
        """The rows of A that touch two particles (blocks): bonds (read-only, kept)."""
        rows = np.flatnonzero(np.diff(self._block_parts[1]) == 2)
        rows.flags.writeable = False
        return rows

    @cached_property
    def _block_parts(self):
        b = self.block
        return _read_only(self.cols[::b] // b, self.indptr // b)

    def _block_data(self, data, w=None) -> np.ndarray:
        """diag(w) A's entries in row-major order, as (nnz / b, 1, b) blocks."""
        d = self.ordered(np.asarray(data, dtype=np.float64))
        if w is not None:
            d = d * np.repeat(np.asarray(w, dtype=np.float64), np.diff(self.indptr))
        return d.reshape(-1, 1, self.block)


class _Stack:
    """The Gram operators of a list of terms stacked row-wise, plus b identity rows per
    node (weight 0 numerically) so that every diagonal block is in the product."""

    def __init__(self, grams: list[Gram]):
        b = grams[0].block
        self.grams, self.block = list(grams), b
        self.nodes = grams[0].shape[1] // b
        indices, ptrs, offset = [], [], 0
        for g in self.grams:
            ind, ptr = g.block_parts()
            indices.append(ind)
            ptrs.append(ptr[:-1] + offset)
            offset += len(ind)
        indices.append(np.arange(self.nodes))
        ptrs.append(np.arange(self.nodes + 1) + offset)
        self.indices = np.concatenate(indices)
        self.indptr = np.concatenate(ptrs)
        self.n_rows = len(self.indptr) - 1
        self._eye = np.zeros((self.nodes, 1, b))

    def product(self, data_list, w_list) -> sp.bsr_matrix:
        """sum_t A_t^T diag(w_t) A_t as a BSR matrix of b x b blocks (block order of scipy's
        product: fixed by the structure alone)."""
        A = np.concatenate([g._block_data(d) for g, d in zip(self.grams, data_list)] + [self._eye])
        WA = np.concatenate([g._block_data(d, w) for g, d, w in zip(self.grams, data_list, w_list)]
                            + [self._eye])
        shape = (self.n_rows, self.nodes * self.block)
        left = sp.bsr_matrix((A, self.indices, self.indptr), shape=shape).T
        right = sp.bsr_matrix((WA, self.indices, self.indptr), shape=shape)
        return left @ right


def _expand_blocks(node_indptr, node_indices, b):
    """Dof-level CSC pattern (rows, cols) of a symmetric node-level pattern whose every
    entry stands for a full b x b block: column b J + a' holds rows b I + a for the nodes
    I of column J (sorted) and a = 0..b-1, the same rows for every a'."""
    n = len(node_indptr) - 1
    counts = np.diff(node_indptr)
    col_counts = np.repeat(b * counts, b)  # entries per dof column
    col_ptr = np.zeros(n * b + 1, dtype=np.int64)
    np.cumsum(col_counts, out=col_ptr[1:])
    rows = np.empty(col_ptr[-1], dtype=np.int64)
    a = np.arange(b)
    step = max(1, _CHUNK // max(1, b * b * int(counts.max(initial=1))))
    for J0 in range(0, n, step):
        J1 = min(n, J0 + step)
        seg = (b * node_indices[node_indptr[J0]:node_indptr[J1]][:, None] + a).reshape(-1)
        # each dof column (J, a') repeats node column J's rows: gather its segment b times
        k0, k1 = b * J0, b * J1
        start = np.repeat(b * (node_indptr[J0:J1] - node_indptr[J0]), b)  # segment start per column
        src = np.arange(col_ptr[k1] - col_ptr[k0])
        src -= (col_ptr[k0:k1] - col_ptr[k0] - start)[_group_ids(col_counts[k0:k1])]
        rows[col_ptr[k0]:col_ptr[k1]] = seg[src]
    return rows, _group_ids(col_counts)


def union_pattern(grams: list[Gram]) -> Pattern:
    """The symmetric pattern of sum_t A_t^T A_t, plus the diagonal."""
    grams = [g.explicit for g in grams]
    n = grams[0].shape[1]
    b = grams[0].block
    if b > 1 and all(g.block == b and g.shape[1] == n for g in grams):
        stack = _Stack(grams)
        K = stack.product([np.ones(len(g.cols)) for g in grams], [np.ones(g.shape[0]) for g in grams])
        # sort the blocks of each row, keeping the permutation (carried as exact float data)
        S = sp.csr_matrix((np.arange(len(K.indices), dtype=np.float64), K.indices.copy(),
                           K.indptr.copy()), shape=(stack.nodes, stack.nodes))
        S.sort_indices()
        node_ptr, node_ind = S.indptr.astype(np.int64), S.indices.astype(np.int64)
        rows, cols = _expand_blocks(node_ptr, node_ind, b)
        pattern = Pattern(rows, cols, n, blocks=NodeBlocks(b, node_ptr, node_ind))
        smap = _StackMap(stack, pattern)
        smap.set_structure(K, sorted_position=_inverse(S.data.astype(np.int64)))
        pattern.blocks.maps[tuple(map(id, grams))] = smap
        return pattern
    S = sum(g.structure() for g in grams) + sp.identity(n, format="csr")
    S = S.tocsc()
    S.sort_indices()
    cols = np.repeat(np.arange(n), np.diff(S.indptr))
    return Pattern(S.indices.astype(np.int64), cols.astype(np.int64), n)


def _inverse(perm: np.ndarray) -> np.ndarray:
    inv = np.empty_like(perm)
    inv[perm] = np.arange(len(perm))
    return inv


class _StackMap:
    """A stack of Gram operators and where each entry of its BSR product lands in a pattern."""

    def __init__(self, stack: _Stack, pattern: Pattern):
        self.stack = stack
        self.pattern = pattern
        self.indices = self.indptr = None  # the product's block structure, after a first product
        self.dest, self.bijective = None, False

    def set_structure(self, K: sp.bsr_matrix, sorted_position: np.ndarray | None = None):
        """Record K's block structure and the pattern position of each entry of K.data
        (flattened (block, a', a) order). Block q in BSR row J and column I holds
        K[b J + a', b I + a], which by symmetry is the pattern entry at row b I + a of column
        b J + a'. ``sorted_position``: each block's index in the pattern's node structure
        when known (the full stack); else found by binary search."""
        blocks = self.pattern.blocks
        b, node_ptr, node_ind = blocks.size, blocks.indptr, blocks.indices
        n = len(node_ptr) - 1
        counts = np.diff(node_ptr)
        J = _group_ids(np.diff(K.indptr))
        if sorted_position is None:
            keys = np.repeat(np.arange(n, dtype=np.int64), counts) * n + node_ind
            query = J * n + K.indices
            q = np.searchsorted(keys, query)
            if not (np.all(q < len(keys)) and np.array_equal(keys[np.minimum(q, len(keys) - 1)], query)):
                raise KeyError("a block of the product is not in the pattern")
        else:
            q = sorted_position
        start = node_ptr[J]
        base = q - start
        base *= b
        base += b * b * start
        del start
        stride = b * counts[J]  # entries in each dof column of node column J
        dest = np.empty((len(J), b, b), dtype=np.int64)
        for a1 in range(b):
            for a in range(b):
                dest[:, a1, a] = base + (a1 * stride + a)
        self.indices, self.indptr = K.indices.copy(), K.indptr.copy()
        self.dest = dest.reshape(-1)
        self.bijective = len(self.dest) == self.pattern.nnz

    def values(self, data_list, w_list) -> np.ndarray:
        K = self.stack.product(data_list, w_list)
        if self.indices is None or not (len(K.indices) == len(self.indices)
                                        and np.array_equal(K.indptr, self.indptr)
                                        and np.array_equal(K.indices, self.indices)):
            self.set_structure(K)
        out = np.empty(self.pattern.nnz) if self.bijective else np.zeros(self.pattern.nnz)
        out[self.dest] = K.data.reshape(-1)
        return out


def to_numpy(x) -> np.ndarray:
    if isinstance(x, torch.Tensor):
        return x.detach().cpu().numpy()
    return np.asarray(x)


def numeric_values(pattern: Pattern, terms) -> torch.Tensor:
    """sum_t A_t^T diag(w_t) A_t on ``pattern`` from (gram, data, w) triples, via scipy."""
    terms = [(g.explicit, to_numpy(g.explicit_data(d)), to_numpy(w)) for g, d, w in terms]
    grams = [g for g, _, _ in terms]
    blocks = pattern.blocks
    if blocks is not None and all(g.block == blocks.size for g in grams):
        key = tuple(map(id, grams))
        if key not in blocks.maps:
            blocks.maps[key] = _StackMap(_Stack(grams), pattern)
        m = blocks.maps[key]
        if all(a is b for a, b in zip(m.stack.grams, grams)):
            return torch.as_tensor(m.values([d for _, d, _ in terms], [w for _, _, w in terms]))
    K = sum(g.matrix(d, w) for g, d, w in terms)
    K = K.tocoo()  # no duplicates: scipy sums them in the products
    values = np.zeros(pattern.nnz)
    values[pattern.position(K.row, K.col)] = K.data
    return torch.as_tensor(values)


def internal_force(terms, u: torch.Tensor) -> torch.Tensor:
    """K u = sum_t A_t^T (w_t (A_t u)) matrix-free in torch (differentiable), u flat."""
    return sum(g.apply_transpose(d, w * g.apply(d, u)) for g, d, w in terms)
