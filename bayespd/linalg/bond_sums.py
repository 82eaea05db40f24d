"""A = S B: an operator whose rows sum the rows of a bond operator B at the bonds' particles,
kept factored (the LPS dilatation, Turner 2015 eq 10: theta_k = sum over the bonds b at particle
k of s_kb e_b, e = B u the bond extensions, s_kb = d omega |xi| V_other / m_k).

B is a ``Gram`` whose every row touches two particles (p_r, q_r) (blocks a_r on p_r's dofs, c_r
on q_r's), its data fixed; S has two entries per row r of B, s_0r at particle p_r and s_1r at
q_r, the data given per call as a (2, R) array. Its products cost O(rows of B), and a stiffness
term A^T diag(w) A is applied as B^T (S^T (w S (B x))) without forming A: at 160k particles,
m = 2, A as a ``Gram`` has 6.7 M entries (B 6.4 M), whose index arrays, data and products came on
top of B's. ``explicit`` is A as a Gram of one row per particle (its family: the particle itself
and every row's other particle), with ``explicit_data``, for what needs A's entries: assembly
on a pattern, a direct factorisation, its CSR.
"""
from __future__ import annotations

from functools import cached_property

import numpy as np
import scipy.sparse as sp
import torch

from bayespd import bond_loops
from bayespd.linalg.assembly import Gram, to_numpy


class BondSums:
    """A = S B (module docstring) on ``nodes`` particles; ``bond_data``: B's fixed data (in the
    order of B's construction). Offers a Gram's products (``apply``, ``apply_transpose``,
    ``normal_product``) and, through ``explicit``, its assembly (``operator``, ``matrix``,
    ``values``, ``structure``)."""

    factored = True

    def __init__(self, bonds: Gram, bond_data: torch.Tensor, nodes: int):
        ind, ptr = bonds.block_parts()
        if not np.all(np.diff(ptr) == 2):
            raise ValueError("BondSums needs a bond operator: every row on two particles")
        b = bonds.block
        self.bonds, self.bond_data, self.block = bonds, bond_data, b
        self.shape = (nodes, bonds.shape[1])
        self.p, self.q = ind[0::2].astype(np.int64), ind[1::2].astype(np.int64)
        self._p, self._q = torch.as_tensor(self.p), torch.as_tensor(self.q)
        blocks = torch.as_tensor(bonds.ordered(to_numpy(bond_data))).reshape(-1, 2, b)
        self.a, self.c = blocks[:, 0], blocks[:, 1]  # B's blocks on p_r and on q_r
        self.two_block_rows = np.empty(0, dtype=np.int64)  # a family row is never a pair row

    def apply(self, data: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        """A x = S (B x) for a flat x (differentiable in data and x)."""
        e = self.bonds.apply(self.bond_data, x)
        z = torch.zeros(self.shape[0], dtype=e.dtype)
        return z.index_add(0, self._p, data[0] * e).index_add(0, self._q, data[1] * e)

    def apply_transpose(self, data: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        """A^T y = B^T (S^T y) for y over A's rows (differentiable in data and y)."""
        t = data[0] * y.index_select(0, self._p) + data[1] * y.index_select(0, self._q)
        return self.bonds.apply_transpose(self.bond_data, t)

    def normal_product(self, data, w, free_index: np.ndarray, bond_weights=None):
        """x -> A_f^T diag(w) A_f x on the free dofs (numpy, x of shape (n_free,)): A's columns
        restricted to ``free_index``; plus B_f^T diag(k) B_f x with ``bond_weights`` k (B's own
        stiffness term, e.g. LPS's bond term: then the product is the whole K, in the same two
        passes). Two compiled passes over the rows of B where numba is installed
        (``bond_loops.shared``: the same bits on one thread or two), else numpy."""
        s, w = np.ascontiguousarray(to_numpy(data), dtype=np.float64), np.asarray(to_numpy(w), dtype=np.float64)
        w = np.broadcast_to(w, (self.shape[0],))
        k = np.zeros(1) if bond_weights is None else np.ascontiguousarray(to_numpy(bond_weights), dtype=np.float64)
        n, b = self.shape[0], self.block
        compiled = bond_loops.usable()
        if compiled:
            ends = (self.p, self.q)
            blocks = (self.p.view(np.uint64), self.q.view(np.uint64), *self._contiguous_blocks)
        else:
            B = self.bonds.operator(to_numpy(self.bond_data))

        def product(x):
            full = np.zeros(n * b)
            full[free_index] = x
            if compiled:
                threads = torch.get_num_threads()
                parts = bond_loops.shares(ends, bond_loops.SHARES_PER_THREAD * threads if threads > 1 else 1)
                u = full.reshape(n, b)
                theta = bond_loops.shared(_sums, (u, *blocks, s), parts, (n,), np.float64, threads)
                out = bond_loops.shared(_spread, (u, w * theta, *blocks, s, k, bond_weights is not None), parts,
                                        (n, b), np.float64, threads)
                return out.reshape(-1)[free_index]
            e = B @ full
            z = w * (np.bincount(self.p, s[0] * e, minlength=n) + np.bincount(self.q, s[1] * e, minlength=n))
            t = s[0] * z[self.p] + s[1] * z[self.q]
            return (B.T @ (t if bond_weights is None else t + k * e))[free_index]

        return product

    @cached_property
    def _contiguous_blocks(self):
        """(a, c) as contiguous numpy arrays: the compiled passes read them a third faster
        than the strided views."""
        return np.ascontiguousarray(self.a.numpy()), np.ascontiguousarray(self.c.numpy())

    @cached_property
    def _family(self):
        """(Gram of A with one row per particle, ``order``): the family ends in row-major
        (owner, node) order, each end's id in ``order`` (``_family_ends``)."""
        n, b = self.shape[0], self.block
        owner, node, order = _family_ends(self.p, self.q, n)
        a = np.arange(b)
        return Gram(np.repeat(owner, b), (b * node[:, None] + a).reshape(-1), n, b * n), order

    @property
    def explicit(self) -> Gram:
        """A as a Gram (built on first use)."""
        return self._family[0]

    def explicit_data(self, data):
        """The entries of A in ``explicit``'s order (differentiable in data): end (p_r, q_r)
        s_0r c_r, end (q_r, p_r) s_1r a_r, the particle's own end the sum of its rows' s a (at
        p) and s c (at q)."""
        data = torch.as_tensor(data)
        at_p, at_q = data[0][:, None], data[1][:, None]
        own = torch.zeros(self.shape[0], self.block, dtype=data.dtype).index_add_(
            0, self._p, at_p * self.a).index_add_(0, self._q, at_q * self.c)
        ends = torch.cat([at_p * self.c, at_q * self.a, own])
        return ends.index_select(0, self._family[1]).reshape(-1)  # backward: index_add, 25 % less CPU than x[idx]

    def operator(self, data) -> sp.csr_matrix:
        return self.explicit.operator(to_numpy(self.explicit_data(data)))

    def matrix(self, data, w) -> sp.csr_matrix:
        return self.explicit.matrix(to_numpy(self.explicit_data(data)), w)

    def structure(self) -> sp.csr_matrix:
        return self.explicit.structure()

    def values(self, data, w, pattern, rows=None):
        return self.explicit.values(self.explicit_data(data), w, pattern, rows)


def _family_ends(i: np.ndarray, j: np.ndarray, n: int):
    """(owner, node, order) of the family ends of distinct bonds (i, j), i != j, in row-major
    (owner, node) order: ``order`` holds each one's end id (b for (i_b, j_b), nb + b for
    (j_b, i_b), 2 nb + k for (k, k)). Sparse CSR sums order them (counting sorts, O(ends))."""
    nb = len(i)
    ids = np.arange(1, 2 * nb + n + 1, dtype=np.float64)  # + 1: a sum drops explicit zeros
    upper = sp.csr_matrix((ids[:nb], (i, j)), shape=(n, n))
    lower = sp.csr_matrix((ids[nb:2 * nb], (j, i)), shape=(n, n))
    family = upper + lower + sp.csr_matrix((ids[2 * nb:], np.arange(n), np.arange(n + 1)), shape=(n, n))
    family.sort_indices()
    if family.nnz != 2 * nb + n:
        raise ValueError("bonds must be distinct pairs of distinct particles (as find_bonds gives)")
    owner = np.repeat(np.arange(n), np.diff(family.indptr))
    return owner, family.indices.astype(np.int64), torch.as_tensor(family.data.astype(np.int64) - 1)


def _inline(fn):
    """Compiled into the kernels that call it (numba), or plain Python without numba."""
    return fn if bond_loops.numba is None else bond_loops.numba.njit(inline="always", cache=True)(fn)


@_inline
def _row(u, p, q, a, c, r):  # pragma: no cover (compiled)
    """(B u)_r = a_r . u_p + c_r . u_q."""
    e = 0.0
    for k in range(u.shape[1]):
        e += a[r, k] * u[p[r], k] + c[r, k] * u[q[r], k]
    return e


@bond_loops.fast_kernel
def _sums(u, p, q, a, c, s, b0, b1, lo, out):  # pragma: no cover (compiled)
    """out[k - lo] += s_kr (B u)_r over the rows r in [b0, b1): S B u (p, q unsigned views: no
    wrap-around checks)."""
    for r in range(b0, b1):
        e = _row(u, p, q, a, c, r)
        out[p[r] - lo] += s[0, r] * e
        out[q[r] - lo] += s[1, r] * e


@bond_loops.fast_kernel
def _spread(u, z, p, q, a, c, s, kb, bonds, b0, b1, lo, out):  # pragma: no cover (compiled)
    """out[p_r - lo] += a_r t_r, out[q_r - lo] += c_r t_r, t_r = s_0r z_p + s_1r z_q (B^T S^T z),
    plus k_r (B u)_r with ``bonds`` (B^T diag(k) B u)."""
    for r in range(b0, b1):
        t = s[0, r] * z[p[r]] + s[1, r] * z[q[r]]
        if bonds:
            t += kb[r] * _row(u, p, q, a, c, r)
        for k in range(out.shape[1]):
            out[p[r] - lo, k] += a[r, k] * t
            out[q[r] - lo, k] += c[r, k] * t
