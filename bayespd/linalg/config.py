"""The settings of the linear algebra, in one frozen ``LinalgSettings``: the threads it takes
and CHOLMOD's fill-reducing ordering. They change speed and rounding (the order of sums in a
factorisation), never what is solved.

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


@dataclass(frozen=True)
class LinalgSettings:
    """``factor_threads``: OpenBLAS threads while CHOLMOD factorises (None: OpenBLAS's own
    setting, all cores unless OPENBLAS_NUM_THREADS or ``threadpoolctl`` lowered it, as each
    MCMC chain worker does); ``matvec_threads``: row blocks of the matrix-free product applied
    in parallel (None: all cores); ``cholmod_ordering``: CHOLMOD's fill-reducing ordering of a
    pattern's first factorisation ("default" tries AMD and METIS and keeps the better; "amd"
    analyses faster on large 2D problems but fills more)."""

    factor_threads: int | None = None
    matvec_threads: int | None = 1
    cholmod_ordering: str = "default"

    def __post_init__(self):
        for name in ("factor_threads", "matvec_threads"):
            value = getattr(self, name)
            if value is not None and not (isinstance(value, int) and value >= 1):
                raise ValueError(f"{name} must be a positive integer or None, got {value!r}")
        if self.cholmod_ordering not in ORDERINGS:
            raise ValueError(f"cholmod_ordering must be one of {ORDERINGS}, got {self.cholmod_ordering!r}")


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
