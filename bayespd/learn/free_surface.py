"""The free-surface-corrected LPS of paper 004 (You et al., eqs 3.13-3.21), 2D, on a square lattice.

With K_ij the influence, W_ij = beta_ij V_j the quadrature weight (beta the partial volume), gamma_ij
the intact fraction, xi = x_j - x_i, du = u_j - u_i, C1 = 2, C2 = 16 (d = 2) and m_i the weighted
volume of the complete family (eq 3.6, gamma ignored), the operator of eq 3.18 is

    L_i = - C1/m_i sum_j (lam - mu) K gamma xi (theta_i + theta_j) W            (T1)
          - C2/m_i sum_j mu K gamma xi (xi . du) / |xi|^2 W                     (T2)
          - 2 C1 theta_i/m_i sum_j (lam - mu) K (1 - gamma) xi W                (T3)
          - C2 theta_i/(2 m_i) sum_j (lam + 2 mu) K (1 - gamma) (xi.n)(xi.p)^2/|xi|^2 n W   (T4)
          + C2 theta_i/(2 m_i) sum_j lam K (1 - gamma) (xi.n)^3/|xi|^2 n W      (T5)

with the corrected dilatation theta_i = (d/m_i) sum_j K gamma xi . M_i du W (eq 3.19), M_i =
[(d/m_i) sum_j K gamma xi (x) xi W]^-1 (eq 3.20), the outward normal n_i = -q/|q|, q = sum_j gamma
xi W (eq 3.21), and the tangent p = n rotated by +90 degrees. The equation of motion is rho u'' + L
= b (eq 3.17); ``force`` returns the nodal force -V_i L_i. The missing bonds of a node next to a free
surface (lattice sites outside the body, and bonds cut by a pre-crack) enter as broken bonds
(gamma = 0): they count in m_i and in the (1 - gamma) sums. Sites beyond a prescribed (Dirichlet)
edge, where the paper has a collar of data, are no bonds at all (``free`` says which is which).

Derivation (the text extraction's eq 3.18 checked, not garbled): for u = H x the sums over the
complete family of T1 and T2 vanish (odd in xi), so the intact bonds' T1 + T2 equal minus the
broken ones'; theta_i = tr H exactly for any intact set (M_i inverts its second moment). T3
cancels the broken bonds' share of T1. For a straight free edge (missing set mirror-symmetric about
n) with the traction-free strain sigma n = 0 (eps_np = 0, eps_nn = -lam theta / (2 mu), eps_pp =
(lam + 2 mu) theta / (2 mu)), the broken bonds' share of T2 is C2/(2m) theta sum (1 - gamma) K
[(lam + 2 mu) a b^2 - lam a^3] / |xi|^2 n W with a = xi.n, b = xi.p, which T4 and T5 cancel. So
L = 0 at every node of a traction-free homogeneous strain, whole family or not (tests/learn/
test_free_surface.py); in the bulk (all gamma = 1) T3-T5 vanish, M = I and L is eq 3.5.

The paper's operator is linear in u for given gamma (eq 3.18 uses du, not the deformed bond); the
damage law reads the exact stretch (eq 3.16), as in ``bayespd.learn.forward``.
"""
from __future__ import annotations

import numpy as np
import torch

C1, C2 = 2.0, 16.0  # the 2D constants of eqs 3.2 / 3.18
A_FLOOR = 1e-3      # eigenvalues of (d/m) sum K gamma xi xi W below this (bulk: 1) carry no dilatation:
#                     a node with its bonds (nearly) all broken along a direction gets no theta from it


class FreeSurface:
    """Eq 3.18 for the 2D material ``material`` (``bayespd.materials.LPS`` on nodes of a square
    lattice of spacing h) at ``params``. ``free(sites)`` -> bool per missing lattice site ((M, 2)
    positions): True where the site lies beyond a free surface (a broken bond), False beyond a
    prescribed edge (no bond); None: every missing site is beyond a free surface. Bonds of the
    material that a pre-crack removed are always broken bonds."""

    def __init__(self, material, params: dict, free=None):
        if material.dim != 2:
            raise ValueError("the free-surface correction (paper 004 eq 3.18) is written for 2D: pass a 2D material")
        moduli = material.moduli(params)
        kappa, mu = material.kappa(moduli["K"], moduli["G"]), moduli["G"]
        self.lam, self.mu = (kappa - mu).detach(), mu.detach()  # in-plane Lame moduli (kappa = lam + mu)
        bonds, n = material.bonds, material.particles.n
        delta = params["delta"]
        K = material.influence(material.length, delta, params).detach()
        W = bonds.weight(delta).detach()
        V = material.volume
        i, j = material.i, material.j
        self.owner, self.other = torch.cat([i, j]), torch.cat([j, i])
        xi = torch.as_tensor(bonds.xi)
        self.xi = torch.cat([xi, -xi])
        self.KW = torch.cat([K * W * V[j], K * W * V[i]])
        self.W = torch.cat([W * V[j], W * V[i]])
        self.r2 = (self.xi**2).sum(1)
        self.n, self.V = n, V
        g_owner, g_xi, g_KW = _missing_bonds(material, params, free)
        self.m = self._sum(self.KW * self.r2) + _add(g_owner, g_KW * (g_xi**2).sum(1), n)
        if bool(torch.any(self.m <= 0)):
            raise ValueError("a node has a non-positive weighted volume m: use a non-negative influence function")
        self.ghost_s1 = _add(g_owner, g_KW[:, None] * g_xi, n)          # sum K W xi over the missing bonds
        self.ghost_s3 = _add(g_owner, g_KW[:, None, None, None] * _cube(g_xi), n)

    def _sum(self, values: torch.Tensor) -> torch.Tensor:
        return _add(self.owner, values, self.n)

    def _gamma(self, intact) -> torch.Tensor:
        g = torch.ones(len(self.owner) // 2, dtype=torch.float64) if intact is None else torch.as_tensor(intact)
        return torch.cat([g, g])

    def dilatation(self, u, intact=None) -> torch.Tensor:
        """theta_i (eqs 3.19-3.20); exact (tr H) for u = H x at every node with a 2D intact family."""
        return self._dilatation(torch.as_tensor(u), self._gamma(intact))

    def _dilatation(self, u, g):
        du = u[self.other] - u[self.owner]
        wg = (self.KW * g)[:, None, None]
        A = 2.0 / self.m[:, None, None] * self._sum(wg * self.xi[:, :, None] * self.xi[:, None, :])
        B = self._sum(wg * self.xi[:, :, None] * du[:, None, :])
        return 2.0 / self.m * (_pinv(A) * B).sum((1, 2))

    def normal(self, intact=None) -> torch.Tensor:
        """n_i = -q / |q|, q = sum_j gamma xi W (eq 3.21); 0 where q = 0 (then T4 = T5 = 0)."""
        q = self._sum((self.W * self._gamma(intact))[:, None] * self.xi)
        size = q.norm(dim=1, keepdim=True)
        return -q / torch.where(size > 0, size, torch.ones_like(size))

    def operator(self, u, intact=None) -> torch.Tensor:
        """L_i of eq 3.18 (module docstring), (N, 2)."""
        u, g = torch.as_tensor(u), self._gamma(intact)
        lam, mu, m = self.lam, self.mu, self.m
        theta = self._dilatation(u, g)
        du = u[self.other] - u[self.owner]
        o = self.owner
        wg = self.KW * g
        t1 = -C1 * (lam - mu)[o] / m[o] * wg * (theta[o] + theta[self.other])
        t2 = -C2 * mu[o] / m[o] * wg * (self.xi * du).sum(1) / self.r2
        L = self._sum((t1 + t2)[:, None] * self.xi)
        wb = self.KW * (1 - g)
        s1 = self._sum(wb[:, None] * self.xi) + self.ghost_s1
        s3 = self._sum(wb[:, None, None, None] * _cube(self.xi)) + self.ghost_s3
        n = self.normal(intact)
        p = torch.stack([-n[:, 1], n[:, 0]], 1)
        npp = torch.einsum("iabc,ia,ib,ic->i", s3, n, p, p)
        nnn = torch.einsum("iabc,ia,ib,ic->i", s3, n, n, n)
        t3 = -2 * C1 * theta / m * (lam - mu)
        t45 = C2 * theta / (2 * m) * (lam * nnn - (lam + 2 * mu) * npp)
        return L + t3[:, None] * s1 + t45[:, None] * n

    def force(self, u, intact=None) -> torch.Tensor:
        """The nodal force -V_i L_i (the ``bayespd.learn.forward`` convention m_i u'' = f_i + V_i b_i)."""
        return -self.V[:, None] * self.operator(u, intact)

    def strain_energy(self, u, intact=None) -> torch.Tensor:
        """u . (-f) / 2: the strain energy where the operator is symmetric (no broken or missing
        bond); with the correction the operator is not an energy's gradient and this is a diagnostic."""
        u = torch.as_tensor(u)
        return -0.5 * (u * self.force(u, intact)).sum()


def _add(index, values, n):
    return torch.zeros((n, *values.shape[1:]), dtype=values.dtype).index_add_(0, index, values)


def _cube(xi: torch.Tensor) -> torch.Tensor:
    """xi_a xi_b xi_c / |xi|^2 per bond, (B, 2, 2, 2)."""
    return xi[:, :, None, None] * xi[:, None, :, None] * xi[:, None, None, :] / (xi**2).sum(1)[:, None, None, None]


def _pinv(A: torch.Tensor) -> torch.Tensor:
    """Inverse of symmetric 2 x 2 matrices with eigenvalues below A_FLOOR dropped."""
    e, v = torch.linalg.eigh(A)
    inv = torch.where(e > A_FLOOR, 1.0 / torch.where(e > A_FLOOR, e, torch.ones_like(e)), torch.zeros_like(e))
    return (v * inv[:, None, :]) @ v.transpose(1, 2)


def _missing_bonds(material, params, free):
    """(owner, xi, K W V) of each node's missing bonds: the complete lattice family
    (``material.lattice_family``) less the material's bonds, without the sites ``free`` rejects."""
    x, h = material.particles.x, material.bonds.h
    origin = x.min(0)
    k = np.rint((x - origin) / h).astype(np.int64)
    if np.abs(x - origin - k * h).max() > 1e-6 * h:
        raise ValueError("the free-surface correction needs the nodes on a square lattice of spacing h "
                         f"(h = {h:g}): coarse-grain onto a regular grid")
    r, unit, cell = material.lattice_family
    offsets = np.rint(r.numpy()[:, None] * unit.numpy() / h).astype(np.int64)
    weight = (material.lattice_weight(r, params) * cell).detach()
    n, size = len(x), k.max(0) + 1
    lookup = np.full(tuple(size), -1, dtype=np.int64)
    lookup[k[:, 0], k[:, 1]] = np.arange(n)
    site = k[:, None, :] + offsets[None, :, :]                      # (N, F, 2)
    inside = ((site >= 0) & (site < size)).all(-1)
    target = np.where(inside, lookup[np.clip(site[..., 0], 0, size[0] - 1), np.clip(site[..., 1], 0, size[1] - 1)], -1)
    b = material.bonds
    present = np.minimum(b.i, b.j) * n + np.maximum(b.i, b.j)
    owner = np.repeat(np.arange(n)[:, None], len(offsets), 1)
    code = np.minimum(owner, target) * n + np.maximum(owner, target)
    missing = (target < 0) | ~np.isin(code, present)
    empty = missing & (target < 0)
    if free is not None and empty.any():
        where = origin + site[empty] * h
        keep = np.asarray(free(where), bool)
        if keep.shape != (len(where),):
            raise ValueError("free(sites) must return one bool per site")
        missing[empty] = keep
    rows, cols = np.nonzero(missing)
    return (torch.as_tensor(rows), torch.as_tensor(offsets[cols] * h, dtype=torch.float64),
            weight[torch.as_tensor(cols)])
