"""Volume-constrained Dirichlet layers, distributed loads, and reduction to free dofs."""
from __future__ import annotations

from functools import cached_property

import numpy as np
import torch

from bayespd.discretize import Particles
from bayespd.linalg.sparse import Pattern
from bayespd.validate import finite


class Dirichlet:
    """Prescribed displacement on a region (a layer at least delta thick, Delorme 2018 §3.1).

    ``value`` gives one entry per component; ``None`` leaves that component free
    (e.g. ``(None, 0.0)`` is a roller). ``depth`` is the layer thickness when known, so the
    scene can check it covers the horizon.
    """

    def __init__(self, mask: np.ndarray, value=(0.0, 0.0), depth: float | None = None):
        self.mask = np.asarray(mask, dtype=bool)
        if not self.mask.any():
            raise ValueError("the Dirichlet region is empty: check the mask or layer depth")
        self.value, self.depth = tuple(value), depth
        for c, v in enumerate(self.value):
            if v is not None:
                finite(f"the Dirichlet value of component {c}", v,
                       "give a finite displacement (None leaves a component free)")

    @staticmethod
    def layer(particles: Particles, side: str, depth: float, value=(0.0, 0.0)) -> "Dirichlet":
        """Constrain a layer of thickness ``depth`` (>= delta) along one side."""
        return Dirichlet(particles.layer(side, depth), value, depth)


class Load:
    """A total force spread over a region in proportion to particle volume."""

    def __init__(self, mask: np.ndarray, force):
        self.mask = np.asarray(mask, dtype=bool)
        if not self.mask.any():
            raise ValueError("the load region is empty: check the mask or layer depth")
        self.force = torch.as_tensor(finite("the load", force, "pass a finite force"), dtype=torch.get_default_dtype())

    def nodal(self, particles: Particles) -> torch.Tensor:
        """Nodal forces (N, dim): F * V_i / sum V over the region."""
        if self.force.shape != (particles.dim,):
            raise ValueError(f"force must have {particles.dim} components")
        if self.mask.shape != (particles.n,):
            raise ValueError(f"the load region's mask has shape {self.mask.shape}, not one entry per particle ({particles.n})")
        w = torch.as_tensor(np.where(self.mask, particles.volume, 0.0))
        return (w / w.sum())[:, None] * self.force


class Constraints:
    """Splits dofs into prescribed and free; K u = f becomes K_ff u_f = f_f - K_fc u_c."""

    def __init__(self, particles: Particles, pattern: Pattern | None, dirichlet: list[Dirichlet]):
        n, dim = particles.n, particles.dim
        fixed = np.zeros((n, dim), dtype=bool)
        prescribed = np.zeros((n, dim))
        for bc in dirichlet:
            if bc.mask.shape != (n,):
                raise ValueError(f"the Dirichlet region's mask has shape {bc.mask.shape}, not one entry per particle ({n})")
            if len(bc.value) != dim:
                raise ValueError(f"Dirichlet value needs {dim} components (None = free)")
            for c, v in enumerate(bc.value):
                if v is not None:
                    fixed[bc.mask, c] = True
                    prescribed[bc.mask, c] = v
        self.shape = (n, dim)
        self.fixed_particles = fixed.any(axis=1)
        self.prescribed = torch.as_tensor(prescribed)
        self.has_prescribed = bool(np.any(prescribed))
        self.free_mask = free = ~fixed.reshape(-1)
        self._full_pattern = pattern  # None: a matrix-free solver needs no pattern
        self.free_dofs = np.flatnonzero(free)  # flat dof indices d*i + a of the free dofs
        self._free_idx = torch.as_tensor(self.free_dofs)

    @cached_property
    def _restricted(self):
        if self._full_pattern is None:
            raise ValueError("these constraints were built without a pattern (matrix-free solver)")
        sub, entries = self._full_pattern.restrict(self.free_mask)
        return sub, torch.as_tensor(entries)

    @property
    def pattern(self) -> Pattern:
        """K_ff's pattern (built on first use)."""
        return self._restricted[0]

    def free_values(self, values: torch.Tensor) -> torch.Tensor:
        """Values of K_ff from values of K on the full pattern."""
        return values[self._restricted[1]]

    def free(self, x: torch.Tensor) -> torch.Tensor:
        """The free dofs of a nodal field (N, dim)."""
        return x.reshape(-1)[self._free_idx]

    def embed(self, x_free: torch.Tensor) -> torch.Tensor:
        """A nodal field (N, dim) equal to x_free on the free dofs and zero elsewhere."""
        x = torch.zeros(self.shape[0] * self.shape[1], dtype=x_free.dtype)
        return x.index_put((self._free_idx,), x_free).reshape(self.shape)

    def expand(self, u_free: torch.Tensor) -> torch.Tensor:
        """Full displacement (N, dim): the free dofs plus the prescribed values."""
        return self.embed(u_free) + self.prescribed.to(u_free.dtype)
