"""Quadrature over one scalar site on a grid of increasing points: the log density interpolated
linearly between neighbouring points (in log site for a scale) and integrated exactly.

Exact for a density exponential in the variable between points, so a cusp (a kink of the log
density, as the bond weights make in the PD horizon: ``bayespd.bonds.Bonds.kinks``) costs nothing
when it is a grid point, where the midpoint rule errs by O(step / width) at a cusp of width
``width``; for a smooth log density L each cell errs by O(step^3 L''), as the trapezoid rule on L
(O(step^2) in all).
Each point owns the halves of its two cells (the ends one half: the integral runs from the first
point to the last, so their weights should be negligible).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from scipy.special import expit

TINY = 1e-9  # |slope x half-cell| below which exp(slope t) is 1 + slope t to rounding


@dataclass(frozen=True)
class GridAxis:
    """``site`` integrated over ``grid`` (increasing, >= 3 points, any spacing), in log site when
    ``log`` (a scale: its density over log site carries the Jacobian site)."""
    site: str
    grid: np.ndarray
    log: bool = False

    def __post_init__(self):
        grid = np.asarray(self.grid, float)
        if grid.ndim != 1 or len(grid) < 3 or not np.all(np.diff(grid) > 0) or not np.all(np.isfinite(grid)):
            raise ValueError(f"the grid of {self.site!r} must be >= 3 finite increasing points, got {self.grid}")
        if self.log and not grid[0] > 0:
            raise ValueError(f"the grid of {self.site!r} is integrated in log: its points must be positive, got {grid}")
        object.__setattr__(self, "grid", grid)

    @property
    def x(self) -> np.ndarray:
        """The variable integrated over: log site or site."""
        return np.log(self.grid) if self.log else self.grid

    def log_jacobian(self, i: int) -> float:
        return math.log(self.grid[i]) if self.log else 0.0

    def log_weights(self, L) -> np.ndarray:
        """Each point's log weight: log of the integral of exp(l - L_i) over its half-cells, l the
        linear interpolant of the points' log densities ``L`` (over x)."""
        return np.logaddexp(*self._half_cells(np.asarray(L, float)).T)

    def draw(self, i: int, L, count: int, generator: torch.Generator) -> torch.Tensor:
        """``count`` values of the site from point i's share of the interpolated density."""
        L = np.asarray(L, float)
        halves = self._half_cells(L)[i]
        right = torch.rand(count, generator=generator, dtype=torch.float64) < expit(halves[1] - halves[0])
        u = torch.rand(count, generator=generator, dtype=torch.float64)
        x = torch.full((count,), float(self.x[i]), dtype=torch.float64)
        for side, chosen in ((-1, ~right), (1, right)):
            k = i + side
            if 0 <= k < len(L) and bool(chosen.any()):
                d = (self.x[k] - self.x[i]) / 2  # signed half-cell
                s = (L[k] - L[i]) / (2 * d)  # slope of l along t = x - x_i
                x[chosen] += _inverse_cdf(u[chosen], s, d)
        return torch.exp(x) if self.log else x

    def _half_cells(self, L) -> np.ndarray:
        """(n, 2): per point the log integral of exp(l - L_i) over its left and right half-cells
        (-inf beyond the ends)."""
        half = np.diff(self.x) / 2
        rise = np.diff(L) / 2  # l's change over a half-cell, from the left point
        out = np.full((len(L), 2), -np.inf)
        out[:-1, 1] = np.log(half) + _log_exprel(rise)
        out[1:, 0] = np.log(half) + _log_exprel(-rise)
        return out


def _log_exprel(a) -> np.ndarray:
    """log((e^a - 1) / a), elementwise and stable for large |a| (log 1 at 0)."""
    a = np.asarray(a, float)
    out = a / 2  # small |a|
    big = np.abs(a) > TINY
    b = a[big]
    out[big] = np.where(b > 0, b + np.log(-np.expm1(-np.abs(b))) - np.log(np.abs(b)),
                        np.log(-np.expm1(-np.abs(b))) - np.log(np.abs(b)))
    return out


def _inverse_cdf(u: torch.Tensor, s: float, d: float) -> torch.Tensor:
    """t in [0, d] (or [d, 0]) with density proportional to exp(s t), from uniform u."""
    a = s * d
    if abs(a) <= TINY:
        return u * d
    if a > 0:  # the mass sits at the far end: measure from there
        return d + torch.log(u + (1 - u) * math.exp(-a)) / s
    return torch.log1p(u * math.expm1(a)) / s
