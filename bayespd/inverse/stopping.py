"""When a Tikhonov minimisation has converged, stalled or run out of evaluations.

The optimiser sees the scale-free objective f = J / J0 (J0 = J at the start, 1 if J0 = 0): J
scales as 1 / sigma^2 and with the data's units, f does not, so the tolerances mean the same
for every problem. On log-parameters z the tests are

* projected gradient: ||z - clip(z - grad f, lo, hi)||_inf <= gtol (Nocedal & Wright 2006,
  eq 16.69: zero exactly at a KKT point of the bound-constrained problem; without bounds
  it is ||grad f||_inf), checked by us at the returned point, whatever the optimiser says;
* relative decrease: 0 < J_{k-1} - J_k <= ftol J_{k-1} over one accepted iteration
  (L-BFGS-B's factr test, but relative to J itself, not to max(J, 1); no decrease at all is
  no progress, which the stall test judges);
* an exact fit: J <= EXACT_FIT J0 (J >= 0, so J is within machine epsilon of the start's J of its
  lower bound: noise-free same-model data fitted to round-off, where the gradient test can fail
  only by the gradient's own round-off, e.g. 1.6e-12 against gtol = 1e-12 on one CPU and not another).

A minimisation is *converged* only if one of them passed. It stops without converging when
``maxfun`` evaluations are spent, or when it stalls: ``stall`` evaluations in a row lower the
best J by no more than ftol relatively (a line search re-evaluating the same point at the
gradient's round-off floor), or when the optimiser proposes a log-parameter that is not
finite or whose parameter would overflow (|z| > LOG_LIMIT: L-BFGS-B, its curvature pairs
spoilt by round-off noise near the minimum, can step to inf); :class:`Monitor` raises
:class:`Stop` from inside the objective, and the best point evaluated is returned.
"""
from __future__ import annotations

import numpy as np

EXACT_FIT = float(np.finfo(float).eps)  # J / J0 at or below it: the data are fitted to round-off
LOG_LIMIT = 700.0  # exp(700) ~ 1e304: a parameter beyond it overflows (or underflows below -700)


class Stop(Exception):
    """Raised by :class:`Monitor` to end a minimisation; ``reason`` says why."""

    def __init__(self, reason: str, converged: bool = False):
        super().__init__(reason)
        self.reason, self.converged = reason, converged


def projected_gradient(z, g, lo, hi) -> float:
    """||z - clip(z - g, lo, hi)||_inf: 0 exactly at a KKT point of min f on [lo, hi]."""
    return float(np.abs(z - np.clip(z - g, lo, hi)).max())


class Monitor:
    """Counts evaluations of J, keeps the best point, and stops a stall or an exhausted budget."""

    def __init__(self, ftol: float, maxfun: int, stall: int):
        self.ftol, self.maxfun, self.stall = ftol, maxfun, stall
        self.evaluations, self.best_J, self.best_z, self.since_best = 0, np.inf, None, 0
        self.previous = None  # J at the last accepted iteration

    def proposed(self, z) -> None:
        """Raise Stop before evaluating a point no parameter can take (non-finite or |z| > LOG_LIMIT)."""
        if not bool(np.all(np.abs(z) <= LOG_LIMIT)):
            raise Stop(f"the optimiser proposed a log-parameter that is NaN or beyond +-{LOG_LIMIT:g} "
                       "(a line search lost in round-off near the minimum): the best point is "
                       "returned; raise gtol or ftol")

    def evaluated(self, z, J: float) -> None:
        """Record J(z); raise Stop on a stall or when the budget is spent."""
        self.evaluations += 1
        if self.evaluations == 1 or J < self.best_J - self.ftol * abs(self.best_J):
            self.since_best = 0
        else:
            self.since_best += 1
        if J < self.best_J:
            self.best_J, self.best_z = J, np.array(z, copy=True)
        if self.since_best >= self.stall:
            raise Stop(f"stalled: {self.stall} evaluations in a row lowered J by at most ftol={self.ftol:g} "
                       "relatively (the gradient is at its round-off floor); raise gtol or ftol")
        if self.evaluations >= self.maxfun:
            raise Stop(f"maxfun={self.maxfun} evaluations spent: raise maxfun")

    def iteration(self, J: float) -> None:
        """An accepted iteration with value J: Stop (converged) if J fell, by <= ftol relatively."""
        previous, self.previous = self.previous, J
        if previous is not None and 0 < previous - J <= self.ftol * abs(previous):
            raise Stop(f"relative decrease of J over the last iteration "
                       f"{(previous - J) / abs(previous) if previous else 0.0:.3g} <= ftol={self.ftol:g}",
                       converged=True)
