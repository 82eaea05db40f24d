"""Phase 2 of paper 004's learning by simulation: s0 of the smoothed damage law (eq 3.10) as the
minimiser of the PD-MD discrepancy of the dynamic forward run (``bayespd.learn.forward``).

Why not the equation residual of eq 4.9 (the paper's phase 2): evaluated on the coarse data with
the intact LPS operator and without the free-surface correction (eqs 3.13-3.21), the elastic force
K u / V was 10-100x the coarse inertia before any MD bond broke, so every broken bond lowered the
residual and its minimiser sat at the lower bound s0 -> 0 (docs/results.md, "MD learning"). The
paper's own accuracy metric is the time-averaged relative discrepancy between the PD prediction
and the coarse-grained MD fields (sec. 5.2); minimising it over the training frames learns s0 from
what the model is used for, and needs no second time derivative of noisy coarse data.

Metric (the paper's "averaged (in time) ... normalized with respect to the ground truth"):

    E(a, a_md) = mean over frames n with a_md^n != 0 of ||a^n - a_md^n||_2 / ||a_md^n||_2,

over the evaluated nodes, a the displacement (N, 2) or the damage index (N,).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
import scipy.optimize

from bayespd.validate import positive


def relative_error(pred, data, nodes=None) -> float:
    """E of the module docstring for (F, N[, 2]) arrays over ``nodes`` (bool (N,); None: all)."""
    pred, data = np.asarray(pred, float), np.asarray(data, float)
    if pred.shape != data.shape:
        raise ValueError(f"prediction {pred.shape} and data {data.shape} must have one shape (frames, nodes[, 2])")
    if nodes is not None:
        pred, data = pred[:, nodes], data[:, nodes]
    axes = tuple(range(1, data.ndim))
    norm = np.sqrt((data**2).sum(axes))
    used = norm > 0
    if not used.any():
        raise ValueError("the data are zero at every frame: the relative error is undefined")
    return float((np.sqrt(((pred - data) ** 2).sum(axes))[used] / norm[used]).mean())


@dataclass
class S0Fit:
    """The learned s0, its discrepancy, the discrepancy with no damage (s0 -> infinity), every
    evaluated (s0, discrepancy) pair and the wall time."""
    s0: float
    error: float
    error_intact: float
    evaluations: list = field(default_factory=list)
    wall_time_s: float = 0.0


def learn_s0(discrepancy: Callable[[float | None], float], bounds=(0.01, 1.0), xatol: float = 0.01) -> S0Fit:
    """argmin of ``discrepancy(s0)`` (a forward run and its E against the training frames) by
    bounded Brent on log s0 to ``xatol`` in log s0; ``discrepancy(None)`` is the undamaged run."""
    lo, hi = (positive("bounds", b, "pass 0 < low < high") for b in bounds)
    if not lo < hi:
        raise ValueError(f"bounds must satisfy low < high, got {bounds}")
    t0 = time.perf_counter()
    seen = []

    def objective(z):
        s0 = float(np.exp(z))
        e = discrepancy(s0)
        seen.append((s0, e))
        return e

    res = scipy.optimize.minimize_scalar(objective, bounds=(np.log(lo), np.log(hi)), method="bounded",
                                         options={"xatol": xatol})
    return S0Fit(float(np.exp(res.x)), float(res.fun), discrepancy(None), seen, time.perf_counter() - t0)
