"""The settings of the linear algebra, in one frozen ``LinalgSettings``: the threads it takes,
CHOLMOD's fill-reducing ordering and how a static scene's solver is chosen. They change speed
and rounding (the order of sums in a factorisation, an iterative solve's residual <= rtol),
never what is solved.

How a ``Scene(solver="auto")`` (the default) is solved, ``choose_solver``:

* the setting ``static_solver`` ("auto" by default) may force "direct", "pcg" or "amg";
* "auto": a direct factorisation (CHOLMOD when the ``fast`` extra is installed, else scipy's
  SuperLU) for at most ``direct_max_dofs`` dofs (None: ``DIRECT_MAX_DOFS``, the crossover
  measured per backend and dimension, benchmarks/README.md, issue 31), above it the
  matrix-free PCG with the smoothed-aggregation AMG preconditioner (``linalg.amg``; pyamg
  is a dependency, so a plain pip install has it);
* a scene that needs the assembled matrix (confinement eps > 0, a symmetry half-model) is
  direct at any size;
* SuperLU is refused (``SuperLUFillError``, naming the fix) on a K_ff with more than
  ``SPLU_MAX_NNZ`` entries: its fill grows past the memory of a 24 GB machine there
  (80k dofs, 19.8 M entries: 11 GB, 53 s).

    from bayespd import linalg
    linalg.set_defaults(factor_threads=1)       # for the rest of the process (a script)
    with linalg.settings(factor_threads=1):      # for a block; the settings before come back
        ...
    linalg.current_settings().factor_threads

Process-wide rather than per thread: OpenBLAS's thread count belongs to the process, and the
work they steer runs in threads (the jobs of a ``lockstep`` run, the product's pool) that must
see their caller's choice, which a ``contextvars`` value would not reach. So change them from
one thread at a time. A call site that knows better passes an argument, which wins
(``Pattern.factorize(ordering=...)``, ``Assembly.operator(threads=...)``).
"""
from __future__ import annotations

import contextlib
from dataclasses import dataclass, replace

ORDERINGS = ("default", "amd", "metis", "nesdis", "colamd", "natural", "best")
STATIC_SOLVERS = ("auto", "direct", "pcg", "amg")
# Largest dof count solved directly by "auto", per (backend, dimension): where the direct
# factorisation takes about 1 s on the 2-core host, so that its many cheap right-hand sides
# (Laplace, observation matrices) still pay; above it one AMG solve + gradient is 7x (2D) to
# 25x (3D) cheaper. Measured for SuperLU (LPS, m = 3 in 2D, m = 2 in 3D; benchmarks/README.md,
# issue 31); CHOLMOD's 2D value from its 0.9 s at 20k dofs (README), its 3D value scaled from
# SuperLU's by the 2D ratio (not measured: no CHOLMOD on the host of issue 31).
DIRECT_MAX_DOFS = {("splu", 2): 8_000, ("splu", 3): 2_000,
                   ("cholmod", 2): 20_000, ("cholmod", 3): 5_000}
SPLU_MAX_NNZ = 12_000_000


class SuperLUFillError(ValueError):
    """A direct SuperLU solve on a matrix whose factor would not fit in memory."""


@dataclass(frozen=True)
class LinalgSettings:
    """``factor_threads``: OpenBLAS threads while CHOLMOD factorises (None: OpenBLAS's own
    setting, all cores unless OPENBLAS_NUM_THREADS or ``threadpoolctl`` lowered it, as each
    MCMC chain worker does); ``matvec_threads``: row blocks of the matrix-free product applied
    in parallel (None: all cores); ``cholmod_ordering``: CHOLMOD's fill-reducing ordering of a
    pattern's first factorisation ("default" tries AMD and METIS and keeps the better; "amd"
    analyses faster on large 2D problems but fills more); ``static_solver`` and
    ``direct_max_dofs``: how ``choose_solver`` picks a scene's solver (module docstring)."""

    factor_threads: int | None = None
    matvec_threads: int | None = 1
    cholmod_ordering: str = "default"
    static_solver: str = "auto"
    direct_max_dofs: int | None = None

    def __post_init__(self):
        for name in ("factor_threads", "matvec_threads"):
            value = getattr(self, name)
            if value is not None and not (isinstance(value, int) and value >= 1):
                raise ValueError(f"{name} must be a positive integer or None, got {value!r}")
        if self.cholmod_ordering not in ORDERINGS:
            raise ValueError(f"cholmod_ordering must be one of {ORDERINGS}, got {self.cholmod_ordering!r}")
        if self.static_solver not in STATIC_SOLVERS:
            raise ValueError(f"static_solver must be one of {STATIC_SOLVERS}, got {self.static_solver!r}")
        if self.direct_max_dofs is not None and not (isinstance(self.direct_max_dofs, int)
                                                     and self.direct_max_dofs >= 0):
            raise ValueError(f"direct_max_dofs must be an integer >= 0 or None, got {self.direct_max_dofs!r}")


_current = LinalgSettings()


def current_settings() -> LinalgSettings:
    """The settings in force."""
    return _current


def set_defaults(**changes) -> LinalgSettings:
    """Change the named settings for the rest of the process; returns the settings before."""
    global _current
    before, _current = _current, replace(_current, **changes)
    return before


@contextlib.contextmanager
def settings(**changes):
    """Run the block with the named settings changed; the settings in force when it began
    are restored after it, however it ends. Yields the settings in force inside."""
    global _current
    before = set_defaults(**changes)
    try:
        yield _current
    finally:
        _current = before


def choose_solver(dofs: int, dim: int, backend: str, needs_matrix: bool = False) -> str:
    """"direct" or "amg" for a static system of ``dofs`` unknowns in ``dim`` dimensions on a
    direct ``backend`` ("cholmod" or "splu"), by the settings (module docstring);
    ``needs_matrix``: the scene needs the assembled K (direct at any size)."""
    forced = _current.static_solver
    if forced != "auto":
        return forced
    if needs_matrix:
        return "direct"
    limit = _current.direct_max_dofs
    if limit is None:
        limit = DIRECT_MAX_DOFS[(backend, 3 if dim >= 3 else 2)]
    return "direct" if dofs <= limit else "amg"


def refuse_superlu_fill(nnz: int) -> None:
    """Raise ``SuperLUFillError`` for a SuperLU factorisation of a matrix with more than
    ``SPLU_MAX_NNZ`` entries."""
    if nnz > SPLU_MAX_NNZ:
        raise SuperLUFillError(
            f"a direct SuperLU solve of this stiffness ({nnz / 1e6:.1f} M entries) would fill "
            f"past the memory of the machine (the limit is {SPLU_MAX_NNZ / 1e6:.0f} M): use "
            "solver='auto' or 'amg' (matrix-free PCG with algebraic multigrid), or install "
            "CHOLMOD (`make fast`, the 'fast' extra)")
