"""Stiffness assembly as sums of Gram products K = sum_t A_t^T diag(w_t) A_t.

Every linearised PD stiffness has this form: A is a sparse operator of fixed structure
(bond extensions, nodal dilatations) whose entries and weights change with the parameters.
``Gram.matrix`` assembles numerically with scipy (fast, for factorisation); ``Gram.values``
assembles the same numbers with torch ops on entry pairs (differentiable, more memory).
"""
from __future__ import annotations

from functools import cached_property

import numpy as np
import scipy.sparse as sp
import torch

from bayespd.sparse import Pattern


class Gram:
    """K = A^T diag(w) A for A with entries at (rows[k], cols[k]) and data given per call."""

    def __init__(self, rows: np.ndarray, cols: np.ndarray, n_rows: int, n_cols: int):
        self.order = np.lexsort((cols, rows))  # row-major order of the entries
        self.rows, self.cols = rows[self.order], cols[self.order]
        self.shape = (n_rows, n_cols)
        self.indptr = np.searchsorted(self.rows, np.arange(n_rows + 1))
        self._rows_t, self._cols_t = torch.as_tensor(self.rows), torch.as_tensor(self.cols)
        self._order_t = torch.as_tensor(self.order)

    def operator(self, data) -> sp.csr_matrix:
        d = np.asarray(data)[self.order]
        return sp.csr_matrix((d, self.cols, self.indptr), shape=self.shape)

    def matrix(self, data, w) -> sp.csr_matrix:
        """A^T diag(w) A numerically (data: entries of A in the order given at construction)."""
        A = self.operator(data)
        return (A.T @ sp.diags(np.asarray(w)) @ A).tocsr()

    def structure(self) -> sp.csr_matrix:
        A = self.operator(np.ones(len(self.order)))
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
        """A x for a flat vector x (differentiable in data and x)."""
        contrib = data[self._order_t] * x[self._cols_t]
        return torch.zeros(self.shape[0], dtype=contrib.dtype).index_add(0, self._rows_t, contrib)

    def values(self, data: torch.Tensor, w: torch.Tensor, pattern: Pattern) -> torch.Tensor:
        """A^T diag(w) A on ``pattern`` as a differentiable torch expression."""
        k1, k2 = self._pairs
        if not hasattr(self, "_targets") or self._targets[0] is not pattern:
            self._targets = (pattern, torch.as_tensor(pattern.position(self.cols[k1], self.cols[k2])))
        d = data[self._order_t]
        contrib = w[torch.as_tensor(self.rows[k1])] * d[torch.as_tensor(k1)] * d[torch.as_tensor(k2)]
        return torch.zeros(pattern.nnz, dtype=contrib.dtype).index_add(0, self._targets[1], contrib)


def union_pattern(grams: list[Gram]) -> Pattern:
    """The symmetric pattern of sum_t A_t^T A_t, plus the diagonal."""
    n = grams[0].shape[1]
    S = sum(g.structure() for g in grams) + sp.identity(n, format="csr")
    S = S.tocsc()
    S.sort_indices()
    cols = np.repeat(np.arange(n), np.diff(S.indptr))
    return Pattern(S.indices.astype(np.int64), cols.astype(np.int64), n)


def numeric_values(pattern: Pattern, terms) -> torch.Tensor:
    """sum_t A_t^T diag(w_t) A_t on ``pattern`` from (gram, data, w) triples, via scipy."""
    K = sum(g.matrix(d.detach().cpu().numpy(), w.detach().cpu().numpy()) for g, d, w in terms)
    K = K.tocoo()  # no duplicates: scipy sums them in the products
    values = np.zeros(pattern.nnz)
    values[pattern.position(K.row, K.col)] = K.data
    return torch.as_tensor(values)
