"""A periodic sheet of grid nodes for the non-fracture data of paper 004 (eq 5.1 loads on a periodic
MD box): nodes, minimum-image bonds, the static solve and the Fourier symbol of the operator.

The grid has ``n`` nodes a side on the box (Lx, Ly); when Lx != Ly the cells are hx x hy and the
partial-volume rule uses h = sqrt(hx hy) (the bond lengths are exact). A periodic body moves
freely as a whole, so the solve pins one node and returns the zero-mean displacement, after
removing the net force from each load (a periodic body balances only self-equilibrated loads).
"""
from __future__ import annotations

from functools import cached_property

import numpy as np
import torch
from scipy.spatial import cKDTree

from bayespd.boundary import Dirichlet, Load
from bayespd.bonds import Bonds
from bayespd.discretize import from_points
from bayespd.problem import Scene
from bayespd.validate import count, positive


NODE_ZERO = (0, 1)  # K's rows of node 0's two dofs: the symbol's


def periodic_grid(box, n: int):
    """Cell-centred nodes (n * n, 2) on [0, Lx) x [0, Ly) and their ``Particles`` (thickness 1,
    cell area hx hy, h = sqrt(hx hy))."""
    box = np.asarray(positive("box", box, "pass the periodic box lengths (Lx, Ly)"), float)
    count("n", n, 4, "use at least 4 nodes a side")
    hx, hy = box / n
    gx, gy = (np.arange(n) + 0.5) * hx, (np.arange(n) + 0.5) * hy
    x = np.stack(np.meshgrid(gx, gy, indexing="ij"), -1).reshape(-1, 2)
    return from_points(x, np.full(len(x), hx * hy), h=float(np.sqrt(hx * hy)))


def periodic_bonds(particles, box, delta_max: float, rule: str = "linear") -> Bonds:
    """All minimum-image pairs closer than ``delta_max + h/2`` (``bayespd.bonds.find_bonds`` on a
    torus); refuses a horizon that would let a node meet its own image."""
    box, h = np.asarray(box, float), particles.h
    if not delta_max + h / 2 < box.min() / 2:
        raise ValueError(f"delta_max + h/2 = {delta_max + h / 2:g} must stay below half the periodic box "
                         f"({box.min() / 2:g}): lower delta_max or use a larger box")
    pairs = cKDTree(np.mod(particles.x, box), boxsize=box).query_pairs(delta_max + h / 2, output_type="ndarray")
    pairs = pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))]
    i, j = pairs[:, 0].astype(np.int64), pairs[:, 1].astype(np.int64)
    xi = particles.x[j] - particles.x[i]
    xi -= np.round(xi / box) * box
    return Bonds(i, j, xi, np.linalg.norm(xi, axis=1), h, float(delta_max), rule)


class PeriodicSheet:
    """Static solves of a material built on ``periodic_bonds`` over ``box`` for many loads at once."""

    def __init__(self, material, box):
        p = material.particles
        self.box = np.asarray(box, float)
        pin = np.zeros(p.n, bool)
        pin[0] = True
        # the scene's own load is never solved for (``solve`` passes its loads as columns); a
        # scene needs one, so this is a unit force on the free nodes
        self.scene = Scene(material, [Dirichlet(pin)], [Load(~pin, (1.0, 0.0))], solver="direct")
        self.material, self.n = material, p.n
        self.volume = torch.as_tensor(p.volume)

    def zero_mean(self, u: torch.Tensor) -> torch.Tensor:
        """u (..., N, 2) less its volume-weighted mean: the part a periodic body determines."""
        w = self.volume / self.volume.sum()
        return u - (w[:, None] * u).sum(-2, keepdim=True)

    def solve(self, params: dict, forces: torch.Tensor) -> torch.Tensor:
        """Zero-mean displacements (k, N, 2) under nodal forces (k, N, 2) (net force removed);
        differentiable in every param (one factorisation, one adjoint solve for all k)."""
        forces = torch.as_tensor(forces, dtype=torch.float64)
        if forces.ndim != 3 or forces.shape[1:] != (self.n, 2):
            raise ValueError(f"forces must be (loads, {self.n}, 2), got {tuple(forces.shape)}")
        f = forces - forces.mean(1, keepdim=True)
        c = self.scene.constraints
        rhs = torch.stack([c.free(fk) for fk in f], 1)
        u = self.scene.solve_free(params, rhs)
        return self.zero_mean(torch.stack([c.expand(u[:, k]) for k in range(len(f))]))

    @cached_property
    def _row(self):
        """Entries of K's two rows of node 0 on the pattern: (positions, row component, column
        node, column component)."""
        pat = self.material.pattern
        at = pat.in_rows(NODE_ZERO)
        return at, pat.rows[at], pat.cols[at] // 2, pat.cols[at] % 2

    def symbol(self, params: dict, wavevectors: torch.Tensor) -> torch.Tensor:
        """The 2x2 symbol S(k) = sum_j K_0j cos(k . xi_0j) (k, 2, 2) of the translation-invariant
        operator, whose eigenvalues are K's eigenvalues at the lattice wavevectors; differentiable."""
        at, a, j, b = self._row
        values = self.material.stiffness(params, NODE_ZERO)
        x = self.material.particles.x
        box = self.box
        off = x[j] - x[0]
        off -= np.round(off / box) * box
        phase = torch.cos(torch.as_tensor(wavevectors) @ torch.as_tensor(off).T)  # (k, entries)
        S = torch.zeros(len(wavevectors), 2, 2, dtype=values.dtype)
        index = torch.as_tensor(2 * a + b)
        return S.reshape(len(wavevectors), 4).index_add(1, index, phase * values).reshape(-1, 2, 2)

    @cached_property
    def _fft_wavevectors(self) -> torch.Tensor:
        """The lattice wavevectors in FFT order (n, n, 2) (nodes are ordered x-major, as ``periodic_grid``)."""
        n = int(round(np.sqrt(self.n)))
        m = np.fft.fftfreq(n, 1.0 / n)
        return torch.as_tensor(np.stack(np.meshgrid(m, m, indexing="ij"), -1) * 2 * np.pi / self.box)

    @property
    def wavevectors(self) -> torch.Tensor:
        """Every non-zero wavevector of the n x n periodic lattice (n * n - 1, 2)."""
        return self._fft_wavevectors.reshape(-1, 2)[1:]

    def spectral_solve(self, params: dict, forces: torch.Tensor) -> torch.Tensor:
        """``solve`` by Fourier diagonalisation: K is block-circulant on the periodic grid, so
        u_hat(k) = S(k)^-1 f_hat(k) for k != 0 and u_hat(0) = 0 (zero mean, net force removed).
        The same numbers as the sparse solve (tests/learn/test_periodic.py) at a fraction of its
        cost; differentiable through the symbol."""
        forces = torch.as_tensor(forces, dtype=torch.float64)
        n = int(round(np.sqrt(self.n)))
        f_hat = torch.fft.fft2(forces.reshape(-1, n, n, 2), dim=(1, 2))
        S = self.symbol(params, self.wavevectors)
        inv = torch.linalg.inv(S).to(f_hat.dtype)
        u_hat = torch.zeros_like(f_hat)
        u_hat.reshape(len(forces), -1, 2)[:, 1:] = torch.einsum("kab,mkb->mka", inv, f_hat.reshape(len(forces), -1, 2)[:, 1:])
        return torch.fft.ifft2(u_hat, dim=(1, 2)).real.reshape(len(forces), self.n, 2)
