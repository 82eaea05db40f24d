"""Block sparsity patterns over particles and the index maps materials assemble with."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from bayespd.bonds import Bonds
from bayespd.sparse import Pattern


class BlockPattern:
    """The dof pattern of a matrix made of dim x dim blocks between particle pairs.

    ``k, l`` list the coupled particle pairs (any order, duplicates allowed; the diagonal and
    the transposes are added). Values are assembled per block, shape (n_blocks, dim, dim),
    and :meth:`values` reorders them onto ``self.pattern`` (CSC order) for the solver.
    """

    def __init__(self, n_nodes: int, dim: int, k: np.ndarray, l: np.ndarray):
        diag = np.arange(n_nodes)
        kk = np.concatenate([k, l, diag])
        ll = np.concatenate([l, k, diag])
        keys = np.unique(ll * n_nodes + kk)  # column-major: sorted by (l, k)
        self.n_nodes, self.dim, self._keys = n_nodes, dim, keys
        bl, bk = np.divmod(keys, n_nodes)
        # scalar entry (block b, alpha, beta) sits at row dim*bk+alpha, column dim*bl+beta
        blocks_per_col = np.bincount(bl, minlength=n_nodes)
        block_ptr = np.concatenate([[0], np.cumsum(blocks_per_col)])
        rank = np.arange(len(keys)) - block_ptr[bl]
        a = np.arange(dim)
        pos = (dim * dim * block_ptr[bl][:, None, None]
               + a[None, None, :] * dim * blocks_per_col[bl][:, None, None]
               + dim * rank[:, None, None] + a[None, :, None])
        perm = np.empty(pos.size, dtype=np.int64)
        perm[pos.reshape(-1)] = np.arange(pos.size)
        self._perm = torch.as_tensor(perm)
        rows = (dim * bk[:, None, None] + a[None, :, None]).repeat(dim, axis=2).reshape(-1)
        cols = (dim * bl[:, None, None] + a[None, None, :]).repeat(dim, axis=1).reshape(-1)
        self.pattern = Pattern(rows[perm], cols[perm], n_nodes * dim)

    @property
    def n_blocks(self) -> int:
        return len(self._keys)

    def block(self, k: np.ndarray, l: np.ndarray) -> torch.Tensor:
        """Block ids of the particle pairs (k, l); every pair must be in the pattern."""
        key = np.asarray(l) * self.n_nodes + np.asarray(k)
        idx = np.searchsorted(self._keys, key)
        found = idx < len(self._keys)
        if not (found.all() and np.array_equal(self._keys[idx], key)):
            raise KeyError("a particle pair is not in the pattern")
        return torch.as_tensor(idx)

    def values(self, blocks: torch.Tensor) -> torch.Tensor:
        """Per-block values (n_blocks, dim, dim) as the pattern's value vector."""
        return blocks.reshape(-1)[self._perm]


@dataclass(frozen=True)
class Families:
    """Each particle's family as a list of *ends*: one per bond touching it, then itself.

    ``owner[e]`` is the particle whose family holds end e, ``node[e]`` the particle the end
    points at, ``bond[e]`` its bond (-1 for the self end) and ``sign[e]`` the orientation of
    the bond vector seen from the owner.
    """

    owner: np.ndarray
    node: np.ndarray
    bond: np.ndarray
    sign: np.ndarray
    n_neighbour_ends: int

    @staticmethod
    def of(bonds: Bonds, n_nodes: int) -> "Families":
        b = np.arange(bonds.n)
        owner = np.concatenate([bonds.i, bonds.j])
        node = np.concatenate([bonds.j, bonds.i])
        bond = np.concatenate([b, b])
        sign = np.concatenate([np.ones(bonds.n), -np.ones(bonds.n)])
        return Families(owner, node, bond, sign, 2 * bonds.n)

    def with_self(self, n_nodes: int):
        """(owner, node) of all ends including one self end per particle (appended last)."""
        diag = np.arange(n_nodes)
        return np.concatenate([self.owner, diag]), np.concatenate([self.node, diag])

    def end_pairs(self, n_nodes: int):
        """All ordered pairs (e1, e2) of ends in the same family, self ends included."""
        owner, _ = self.with_self(n_nodes)
        order = np.argsort(owner, kind="stable")
        size = np.bincount(owner, minlength=n_nodes)
        start = np.concatenate([[0], np.cumsum(size)])[:-1]
        reps = size[owner[order]]
        e1 = np.repeat(order, reps)
        first = np.repeat(np.cumsum(reps) - reps, reps)
        offset = np.arange(len(e1)) - first
        e2 = order[start[owner[e1]] + offset]
        return e1, e2
