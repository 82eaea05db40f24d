"""A symmetry plane: half of a mirror-symmetric body, exact, through mirror (ghost) particles.

A peridynamic particle near the plane bonds with particles across it, so the plane is not a
free edge. Fixing the normal component on a layer at the plane forces u_n = 0 where the full
body has u_n(at + s) = -u_n(at - s) != 0, and a single column leaves the particles next to it
with half their families: both bias the half-model (``tests/test_symmetry.py`` shows it). Here
the half is kept with a layer of ghosts, the mirror images x_g = M x_m of the kept particles
within ``depth`` of the plane (M reflects the normal component), whose displacement is slaved
to their images: u_g = M u_m (the symmetric field, extended by E: u_ext = E u). The half-model
is the full model's equilibrium at the kept particles,

    S K_ext E u = f_kept,                                                            (1)

S the kept rows. It is exact when the ghosts reach as far as the kept rows of K_ext reach, two
bond lengths for state-based laws (the dilatation of a neighbour reads its own family), so
depth = 2 (delta_max + h). S K E is symmetric: K_{i,g(j)} M = M K_{j,g(i)}^T by the mirror
symmetry of the full operator, so the scene's SPD solve and its adjoint apply unchanged. Loads,
Dirichlet regions and observations are declared on the kept particles; the loads are the half
body's (half a load that straddles the plane).
"""
from __future__ import annotations

import numpy as np
import torch

from bayespd.bonds import Bonds
from bayespd.discretize import Particles
from bayespd.linalg.sparse import Pattern
from bayespd.validate import count, finite, positive


class SymmetryPlane:
    """The plane x[axis] = ``at`` of a body whose kept half is ``particles`` (all on one side,
    none on the plane: a cell-centred grid with a cell face on the plane, e.g. ``bp.grid_2d`` of
    the half). ``extended``: the kept particles then the ghosts, to build the material on
    (``bp.LPS(plane.extended, bp.find_bonds(plane.extended, delta_max))``); ``fold(material)``:
    the material of the half-model (eq 1 of the module docstring) for a ``bp.Scene``."""

    def __init__(self, particles: Particles, axis: int, at: float, delta_max: float):
        count("axis", axis, 0)
        if axis >= particles.dim:
            raise ValueError(f"axis must be < {particles.dim} (the normal of the plane), got {axis}")
        finite("at", at, "pass the plane's coordinate along axis")
        positive("delta_max", delta_max, "pass the horizon the bonds are found at")
        side = particles.x[:, axis] - at
        if np.any(np.abs(side) < 1e-6 * particles.h) or (side.min() < 0 < side.max()):
            raise ValueError(f"the particles must lie strictly on one side of the plane x[{axis}] = {at}, none "
                             "on it: keep one half of a grid whose cell faces lie on the plane (e.g. bp.grid_2d "
                             "of the half)")
        self.particles, self.axis, self.at, self.delta_max = particles, axis, float(at), float(delta_max)
        self.depth = 2 * (delta_max + particles.h)
        self.master = np.flatnonzero(np.abs(side) < self.depth)
        ghosts = particles.x[self.master].copy()
        ghosts[:, axis] = 2 * self.at - ghosts[:, axis]
        self.extended = Particles(np.concatenate([particles.x, ghosts]),
                                  np.concatenate([particles.volume, particles.volume[self.master]]),
                                  particles.h, particles.thickness)
        self.sign = np.ones(particles.dim)
        self.sign[axis] = -1.0

    def fold(self, material) -> "Folded":
        """The half-model's material: ``material`` built on ``extended``, folded by eq 1."""
        if material.particles is not self.extended:
            raise ValueError("build the material on plane.extended (the kept particles and their ghosts)")
        if material.bonds.delta_max > self.delta_max:
            raise ValueError(f"the material's bonds reach delta_max={material.bonds.delta_max:g} > the plane's "
                             f"delta_max={self.delta_max:g}: build the plane with the bonds' delta_max")
        return Folded(self, material)


class Folded:
    """A material on the kept particles whose operator is S K_ext E (``SymmetryPlane.fold``):
    what the linear static ``Scene`` uses of a material (pattern, differentiable stiffness and
    form, bonds among the kept particles), for the direct solver."""

    matrix_free = False  # Scene(solver="auto") solves it directly at any size

    def __init__(self, plane: SymmetryPlane, material):
        self.base, self.particles = material, plane.particles
        self.param_names, self.moduli_names = material.param_names, material.moduli_names
        n, d = plane.particles.n, plane.particles.dim
        self._master = torch.as_tensor(plane.master)
        self._sign = torch.as_tensor(plane.sign)
        b = material.bonds
        kept = b.j < n  # i < j: both ends kept
        self.bonds = Bonds(b.i[kept], b.j[kept], b.xi[kept], b.length[kept], b.h, b.delta_max, b.rule)
        pattern = material.pattern
        rows = np.flatnonzero(pattern.rows < n * d)
        node, comp = np.divmod(pattern.cols[rows], d)
        ghost = node >= n
        cols = np.where(ghost, plane.master[np.where(ghost, node - n, 0)] * d + comp, pattern.cols[rows])
        sign = np.where(ghost, plane.sign[comp], 1.0)
        keys, target = np.unique(cols * (n * d) + pattern.rows[rows], return_inverse=True)
        self.pattern = Pattern(keys % (n * d), keys // (n * d), n * d)
        self._source, self._target = torch.as_tensor(rows), torch.as_tensor(target.reshape(-1))
        self._entry_sign = torch.as_tensor(sign)

    def _fold(self, values: torch.Tensor) -> torch.Tensor:
        """Values of S K E on ``pattern`` from values of K_ext on the base pattern."""
        return torch.zeros(self.pattern.nnz, dtype=values.dtype).index_add(
            0, self._target, self._entry_sign * values[self._source])

    def stiffness(self, params: dict) -> torch.Tensor:
        return self._fold(self.base.stiffness(params))

    def numeric_stiffness(self, params: dict) -> torch.Tensor:
        return self._fold(self.base.numeric_stiffness(params))

    def extend(self, u: torch.Tensor) -> torch.Tensor:
        """E u: the kept field (n, dim) and its mirror image on the ghosts."""
        u = u.reshape(self.particles.n, -1)
        return torch.cat([u, u[self._master] * self._sign])

    def form(self, params: dict, v: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """v^T S K_ext E u (the ghosts' test functions zero)."""
        v = v.reshape(self.particles.n, -1)
        return self.base.form(params, torch.cat([v, torch.zeros(len(self._master), v.shape[1], dtype=v.dtype)]),
                              self.extend(u))

    def grams(self):
        raise ValueError("a symmetry half-model is solved with the direct solver: drop solver='pcg'")
