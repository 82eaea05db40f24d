"""Choice of the Tikhonov weight psi (Turner 2015 eq 12 leaves it "tunable").

* Discrepancy principle (Morozov): the psi whose residual rms equals tau times the noise sd,
  found by a sweep and bisection in log psi (the residual grows with psi).
* L-curve (Hansen): the corner of (log ||misfit||, log ||L (z - z_ref)||) parametrised by
  t = log psi, where the signed curvature
  kappa = (x' y'' - x'' y') / (x'^2 + y'^2)^(3/2) is largest.

Both call :func:`bayespd.inverse.tikhonov` (module ``least_squares``) with warm starts and return a
:class:`PsiChoice` holding the sweep, so both choices can be reported side by side; a sweep
made once with :func:`psi_sweep` can be passed to both (``sweep=``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from bayespd.inverse.least_squares import TikhonovResult, tikhonov


@dataclass
class PsiChoice:
    """The chosen ``psi``, the inversion at it (``result``) and the sweep behind the choice."""

    psi: float
    result: TikhonovResult
    rule: str
    psis: np.ndarray
    residual_rms: np.ndarray
    misfit_norm: np.ndarray
    penalty_norm: np.ndarray
    attained: bool | None = None  # discrepancy: whether the target residual was reached
    curvature: np.ndarray | None = None


def psi_sweep(scene, y, init: dict, psis, ref: dict | None = None, **kwargs):
    """(sorted psis, TikhonovResult per psi), solved from the largest psi down, each warm-starting
    the next; ``ref`` defaults to ``init``, ``kwargs`` go to ``tikhonov``."""
    ref = ref if ref is not None else init
    psis = np.sort(np.asarray(psis, dtype=float))
    if psis.ndim != 1 or len(psis) < 2 or not np.all(np.isfinite(psis)) or psis[0] <= 0:
        raise ValueError("psis must be at least two finite, positive values (a log-spaced sweep)")
    results, start = [], init
    for psi in psis[::-1]:  # from strong to weak: each warm-starts the next
        results.append(tikhonov(scene, y, start, psi=float(psi), ref=ref, **kwargs))
        start = results[-1].params
    return psis, results[::-1]


def _arrays(results, attr):
    return np.array([getattr(r, attr) for r in results])


def discrepancy(scene, y, init: dict, *, noise: float | None, psis=None, tau: float = 1.0,
                rtol: float = 1e-3, ref: dict | None = None, max_bisections: int = 40,
                sweep=None, **kwargs) -> PsiChoice:
    """psi with residual_rms = tau * ``noise`` (the observation noise sd, required), bracketed
    by a sweep over ``psis`` (or the given ``sweep`` of :func:`psi_sweep`), then bisected.

    If even the smallest psi misfits by more (model error dominates) or the largest by less,
    the end of the sweep is returned with ``attained=False``. ``kwargs`` go to ``tikhonov``."""
    if noise is None:
        raise ValueError("the discrepancy principle needs the noise level: pass noise= (the "
                         "standard deviation of the observation noise), or use the L-curve")
    if not (math.isfinite(noise) and noise > 0) or not tau > 0:
        raise ValueError(f"noise and tau must be finite and positive, got {noise}, {tau}")
    ref = ref if ref is not None else init
    psis, results = sweep or psi_sweep(scene, y, init, psis, ref, **kwargs)
    rms = _arrays(results, "residual_rms")
    target = tau * noise
    above = np.flatnonzero(rms > target)
    if len(above) == 0 or above[0] == 0:
        k = len(psis) - 1 if len(above) == 0 else 0
        return _choice(psis[k], results[k], "discrepancy", psis, results, attained=False)
    lo, hi = above[0] - 1, above[0]
    t_lo, t_hi, chosen = math.log(psis[lo]), math.log(psis[hi]), results[lo]
    for _ in range(max_bisections):
        t = 0.5 * (t_lo + t_hi)
        res = tikhonov(scene, y, chosen.params, psi=math.exp(t), ref=ref, **kwargs)
        if abs(res.residual_rms / target - 1) <= rtol:
            return _choice(math.exp(t), res, "discrepancy", psis, results, attained=True)
        if res.residual_rms > target:
            t_hi = t
        else:
            t_lo, chosen = t, res
    return _choice(math.exp(t), res, "discrepancy", psis, results, attained=False)


def lcurve_corner(psis, misfit, penalty) -> tuple[float, np.ndarray]:
    """psi at the L-curve's point of largest curvature, and the curvature at each psi.

    The curve (log misfit, log penalty) is differentiated in t = log psi with second-order
    differences (np.gradient, uneven spacing allowed); the maximum over interior points is
    refined by a parabola through it and its neighbours."""
    t = np.log(np.asarray(psis, dtype=float))
    if len(t) < 5:
        raise ValueError("the L-curve needs at least 5 values of psi to locate a corner")
    norms = np.asarray([misfit, penalty], dtype=float)
    if not (np.all(np.isfinite(norms)) and np.all(norms > 0)):
        raise ValueError("the misfit and penalty norms must be positive and finite along the sweep")
    x, y = np.log(norms)
    dx, dy = np.gradient(x, t), np.gradient(y, t)
    ddx, ddy = np.gradient(dx, t), np.gradient(dy, t)
    kappa = (dx * ddy - ddx * dy) / np.maximum(dx**2 + dy**2, 1e-300) ** 1.5
    k = 1 + int(np.argmax(kappa[1:-1]))
    (a, b, _) = np.polyfit(t[k - 1:k + 2], kappa[k - 1:k + 2], 2)
    t_star = -b / (2 * a) if a < 0 else t[k]
    return float(np.exp(np.clip(t_star, t[k - 1], t[k + 1]))), kappa


def lcurve(scene, y, init: dict, *, psis=None, ref: dict | None = None, sweep=None, **kwargs) -> PsiChoice:
    """psi at the L-curve corner (:func:`lcurve_corner`) of a sweep over ``psis`` (or the
    given ``sweep`` of :func:`psi_sweep`)."""
    ref = ref if ref is not None else init
    psis, results = sweep or psi_sweep(scene, y, init, psis, ref, **kwargs)
    psi, kappa = lcurve_corner(psis, _arrays(results, "misfit_norm"), _arrays(results, "penalty_norm"))
    start = results[int(np.argmin(np.abs(np.log(psis / psi))))].params
    res = tikhonov(scene, y, start, psi=psi, ref=ref, **kwargs)
    return _choice(psi, res, "lcurve", psis, results, curvature=kappa)


def _choice(psi, result, rule, psis, results, **extra) -> PsiChoice:
    return PsiChoice(float(psi), result, rule, psis, _arrays(results, "residual_rms"),
                     _arrays(results, "misfit_norm"), _arrays(results, "penalty_norm"), **extra)
