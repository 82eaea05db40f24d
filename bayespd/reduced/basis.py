"""Proper orthogonal decomposition of full-model snapshots (Cui, Marzouk & Willcox 2015 sec 3)."""
from __future__ import annotations

import numpy as np


def pod(snapshots: np.ndarray, rtol: float) -> tuple[np.ndarray, np.ndarray]:
    """An orthonormal basis V (n, r) of the columns of ``snapshots`` (n, N), each scaled to unit
    norm first (the displacement scales as 1/K: the shape, not the size, needs a basis), with r
    the smallest rank whose discarded singular values have relative norm <= ``rtol``; returns
    (V, all singular values)."""
    norms = np.linalg.norm(snapshots, axis=0)
    if np.any(~np.isfinite(snapshots)) or np.any(norms == 0):
        raise ValueError("a snapshot is zero or not finite: the full solve failed at that draw")
    U, s, _ = np.linalg.svd(snapshots / norms, full_matrices=False)
    tail = np.sqrt(np.cumsum(s[::-1] ** 2)[::-1]) / np.linalg.norm(s)  # tail[k]: norm of s[k:]
    rank = int(np.argmax(np.append(tail, 0.0) <= rtol))
    return U[:, :max(rank, 1)], s
