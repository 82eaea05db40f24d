"""Factors of scipy SPD matrices with the project's sparse backends (CHOLMOD or SuperLU)."""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import torch

from bayespd.linalg.sparse import Factor, Pattern


def shifted_factor(A, s: np.ndarray, b: float) -> Factor:
    """A factor of diag(s) + b A for a sparse SPD A, or made by A itself when it knows how
    (``woodbury.LocallyUpdated``: from the factor before a local change)."""
    if hasattr(A, "shifted_factor"):
        return A.shifted_factor(s, b)
    return spd_factor(sp.diags(s) + b * A)


def spd_factor(A, ordering: str | None = None) -> Factor:
    """A factor (``.solve(numpy b)``) of a symmetric positive-definite scipy matrix
    (``ordering``: CHOLMOD's fill-reducing ordering, see ``Pattern.factorize``)."""
    A = sp.csc_matrix(A, dtype=np.float64)
    A.sum_duplicates()
    A.sort_indices()
    n = A.shape[0]
    cols = np.repeat(np.arange(n), np.diff(A.indptr))
    return Pattern(A.indices, cols, n).factorize(torch.from_numpy(A.data), ordering=ordering)
