"""Bonds found once at ``delta_max``, with partial-volume weights continuous in delta."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from scipy.spatial import cKDTree

from bayespd.discretize import Particles


@dataclass(frozen=True)
class Bonds:
    """Each interacting pair once (i < j): ``xi = x[j] - x[i]`` and ``length = |xi|``.

    Pairs are kept up to ``delta_max + h/2`` so that every horizon ``delta <= delta_max``
    is represented by :func:`partial_volume` alone.
    """

    i: np.ndarray
    j: np.ndarray
    xi: np.ndarray
    length: np.ndarray
    h: float
    delta_max: float

    @property
    def n(self) -> int:
        return len(self.i)

    def weight(self, delta) -> torch.Tensor:
        """Partial-volume fraction of each bond at horizon ``delta`` (see partial_volume)."""
        check_horizon(delta, self.h, self.delta_max)
        return partial_volume(torch.as_tensor(self.length), delta, self.h)


def find_bonds(particles: Particles, delta_max: float) -> Bonds:
    """All pairs closer than ``delta_max + h/2``, found once with a k-d tree."""
    h = particles.h
    if not delta_max >= h:
        raise ValueError(f"delta_max={delta_max} must be at least the grid spacing h={h}")
    pairs = cKDTree(particles.x).query_pairs(delta_max + h / 2, output_type="ndarray")
    order = np.lexsort((pairs[:, 1], pairs[:, 0]))
    i, j = pairs[order, 0].astype(np.int64), pairs[order, 1].astype(np.int64)
    xi = particles.x[j] - particles.x[i]
    return Bonds(i, j, xi, np.linalg.norm(xi, axis=1), h, float(delta_max))


def partial_volume(length: torch.Tensor, delta, h: float) -> torch.Tensor:
    """Fraction of a neighbour cell inside the horizon, piecewise linear in delta.

    1 for |xi| <= delta - h/2, 0 for |xi| >= delta + h/2, linear between, so every quantity
    built from it is continuous in delta with a gradient almost everywhere.
    """
    return torch.clamp((torch.as_tensor(delta) + h / 2 - length) / h, 0.0, 1.0)


def check_horizon(delta, h: float, delta_max: float) -> None:
    """Refuse a horizon outside [h, delta_max] with a message that names the fix."""
    d = float(torch.as_tensor(delta).detach())
    if not np.isfinite(d):
        raise ValueError(f"delta must be finite, got {d}")
    if d < h:
        raise ValueError(f"delta={d:g} is smaller than the grid spacing h={h:g}: "
                         "use delta >= h (typically 2h to 4h)")
    if d > delta_max * (1 + 1e-12):
        raise ValueError(f"delta={d:g} exceeds delta_max={delta_max:g} used for the bond "
                         "search: build the scene with a larger delta_max")
