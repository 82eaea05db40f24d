"""Piecewise-polynomial interpolation in one scalar (the horizon delta) of stacked arrays,
evaluated in torch so that it is differentiable in that scalar.

The operator's dependence on delta is smooth between breakpoints (where the partial volume of a
bond length r switches on or saturates: delta = r -/+ h/2) and only C1 (``rule="smooth"``) or C0
(``"linear"``) across them; one global spline converges slowly through all those kinks, a
polynomial on each smooth piece spectrally. Chebyshev points of the second kind include the
ends, so neighbouring pieces agree at their common breakpoint: the interpolant is continuous,
and its derivative jumps only by the interpolation error.
"""
from __future__ import annotations

import numpy as np
import torch


def chebyshev_points(n: int) -> np.ndarray:
    """n Chebyshev points of the second kind on [0, 1], both ends included."""
    return 0.5 * (1 - np.cos(np.pi * np.arange(n) / (n - 1)))


def check_points(n: int) -> np.ndarray:
    """The n - 1 points halfway (in angle) between consecutive Chebyshev points: where the
    interpolation error of a smooth function peaks."""
    return 0.5 * (1 - np.cos(np.pi * (np.arange(n - 1) + 0.5) / (n - 1)))


class Piecewise:
    """Polynomials of degree n - 1 on the pieces [breaks[k], breaks[k + 1]], each through the
    values at its n Chebyshev points; ``values[k]`` has shape (n, ...). ``piecewise(x)`` for a
    scalar x in [breaks[0], breaks[-1]]."""

    def __init__(self, breaks, values: list):
        self.breaks = torch.as_tensor(np.asarray(breaks, dtype=np.float64))
        n = values[0].shape[0]
        vander = np.vander(chebyshev_points(n), n)  # highest power first
        self.coef = torch.as_tensor(np.stack([np.linalg.solve(vander, v.reshape(n, -1)).reshape(v.shape)
                                              for v in values], axis=1))  # (n, pieces, ...)

    @property
    def range(self) -> tuple[float, float]:
        return float(self.breaks[0]), float(self.breaks[-1])

    def __call__(self, x) -> torch.Tensor:
        x = torch.as_tensor(x, dtype=torch.float64)
        low, high = self.range
        if not low - 1e-12 * abs(low) <= float(x.detach()) <= high + 1e-12 * abs(high):
            raise ValueError(f"delta = {float(x):.6g} is outside the range [{low:.6g}, {high:.6g}] "
                             "the reduced operators were built on: rebuild the reduced model with "
                             "a delta_range that covers it (or a prior inside it)")
        k = int(torch.searchsorted(self.breaks[1:-1], x.detach(), right=True))
        s = (x - self.breaks[k]) / (self.breaks[k + 1] - self.breaks[k])
        out = self.coef[0, k]
        for c in self.coef[1:, k]:
            out = out * s + c
        return out
