"""Geometrically exact (nonlinear) bond kinematics, internal force and potential energy.

With eta = u_j - u_i and the deformed bond y = xi + eta, the extension is e = |y| - |xi| and
the stretch s = e / |xi| (seed 002 eq 1-2; seed 004 eq 3.11). Each bond carries its intact
fraction mu in [0, 1] (from ``bayespd.damage``; 1 when no damage law is present), held fixed
while the force is taken: the force is -dV/du at the current damage state.

Bond-based PMB (seed 002 eq 2): bond energy 1/2 c_b w_b mu_b s^2 |xi| V_i V_j with the
calibration and weights of the linearised ``BondBased`` (c_b the mean micromodulus of the two
ends, w_b = omega * beta from ``bond_weight``, times the surface factor when switched on).

LPS: the energy of the linear LPS (``materials`` docstring) with the exact extension and the
intact weights mu w: m_i = sum_j mu w |xi|^2 V_j, theta_i = (d / m_i) sum_j mu w |xi| e V_j,

    V_i W_i = V_i [(kappa_i/2 - c_d G_i/(2 d^2)) theta_i^2 + (c_d G_i/(2 m_i)) sum_j mu w e^2 V_j].

m_i is floored at ``M_FLOOR`` times its undamaged value: a fully broken particle (theta = 0,
no bond energy) then divides 0 by a positive number; above the floor nothing changes, below it
the particle's energy fades continuously to zero with its last bonds.

Total potential energy (seed 002 eq 3): V(u) = sum of bond energies - p . u + (eps/2) u . u.
For small u both forces equal the linearised -K u up to O(|u|^2).

The force is written by hand (gather, per-bond scalar, two ``index_add_``), never through
autograd of the energy; it is differentiable in the moduli, the horizon and mu.
"""
from __future__ import annotations

import torch

from bayespd.materials import _C_DEV, LPS, BondBased

M_FLOOR = 1e-9


class NonlinearBonds:
    """Exact bond kinematics of a ``BondBased`` or ``LPS`` material (index tensors built once).

    ``at(params, delta)`` evaluates the per-bond coefficients once per parameter value and
    returns an object whose ``force(u, intact)`` / ``energy(u, intact, load, eps)`` are the
    cheap per-step calls; ``force(u, params, delta, intact)`` does both at once.
    """

    def __init__(self, material):
        if not isinstance(material, (BondBased, LPS)):
            raise TypeError("NonlinearBonds needs a BondBased or LPS material")
        self.material = material
        self.i, self.j = material._i, material._j
        self.xi = torch.as_tensor(material.bonds.xi)
        self.length = material.length
        self.n, self.dim = material.particles.n, material.dim
        # flat dof indices d*i + a: 1-D gathers and index_add_ are the fastest on CPU
        d, a = self.dim, torch.arange(self.dim)
        self._di = (d * self.i[:, None] + a).reshape(-1)
        self._dj = (d * self.j[:, None] + a).reshape(-1)

    def deformed(self, u: torch.Tensor):
        """(y, |y|): deformed bond vectors xi + u_j - u_i and their lengths."""
        if u.shape != (self.n, self.dim):
            raise ValueError(f"u must have shape ({self.n}, {self.dim}), got {tuple(u.shape)}")
        flat = u.reshape(-1)
        y = (flat.index_select(0, self._dj) - flat.index_select(0, self._di)).view(-1, self.dim)
        y += self.xi
        return y, torch.linalg.vector_norm(y, dim=1)

    def stretch(self, u: torch.Tensor) -> torch.Tensor:
        """s = (|xi + eta| - |xi|) / |xi| per bond for u of shape (N, dim)."""
        return self.deformed(u)[1] / self.length - 1

    def at(self, params: dict, delta):
        """The material's per-bond coefficients at (params, delta) (differentiable)."""
        cls = LPSForce if isinstance(self.material, LPS) else PMBForce
        return cls(self, params, delta)

    def force(self, u, params: dict, delta, intact=None) -> torch.Tensor:
        """Internal force -dV_strain/du, shape (N, dim)."""
        return self.at(params, delta).force(u, intact)

    def energy(self, u, params: dict, delta, intact=None, load=None, eps: float = 0.0):
        """Total potential energy V(u) of seed 002 eq 3."""
        return self.at(params, delta).energy(u, intact, load, eps)


class _Force:
    """Per-bond coefficients at one (params, delta): ``force(u, intact)``,
    ``strain_energy(u, intact)`` and ``energy(u, intact, load, eps)``."""

    def __init__(self, kin: NonlinearBonds, params: dict, delta):
        self.kin = kin
        self.moduli = kin.material._moduli(params)
        self.factor = kin.material._bond_correction(self.moduli, params, delta)

    def _scatter(self, y, t_over_r, like):
        """Bond force t y/|y| pulls i towards j (+) and j towards i (-)."""
        fb = (y * t_over_r[:, None]).view(-1)
        f = torch.zeros(like.numel(), dtype=fb.dtype).index_add_(0, self.kin._di, fb)
        return f.index_add_(0, self.kin._dj, -fb).view(like.shape)

    def energy(self, u, intact=None, load=None, eps: float = 0.0):
        """Strain energy - p . u + (eps/2) u . u (seed 002 eq 3)."""
        V = self.strain_energy(u, intact)
        if load is not None:
            V = V - (torch.as_tensor(load) * u).sum()
        return V + 0.5 * eps * (u * u).sum()


class PMBForce(_Force):
    """Bond-based PMB: t_b = k_b mu e_b with k_b = c_b w_b V_i V_j / |xi| (times the factor)."""

    def __init__(self, kin, params, delta):
        super().__init__(kin, params, delta)
        self.k = self.factor * kin.material._bond_stiffness(self.moduli, params, delta)
        self.kL = self.k * kin.length

    def force(self, u, intact=None):
        y, r = self.kin.deformed(u)
        t_over_r = self.k - self.kL / r  # k e / r
        return self._scatter(y, t_over_r if intact is None else t_over_r * intact, u)

    def strain_energy(self, u, intact=None):
        e = self.kin.deformed(u)[1] - self.kin.length
        k = self.k if intact is None else self.k * intact
        return 0.5 * (k * e * e).sum()


class LPSForce(_Force):
    """LPS: dV/de_b = mu w V_i V_j [|xi| (a_i + a_j) + F_b e (b_i + b_j)] with
    a = 2 d A theta / m, b = c_d G / m, A = kappa/2 - c_d G/(2 d^2), F_b the surface factor."""

    def __init__(self, kin, params, delta):
        super().__init__(kin, params, delta)
        mat, d, L = kin.material, kin.dim, kin.length
        K, G = self.moduli["K"], self.moduli["G"]
        self.A = 0.5 * (mat.kappa(K, G) - _C_DEV[d] * G / d**2)
        self.cG = _C_DEV[d] * G
        w = mat.bond_weight(params, delta)
        self.m0 = mat.weighted_volume(w)
        Vi, Vj = mat.volume[kin.i], mat.volume[kin.j]
        self.wVVL, self.wVVF = w * Vi * Vj * L, w * Vi * Vj * self.factor
        self.wLVi, self.wLVj = w * L * Vi, w * L * Vj

    def _sum(self, at_i, at_j):
        """Per-particle sum of per-bond values at_i (to end i) and at_j (to end j)."""
        z = torch.zeros(self.kin.n, dtype=at_i.dtype)
        return z.index_add_(0, self.kin.i, at_i).index_add_(0, self.kin.j, at_j)

    def _state(self, u, intact):
        """(y, |y|, mu e, e, m, theta); mu e stands for e when there is no damage."""
        kin = self.kin
        y, r = kin.deformed(u)
        e = r - kin.length
        if intact is None:
            me, m = e, self.m0
        else:
            me = e * intact
            wL2 = intact * kin.length
            m = torch.maximum(self._sum(wL2 * self.wLVj, wL2 * self.wLVi), M_FLOOR * self.m0)
        theta = kin.dim / m * self._sum(self.wLVj * me, self.wLVi * me)
        return y, r, me, e, m, theta

    def force(self, u, intact=None):
        kin = self.kin
        y, r, me, e, m, theta = self._state(u, intact)
        ab = torch.stack([2 * kin.dim * self.A * theta / m, self.cG / m], dim=1)
        ab = ab.index_select(0, kin.i) + ab.index_select(0, kin.j)
        bond = self.wVVL * ab[:, 0] if intact is None else self.wVVL * intact * ab[:, 0]
        t = torch.addcmul(bond, self.wVVF * me, ab[:, 1])
        return self._scatter(y, t / r, u)

    def strain_energy(self, u, intact=None):
        y, r, me, e, m, theta = self._state(u, intact)
        b = self.cG / m
        bond = 0.5 * self.wVVF * me * e * (b[self.kin.i] + b[self.kin.j])
        return (self.kin.material.volume * self.A * theta**2).sum() + bond.sum()
