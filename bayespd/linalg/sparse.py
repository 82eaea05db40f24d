"""Sparse symmetric positive-definite factors on a fixed pattern (the differentiable solve that
uses them is ``bayespd.linalg.adjoint``).

Backends: CHOLMOD (scikit-sparse) when importable, analysing the pattern once and
refactorising per value; else scipy's SuperLU in symmetric mode with an AMD ordering.
``PCGFactor`` is a preconditioned conjugate-gradient "factor" with the same ``solve``
interface, for problems too large to factorise (see ``bayespd.linalg.stiffness_solver.Assembly``); it raises
``ConvergenceError`` when it does not reach its tolerance.

Threads: CHOLMOD's supernodal factorisation runs in OpenBLAS; ``blas_threads(n)`` sets how
many threads that OpenBLAS uses (``config.LinalgSettings.factor_threads`` while factorising).
Triangular solves and the PCG loop run with one thread: a second OpenBLAS thread spinning
between calls only slows the single-threaded scipy code in between.
"""
from __future__ import annotations

import contextlib
import ctypes
import warnings
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import torch

from bayespd.linalg import reuse
from bayespd.linalg.config import current_settings

try:  # optional extra `fast`
    from sksparse import cholmod
except ImportError:  # pragma: no cover - depends on the machine
    cholmod = None


class NotPositiveDefiniteError(RuntimeError):
    """The stiffness is not positive definite (unstable material, too few constraints, ...)."""


class ConvergenceError(RuntimeError):
    """An iterative solve did not reach its tolerance."""


def _load_openblas():
    for name in ("libopenblas.so.0", "libopenblas.so", "libopenblasp-r0.3.21.so"):
        try:
            lib = ctypes.CDLL(name)
            lib.openblas_set_num_threads, lib.openblas_get_num_threads  # noqa: B018
            return lib
        except (OSError, AttributeError):
            continue
    return None


_OPENBLAS = _load_openblas() if cholmod is not None else None


@contextlib.contextmanager
def blas_threads(n: int | None):
    """Run the block with ``n`` OpenBLAS threads (CHOLMOD's BLAS); None leaves the current
    setting, so a process limited by ``threadpoolctl`` (chain workers sharing the cores) keeps
    its limit rather than oversubscribing the cores."""
    if _OPENBLAS is None or n is None:
        yield
        return
    before = _OPENBLAS.openblas_get_num_threads()
    _OPENBLAS.openblas_set_num_threads(int(n))
    try:
        yield
    finally:
        _OPENBLAS.openblas_set_num_threads(before)


@dataclass(frozen=True, eq=False)
class NodeBlocks:
    """The structure of a symmetric pattern made of full ``size`` x ``size`` blocks (the
    dofs of one node each): node column J holds the nodes ``indices[indptr[J]:indptr[J + 1]]``
    (sorted), and every dof entry of those blocks is in the pattern. ``maps`` is the
    assemblers' cache of where their products land in the pattern
    (``assembly.numeric_values``), kept with the pattern it is valid for."""

    size: int
    indptr: np.ndarray
    indices: np.ndarray
    maps: dict = field(default_factory=dict, repr=False)


RESTRICTED = 4  # sub-patterns a Pattern keeps (``restrict``)


@dataclass(eq=False)
class Pattern:
    """A fixed sparsity pattern of an n x n matrix, entries in CSC order (column-major).

    ``rows``/``cols`` are int64 arrays; symmetric patterns list both triangles; ``blocks``:
    its ``NodeBlocks`` when it is made of node blocks (``assembly.union_pattern``), else None.
    ``indptr`` (CSC column pointers) and ``rows_t``/``cols_t`` (torch copies) are derived.
    """

    rows: np.ndarray
    cols: np.ndarray
    n: int
    blocks: NodeBlocks | None = field(default=None, repr=False)
    indptr: np.ndarray = field(init=False, repr=False)
    rows_t: torch.Tensor = field(init=False, repr=False)
    cols_t: torch.Tensor = field(init=False, repr=False)
    _strict: bool = field(init=False, repr=False)  # no duplicate entries
    _symbolic: object = field(default=None, init=False, repr=False)  # CHOLMOD's analysis
    _restricted: dict = field(default_factory=dict, init=False, repr=False)  # ``restrict``'s latest

    def __post_init__(self):
        self.rows = np.asarray(self.rows, dtype=np.int64)
        self.cols = np.asarray(self.cols, dtype=np.int64)
        b = self.blocks
        if b is not None and (b.size * (len(b.indptr) - 1) != self.n
                              or b.size ** 2 * len(b.indices) != self.nnz):
            raise ValueError("blocks must describe this pattern's node blocks")
        self._strict = True
        step = 1 << 20  # O(nnz) check in chunks (no sort, no large temporaries)
        for k in range(0, max(0, len(self.rows) - 1), step):
            dc = np.diff(self.cols[k:k + step + 1])
            dr = np.diff(self.rows[k:k + step + 1])
            if np.any(dc < 0) or np.any((dc == 0) & (dr < 0)):
                raise ValueError("pattern entries must be sorted by (col, row)")
            self._strict = self._strict and not np.any((dc == 0) & (dr == 0))
        self.indptr = np.searchsorted(self.cols, np.arange(self.n + 1)).astype(np.int64)
        self.rows_t = torch.as_tensor(self.rows)
        self.cols_t = torch.as_tensor(self.cols)

    def __getstate__(self):
        """Pickled without CHOLMOD's analysis (it does not pickle): the next factorisation
        redoes it, so a scene can be sent to worker processes after it has solved."""
        return {**self.__dict__, "_symbolic": None, "_restricted": {}}

    @property
    def nnz(self) -> int:
        return len(self.rows)

    @cached_property
    def _keys(self) -> np.ndarray:
        return self.cols * self.n + self.rows

    def position(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """Entry index of each (row, col); every pair must be in the pattern."""
        keys = self._keys
        query = np.asarray(cols, dtype=np.int64) * self.n + np.asarray(rows, dtype=np.int64)
        idx = np.searchsorted(keys, query)
        if not (np.all(idx < len(keys)) and np.array_equal(keys[np.minimum(idx, len(keys) - 1)], query)):
            raise KeyError("an entry is not in the pattern")
        return idx

    def in_rows(self, rows) -> np.ndarray:
        """Entry indices (increasing) of the entries in the given rows."""
        return np.flatnonzero(np.isin(self.rows, np.asarray(rows, dtype=np.int64)))

    @cached_property
    def _csc_index(self):
        """(indices, indptr) in the narrowest dtype scipy accepts, converted once."""
        dtype = np.int32 if max(self.n, self.nnz) < 2**31 - 1 else np.int64
        return self.rows.astype(dtype), self.indptr.astype(dtype)

    def matrix(self, values: torch.Tensor) -> sp.csc_matrix:
        v = values.detach().cpu().numpy() if isinstance(values, torch.Tensor) else np.asarray(values)
        indices, indptr = self._csc_index
        A = sp.csc_matrix((v, indices, indptr), shape=(self.n, self.n), copy=False)
        if self._strict:
            A.has_sorted_indices = True
        return A

    def matvec(self, values: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        """K x as a differentiable gather/scatter (x may be (n,) or (n, k))."""
        contrib = values.reshape(-1, *([1] * (x.dim() - 1))) * x[self.cols_t]
        return torch.zeros_like(x, dtype=contrib.dtype).index_add(0, self.rows_t, contrib)

    def restrict(self, keep: np.ndarray):
        """Sub-pattern on the dofs where ``keep`` is true, and which entries it keeps: the same
        objects for the same ``keep`` among the latest RESTRICTED ones (read-only; the bodies of
        an ensemble's realisations, on one material, share them: ~50 MB each at 10k particles)."""
        keep = np.asarray(keep, dtype=bool)
        key = keep.tobytes()
        if key not in self._restricted:
            index = np.cumsum(keep) - 1
            entries = keep[self.rows] & keep[self.cols]
            sub = Pattern(index[self.rows[entries]], index[self.cols[entries]], int(keep.sum()))
            if len(self._restricted) >= RESTRICTED:
                self._restricted.pop(next(iter(self._restricted)))
            self._restricted[key] = (sub, np.flatnonzero(entries))
        return self._restricted[key]

    def factorize(self, values: torch.Tensor, backend: str | None = None,
                  ordering: str | None = None) -> "Factor":
        """A factor of the matrix with these values (``ordering``: CHOLMOD's fill-reducing
        ordering for the first factorisation of this pattern, by default the settings')."""
        backend = backend or default_backend()
        A = self.matrix(values)
        if not np.all(np.isfinite(A.data)):
            raise NotPositiveDefiniteError("stiffness has non-finite entries (check parameters)")
        if reuse.active():  # a reference factor of this pattern preconditions CG (linalg.reuse)
            return reuse.factor(self, A, lambda: self._fresh_factor(A, backend, ordering))
        return self._fresh_factor(A, backend, ordering)

    def _fresh_factor(self, A, backend: str, ordering: str | None) -> "Factor":
        if backend == "cholmod":
            if cholmod is None:
                raise ValueError("backend 'cholmod' needs scikit-sparse: install the 'fast' extra")
            return _cholmod_factor(self, A, ordering or current_settings().cholmod_ordering)
        if backend == "splu":
            return splu_factor(A)
        raise ValueError(f"unknown backend {backend!r}: use 'cholmod' or 'splu'")


def default_backend() -> str:
    return "cholmod" if cholmod is not None else "splu"


class Factor:
    """A factorisation with ``solve(b)`` for numpy b of shape (n,) or (n, k); ``cholmod``:
    CHOLMOD's factor object when CHOLMOD made it (its L, P, ...), else None."""

    def __init__(self, solve_fn, cholmod=None):
        self.solve, self.cholmod = solve_fn, cholmod


def _cholmod_factor(pattern: Pattern, A, ordering: str) -> Factor:
    try:
        with blas_threads(current_settings().factor_threads):
            if pattern._symbolic is None:
                pattern._symbolic = cholmod.analyze(A, mode="supernodal", ordering_method=ordering)
            f = pattern._symbolic.cholesky(A)
    except cholmod.CholmodNotPositiveDefiniteError as e:
        raise NotPositiveDefiniteError(f"stiffness is not positive definite ({e})") from None
    check_pivots(f.D(), A.diagonal()[f.P()])

    def solve(b):
        with blas_threads(1):
            return f.solve_A(b)

    return Factor(solve, cholmod=f)


def _dot(a: np.ndarray, b: np.ndarray):
    """Column-wise dot products without BLAS (numpy's own OpenBLAS would start threads)."""
    return np.add.reduce(a * b, axis=0)


class PCGFactor(Factor):
    """K^-1 b by preconditioned conjugate gradients: ``matvec(x)`` is K x and
    ``precondition(r)`` applies an SPD approximation of K^-1 (both for numpy (n,) or (n, k)).

    Converged when ||b - K x|| <= rtol ||b|| for every column; otherwise ``ConvergenceError``.
    A non-positive curvature p^T K p <= 0 raises ``NotPositiveDefiniteError``.
    ``iterations`` holds the iteration count of the last solve; ``log``, a list, gets each
    solve's (the caller's record of how well a kept preconditioner still serves).
    ``renew`` = (limit, make): a solve that reaches ``limit`` iterations unconverged takes the
    preconditioner ``make()`` from then on (once; CG restarts from its iterate), for a
    preconditioner kept from another operator (``renewed`` says whether it happened).
    """

    def __init__(self, matvec, precondition, n: int, rtol: float = 1e-10, maxiter: int | None = None,
                 log: list | None = None, renew: tuple | None = None):
        self.matvec, self.precondition, self.n, self.log, self.renew = matvec, precondition, n, log, renew
        self.rtol, self.maxiter = rtol, maxiter or max(200, int(4 * np.sqrt(n)))
        self.iterations, self.cholmod, self.renewed = 0, None, False  # ``solve`` is a method: no
        # bound method stored on the instance, whose reference cycle kept K_b and the V-cycle
        # alive until Python's rare full collection (fe_convergence: +300 MiB per 3D solve)

    def solve(self, b):
        b = np.asarray(b, dtype=np.float64)
        if b.shape[0] != self.n:
            raise ValueError(f"right-hand side must have {self.n} rows, got {b.shape[0]}")
        with blas_threads(1):
            return self._pcg(b)

    def _pcg(self, b):
        x = np.zeros_like(b)
        norm_b = np.sqrt(_dot(b, b))
        if np.all(norm_b == 0):
            return x
        target = self.rtol * norm_b
        r, done = b.copy(), 0
        while True:
            stop = self.maxiter if self.renew is None else min(self.maxiter, max(self.renew[0], done + 1))
            done, res = self._iterate(x, r, target, done, stop)
            if np.all(res <= target) or done >= self.maxiter:
                break
            self.precondition, self.renew, self.renewed = self.renew[1](), None, True
        self.iterations = done
        if self.log is not None:
            self.log.append(done)
        if np.all(res <= target):
            return x
        worst = float(np.max(res / norm_b))
        raise ConvergenceError(
            f"conjugate gradients did not converge: relative residual {worst:.2e} > rtol="
            f"{self.rtol:g} after {self.maxiter} iterations; use the direct backend "
            "(method='direct'), a stronger preconditioner, or raise maxiter")

    def _iterate(self, x, r, target, done: int, stop: int):
        """CG from the iterate x with residual r (both updated in place), counting from
        ``done`` to at most ``stop`` iterations: (iterations, residual norms)."""
        z = self.precondition(r)
        p = z.copy()
        rz = _dot(r, z)
        for it in range(done + 1, stop + 1):
            Kp = self.matvec(p)
            curvature = _dot(p, Kp)
            if np.any(curvature <= 0) or not np.all(np.isfinite(curvature)):
                raise NotPositiveDefiniteError(
                    "the operator is not positive definite (p^T K p <= 0 in conjugate "
                    "gradients): check moduli, horizon and constraints")
            alpha = rz / curvature
            x += alpha * p
            r -= alpha * Kp
            res = np.sqrt(_dot(r, r))
            if np.all(res <= target):
                return it, res
            z = self.precondition(r)
            rz_new = _dot(r, z)
            p = z + (rz_new / rz) * p
            rz = rz_new
        return stop, res


def splu_factor(A) -> Factor:
    """SuperLU's factor of an SPD csc_matrix A with diagonal pivots (symmetric mode), refusing
    a matrix that is not positive definite."""
    with warnings.catch_warnings():
        warnings.simplefilter("error", sp.SparseEfficiencyWarning)
        try:
            lu = spla.splu(A, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                           options={"SymmetricMode": True})
        except RuntimeError as e:  # "Factor is exactly singular"
            raise NotPositiveDefiniteError(f"stiffness is singular ({e}): are rigid-body "
                                           "motions constrained?") from None
    # With diagonal pivots, K = P^T L U P^T with U's diagonal the pivots of an LDL^T:
    # K is positive definite iff they are all positive and no row swap was needed.
    if not np.array_equal(lu.perm_r, lu.perm_c):
        raise NotPositiveDefiniteError("stiffness is not positive definite (a row swap was "
                                       "needed): check moduli, horizon and constraints")
    check_pivots(lu.U.diagonal(), A.diagonal()[np.argsort(lu.perm_c)])
    return Factor(lu.solve)


# A pivot (Schur complement of a diagonal entry) below PIVOT_RTOL times that entry is zero
# in floating point: a rigid-body mode gives ~1e-15..1e-12 with either sign, depending on
# rounding; a well-posed PD stiffness gives ratios above ~1e-2.
PIVOT_RTOL = 1e-10


def check_pivots(pivots: np.ndarray, diagonal: np.ndarray) -> None:
    """Raise NotPositiveDefiniteError unless every pivot of a factorisation is positive and
    not zero in floating point relative to its diagonal entry (``PIVOT_RTOL``)."""
    if not (np.all(diagonal > 0) and np.all(pivots > PIVOT_RTOL * diagonal)):
        raise NotPositiveDefiniteError("stiffness is not positive definite (a zero or negative "
                                       "pivot): check moduli, horizon and constraints (are "
                                       "rigid-body motions constrained?)")
