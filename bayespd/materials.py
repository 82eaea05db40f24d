"""Linearised peridynamic materials: stiffness values on a fixed pattern, differentiable in
the moduli (scalars or per-particle fields) and the horizon delta.

LPS (ordinary state-based linear peridynamic solid, seed 000 eqs 5-10, seed 001 eqs 18-19,
35-45). With the dilatation theta_i = (d/m_i) sum_j w x e V_j, the deviatoric extension
e^d = e - theta x / d and alpha = c_d G / m (c_2 = 8, c_3 = 15), the energy density
W_i = kappa/2 theta^2 + alpha/2 sum_j w (e^d)^2 V_j rewrites, using sum_j w x e^d V_j = 0, as

    W_i = (kappa_i / 2 - c_d G_i / (2 d^2)) theta_i^2 + (c_d G_i / (2 m_i)) sum_j w e_ij^2 V_j,

so K = sum_i s_i g_i g_i^T + sum_bonds k_b n n^T is the Hessian of sum_i V_i W_i: symmetric
even when the moduli vary from particle to particle (seed 000 eq 8). kappa is the in-plane
bulk modulus: 9KG/(3K+4G) in plane stress, K + G/3 in plane strain, K in 3D. This is the
2D split of Le et al. (2014) and equals seed 001's eqs 18-19 (which use the 3D split x theta/3
in 2D: expanding eq 45 with eq 41 gives the same coefficient 2(K + G/3)/q of theta x in plane
strain). Seed 000 prints k + mu/9 for that coefficient; the calibration above gives k + mu/3.

Bond-based PMB (seed 002 eq 1): W_i = 1/4 sum_j c s^2 |xi| V_j with c = 18K/(pi delta^4)
in 3D, 9K/(pi t delta^3) in plane stress (nu = 1/3, E = K) and 72K/(5 pi t delta^3) in
plane strain (nu = 1/4, E = 3K/2), calibrated on the continuum family.
"""
from __future__ import annotations

import math

import numpy as np
import torch

from bayespd.assembly import BlockPattern, Families
from bayespd.bonds import Bonds
from bayespd.discretize import Particles

_C_DEV = {2: 8.0, 3: 15.0}


def moduli_from_young(E, nu):
    """Bulk and shear moduli (K, G) from Young's modulus and Poisson's ratio."""
    E, nu = torch.as_tensor(E), torch.as_tensor(nu)
    if not bool(torch.all(torch.isfinite(E)) and torch.all(E > 0)):
        raise ValueError("Young's modulus E must be finite and positive")
    if not bool(torch.all((nu > -1) & (nu < 0.5))):
        raise ValueError("Poisson's ratio must lie in (-1, 0.5): nu = 0.5 is incompressible "
                         "and makes the plane-stress LPS constants singular; use nu < 0.5")
    return E / (3 * (1 - 2 * nu)), E / (2 * (1 + nu))


def check_modulus(name: str, value, n: int) -> torch.Tensor:
    """A modulus as a tensor broadcastable to (n,); refuse NaN, inf and non-positive values."""
    v = torch.as_tensor(value)
    if v.dim() > 1 or (v.dim() == 1 and v.shape[0] != n):
        raise ValueError(f"{name} must be a scalar or have one value per particle ({n})")
    if not bool(torch.all(torch.isfinite(v))):
        raise ValueError(f"{name} contains NaN or inf: pass finite moduli")
    if not bool(torch.all(v > 0)):
        raise ValueError(f"{name} must be positive (got min {float(v.min()):g}): moduli "
                         "are positive; sample them on a log scale")
    return v


class _Material:
    """Shared set-up: particles, bonds, fixed geometry as tensors."""

    def __init__(self, particles: Particles, bonds: Bonds, plane: str = "stress"):
        if plane not in ("stress", "strain"):
            raise ValueError("plane must be 'stress' or 'strain'")
        self.particles, self.bonds, self.plane = particles, bonds, plane
        self.dim = particles.dim
        self.volume = torch.as_tensor(particles.volume)
        self.length = torch.as_tensor(bonds.length)
        self.unit = torch.as_tensor(bonds.xi / bonds.length[:, None])
        self._i, self._j = torch.as_tensor(bonds.i), torch.as_tensor(bonds.j)

    @property
    def pattern(self):
        return self.blocks.pattern

    def _bond_blocks(self, blocks: torch.Tensor, k_b: torch.Tensor) -> torch.Tensor:
        """Add k_b n n^T to the (i,i), (j,j) blocks and subtract it from (i,j), (j,i)."""
        kb = k_b[:, None, None] * self.unit[:, :, None] * self.unit[:, None, :]
        ii, jj, ij, ji = self._bond_block_ids
        return blocks.index_add(0, ii, kb).index_add(0, jj, kb).index_add(0, ij, -kb).index_add(0, ji, -kb)

    def _setup_bond_blocks(self):
        b, bl = self.bonds, self.blocks
        self._bond_block_ids = (bl.block(b.i, b.i), bl.block(b.j, b.j),
                                bl.block(b.i, b.j), bl.block(b.j, b.i))

    def extension(self, u: torch.Tensor) -> torch.Tensor:
        """Linearised bond extension e = n . (u_j - u_i) for u of shape (N, dim)."""
        return ((u[self._j] - u[self._i]) * self.unit).sum(-1)


class LPS(_Material):
    """Linear peridynamic solid (state-based), 2D plane stress / plane strain or 3D.

    Params: ``{"K": bulk, "G": shear}`` (3D moduli; scalars or per-particle tensors).
    """

    def __init__(self, particles: Particles, bonds: Bonds, plane: str = "stress"):
        super().__init__(particles, bonds, plane)
        n = particles.n
        self.families = Families.of(bonds, n)
        owner, node = self.families.with_self(n)
        e1, e2 = self.families.end_pairs(n)
        self.blocks = BlockPattern(n, self.dim, node[e1], node[e2])
        self._triple_block = self.blocks.block(node[e1], node[e2])
        self._e1, self._e2 = torch.as_tensor(e1), torch.as_tensor(e2)
        self._triple_owner = torch.as_tensor(owner[e1])
        f = self.families
        self._owner = torch.as_tensor(f.owner)
        self._end_bond = torch.as_tensor(f.bond)
        self._end_sign = torch.as_tensor(f.sign)
        self._end_volume = self.volume[torch.as_tensor(f.node)]
        self._setup_bond_blocks()

    def kappa(self, K: torch.Tensor, G: torch.Tensor) -> torch.Tensor:
        """In-plane bulk modulus of the dimension-reduced continuum."""
        if self.dim == 3:
            return K
        return 9 * K * G / (3 * K + 4 * G) if self.plane == "stress" else K + G / 3

    def _moduli(self, params: dict):
        n = self.particles.n
        missing = {"K", "G"} - set(params)
        if missing:
            raise ValueError(f"LPS needs params {sorted(missing)} (bulk K and shear G)")
        return check_modulus("K", params["K"], n), check_modulus("G", params["G"], n)

    def weighted_volume(self, beta: torch.Tensor) -> torch.Tensor:
        """m_i = sum_j w x^2 V_j with partial volumes (seed 000 eq 9)."""
        f_b = beta[self._end_bond] * self.length[self._end_bond] ** 2 * self._end_volume
        m = torch.zeros(self.particles.n, dtype=f_b.dtype).index_add(0, self._owner, f_b)
        if bool(torch.any(m <= 0)):
            raise ValueError("a particle has an empty family at this horizon: increase delta "
                             "or remove isolated particles")
        return m

    def _dilatation_vectors(self, beta, m):
        """g_e with theta_i = sum_e g_e . u_node(e) (seed 000 eq 10), self ends last."""
        bond, d = self._end_bond, self.dim
        coef = d * beta[bond] * self.length[bond] * self._end_volume / m[self._owner]
        g = (coef * self._end_sign)[:, None] * self.unit[bond]
        g_self = -torch.zeros(self.particles.n, d, dtype=g.dtype).index_add(0, self._owner, g)
        return torch.cat([g, g_self])

    def _coefficients(self, params, delta):
        K, G = self._moduli(params)
        d, c = self.dim, _C_DEV[self.dim]
        beta = self.bonds.weight(delta)
        m = self.weighted_volume(beta)
        G = G.expand(self.particles.n)
        s = self.volume * (self.kappa(K, G) - c * G / d**2)
        V = self.volume
        k_b = c * beta * V[self._i] * V[self._j] * (G[self._i] / m[self._i] + G[self._j] / m[self._j])
        return s, k_b, self._dilatation_vectors(beta, m)

    def stiffness(self, params: dict, delta) -> torch.Tensor:
        """Values of K(params, delta) on ``self.pattern``."""
        s, k_b, g = self._coefficients(params, delta)
        g1, g2 = g[self._e1], g[self._e2]
        tri = s[self._triple_owner][:, None, None] * g1[:, :, None] * g2[:, None, :]
        blocks = torch.zeros(self.blocks.n_blocks, self.dim, self.dim, dtype=tri.dtype)
        blocks = blocks.index_add(0, self._triple_block, tri)
        return self.blocks.values(self._bond_blocks(blocks, k_b))

    def energy(self, params: dict, delta, u: torch.Tensor) -> torch.Tensor:
        """Total strain energy sum_i V_i W_i of the linearised model for u of shape (N, dim)."""
        s, k_b, g = self._coefficients(params, delta)
        n = self.particles.n
        node = torch.cat([torch.as_tensor(self.families.node), torch.arange(n)])
        owner = torch.cat([self._owner, torch.arange(n)])
        theta = torch.zeros(n, dtype=u.dtype).index_add(0, owner, (g * u[node]).sum(-1))
        return 0.5 * (s * theta**2).sum() + 0.5 * (k_b * self.extension(u) ** 2).sum()


class BondBased(_Material):
    """Prototype microelastic brittle (PMB) bond-based material, linearised.

    Params: ``{"K": bulk}`` (scalar or per particle); Poisson's ratio is fixed by the model
    (1/4 in 3D and plane strain, 1/3 in plane stress).
    """

    def __init__(self, particles: Particles, bonds: Bonds, plane: str = "stress"):
        super().__init__(particles, bonds, plane)
        self.blocks = BlockPattern(particles.n, self.dim, bonds.i, bonds.j)
        self._setup_bond_blocks()

    def micromodulus(self, K: torch.Tensor, delta) -> torch.Tensor:
        delta = torch.as_tensor(delta)
        if self.dim == 3:
            return 18 * K / (math.pi * delta**4)
        coef = 9.0 if self.plane == "stress" else 72.0 / 5.0
        return coef * K / (math.pi * self.particles.thickness * delta**3)

    def _bond_stiffness(self, params, delta):
        if "K" not in params:
            raise ValueError("BondBased needs params['K'] (bulk modulus)")
        K = check_modulus("K", params["K"], self.particles.n).expand(self.particles.n)
        beta = self.bonds.weight(delta)
        c = self.micromodulus(K, delta)
        c_b = 0.5 * (c[self._i] + c[self._j])
        return c_b * beta * self.volume[self._i] * self.volume[self._j] / self.length

    def stiffness(self, params: dict, delta) -> torch.Tensor:
        """Values of K(params, delta) on ``self.pattern``."""
        k_b = self._bond_stiffness(params, delta)
        blocks = torch.zeros(self.blocks.n_blocks, self.dim, self.dim, dtype=k_b.dtype)
        return self.blocks.values(self._bond_blocks(blocks, k_b))

    def energy(self, params: dict, delta, u: torch.Tensor) -> torch.Tensor:
        """Total strain energy 1/2 sum_b c V_i V_j e^2 / |xi| of the linearised model."""
        return 0.5 * (self._bond_stiffness(params, delta) * self.extension(u) ** 2).sum()
