"""One factorisation for many nearby matrices on a pattern (the posterior-predictive replay).

Inside ``reusing_factors()``, the first factorisation of each pattern is kept as the
reference M; every later one on that pattern returns conjugate gradients on the new A
preconditioned by M^-1 (``PCGFactor``: a product with A and two triangular solves per
iteration, no factorisation), with a fresh factorisation only if CG has not reached ``rtol``
in ``maxiter`` iterations. The symbolic analysis (CHOLMOD's, cached on the pattern) and the
pattern itself are shared anyway.

Why it is cheap for posterior draws: if A = sum_t c_t A_t with every A_t positive
semi-definite (a Gram sum; LPS at fixed delta is affine in its moduli, K = a_s K_s + a_d K_d,
``bayespd.inverse.vfm``) and M = sum_t c0_t A_t, then x^T A x / x^T M x is a weighted mean of
the ratios c_t / c0_t, so kappa(M^-1 A) <= max_t (c_t / c0_t) / min_t (c_t / c0_t) and CG
reaches rtol in at most ceil(sqrt(kappa) / 2 ln(2 / rtol)) iterations (Saad 2003, eq 6.128):
about 10 for moduli within 20 % of the reference's. A draw at another delta changes the
bonds' weights too; the fallback covers a draw too far from the reference.
"""
from __future__ import annotations

import contextlib

_ACTIVE: dict | None = None  # id(pattern) -> (pattern, reference factor) while reusing
_SETTINGS = {"rtol": 1e-10, "maxiter": 60}


@contextlib.contextmanager
def reusing_factors(rtol: float = 1e-10, maxiter: int = 60):
    """Within the block, factorisations after the first on a pattern are CG solves
    preconditioned by the first (relative residual <= ``rtol``)."""
    global _ACTIVE
    previous, saved = _ACTIVE, dict(_SETTINGS)
    _ACTIVE = {}
    _SETTINGS.update(rtol=rtol, maxiter=maxiter)
    try:
        yield
    finally:
        _ACTIVE = previous
        _SETTINGS.update(saved)


def active() -> bool:
    return _ACTIVE is not None


def factor(pattern, A, fresh):
    """The factor of A (scipy sparse, on ``pattern``): the reference's PCG once one exists,
    else ``fresh()`` (a new factorisation), which becomes the reference."""
    from bayespd.linalg.sparse import ConvergenceError, Factor, PCGFactor

    if id(pattern) not in _ACTIVE:
        _ACTIVE[id(pattern)] = (pattern, fresh())
        return _ACTIVE[id(pattern)][1]
    reference = _ACTIVE[id(pattern)][1]
    pcg = PCGFactor(A.__matmul__, reference.solve, A.shape[0], _SETTINGS["rtol"], _SETTINGS["maxiter"])

    def solve(b):
        try:
            return pcg.solve(b)
        except ConvergenceError:  # too far from the reference: factorise this one
            return fresh().solve(b)

    return Factor(solve)
