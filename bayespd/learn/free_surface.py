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
edge are the paper's collar of data (BOmega_D, eq 3.17): intact bonds to a site that moves with its
nearest node (the prescribed data held constant outward; ``free`` says which sites are which).

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
import scipy.sparse
import torch
from scipy.spatial import cKDTree

from bayespd.bonds import partial_volume

C1, C2 = 2.0, 16.0  # the 2D constants of eqs 3.2 / 3.18
A_FLOOR = 1e-3      # eigenvalues of (d/m) sum K gamma xi xi W below this (bulk: 1) carry no dilatation:
#                     a node with its bonds (nearly) all broken along a direction gets no theta from it


class FreeSurface:
    """Eq 3.18 for the 2D material ``material`` (``bayespd.materials.LPS`` on nodes of a square
    lattice of spacing h) at ``params``. ``free(sites)`` -> bool per missing lattice site ((M, 2)
    positions): True where the site lies beyond a free surface (a broken bond), False beyond a
    prescribed edge (a collar site moving with its nearest node); None: every missing site is beyond
    a free surface. Bonds of the material that a pre-crack removed are always broken bonds. Sums run
    over the directed bond ends (i, j) and (j, i) of the material's bonds, the broken missing bonds
    (gamma = 0, du = 0) and the collar bonds (gamma = 1, the site's u that of its nearest node)."""

    def __init__(self, material, params: dict, free=None):
        if material.dim != 2:
            raise ValueError("the free-surface correction (paper 004 eq 3.18) is written for 2D: pass a 2D material")
        moduli = material.moduli(params)
        kappa, mu = material.kappa(moduli["K"], moduli["G"]), moduli["G"]
        self.lam, self.mu = (kappa - mu).detach().numpy(), mu.detach().numpy()  # in-plane Lame (kappa = lam + mu)
        bonds, n = material.bonds, material.particles.n
        delta = params["delta"]
        K = material.influence(material.length, delta, params).detach().numpy()
        W = bonds.weight(delta).detach().numpy()
        V = material.volume.numpy()
        i, j = bonds.i, bonds.j
        g_owner, g_other, g_xi, g_K, g_W, self.collar = _missing_bonds(material, params, free)
        self.n, self.V, self.bonds = n, V, bonds.n
        self.owner = np.concatenate([i, j, g_owner])
        self.other = np.concatenate([j, i, g_other])
        self.xi = np.concatenate([bonds.xi, -bonds.xi, g_xi])
        self.KW = np.concatenate([K * W * V[j], K * W * V[i], g_K * g_W])
        self.W = np.concatenate([W * V[j], W * V[i], g_W])
        self.r2 = (self.xi**2).sum(1)
        ends = len(self.owner)
        self.sums = scipy.sparse.csr_matrix((np.ones(ends), (self.owner, np.arange(ends))), shape=(n, ends))
        self.m = self._sum(self.KW * self.r2)
        if np.any(self.m <= 0):
            raise ValueError("a node has a non-positive weighted volume m: use a non-negative influence function")
        self.pairs = self.xi[:, :, None] * self.xi[:, None, :]  # xi (x) xi per end

    def _sum(self, values: np.ndarray) -> np.ndarray:
        """Per-node sum over the ends owned, for values (E,) or (E, ...): one sparse product."""
        return (self.sums @ values.reshape(len(values), -1)).reshape(self.n, *values.shape[1:])

    def _gamma(self, intact) -> np.ndarray:
        g = np.ones(self.bonds) if intact is None else np.asarray(intact, float)
        return np.concatenate([g, g, self.collar])

    def dilatation(self, u, intact=None) -> np.ndarray:
        """theta_i (eqs 3.19-3.20); exact (tr H) for u = H x at every node with a 2D intact family."""
        u = np.asarray(u, float)
        return self._dilatation(u[self.other] - u[self.owner], self.KW * self._gamma(intact))

    def _dilatation(self, du, wg):
        A = 2.0 / self.m[:, None, None] * self._sum(wg[:, None, None] * self.pairs)
        B = self._sum(wg[:, None, None] * self.xi[:, :, None] * du[:, None, :])
        return 2.0 / self.m * (_pinv(A) * B).sum((1, 2))

    def normal(self, intact=None) -> np.ndarray:
        """n_i = -q / |q|, q = sum_j gamma xi W (eq 3.21); 0 where q = 0 (then T4 = T5 = 0)."""
        q = self._sum((self.W * self._gamma(intact))[:, None] * self.xi)
        size = np.linalg.norm(q, axis=1, keepdims=True)
        return -q / np.where(size > 0, size, 1.0)

    def operator(self, u, intact=None) -> np.ndarray:
        """L_i of eq 3.18 (module docstring), (N, 2)."""
        u, g = np.asarray(u, float), self._gamma(intact)
        o, lam, mu, m = self.owner, self.lam, self.mu, self.m
        du = u[self.other] - u[o]
        wg = self.KW * g
        theta = self._dilatation(du, wg)
        t12 = -wg / m[o] * (C1 * (lam - mu)[o] * (theta[o] + theta[self.other])
                            + C2 * mu[o] * (self.xi * du).sum(1) / self.r2)
        n = self.normal(intact)
        a = (self.xi * n[o]).sum(1)                                  # xi . n
        b = self.xi[:, 1] * n[o, 0] - self.xi[:, 0] * n[o, 1]          # xi . p, p = n rotated by +90 degrees
        wb = self.KW * (1 - g)
        s1 = self._sum(wb[:, None] * self.xi)
        nnn = self._sum(wb * a**3 / self.r2)
        npp = self._sum(wb * a * b**2 / self.r2)
        t3 = -2 * C1 * theta / m * (lam - mu)
        t45 = C2 * theta / (2 * m) * (lam * nnn - (lam + 2 * mu) * npp)
        return self._sum(t12[:, None] * self.xi) + t3[:, None] * s1 + t45[:, None] * n

    def force(self, u, intact=None) -> torch.Tensor:
        """The nodal force -V_i L_i (the ``bayespd.learn.forward`` convention m_i u'' = f_i + V_i b_i)."""
        return torch.from_numpy(-self.V[:, None] * self.operator(u, intact))

    def strain_energy(self, u, intact=None) -> torch.Tensor:
        """u . (-f) / 2: the strain energy where the operator is symmetric (no broken or missing
        bond); with the correction the operator is not an energy's gradient and this is a diagnostic."""
        return -0.5 * (torch.as_tensor(u) * self.force(u, intact)).sum()


def _pinv(A: np.ndarray) -> np.ndarray:
    """Inverse of symmetric 2 x 2 matrices with eigenvalues below A_FLOOR dropped."""
    e, v = np.linalg.eigh(A)
    inv = np.where(e > A_FLOOR, 1.0 / np.where(e > A_FLOOR, e, 1.0), 0.0)
    return (v * inv[:, None, :]) @ v.transpose(0, 2, 1)


def _missing_bonds(material, params, free):
    """(owner, other, xi, K, W V, gamma) of each node's missing bonds: the complete lattice family
    (``material.lattice_family``) less the material's bonds; broken (gamma = 0, other = owner) or,
    for the sites ``free`` rejects, collar bonds (gamma = 1, other = the node nearest the site)."""
    x, h = material.particles.x, material.bonds.h
    origin = x.min(0)
    k = np.rint((x - origin) / h).astype(np.int64)
    if np.abs(x - origin - k * h).max() > 1e-6 * h:
        raise ValueError("the free-surface correction needs the nodes on a square lattice of spacing h "
                         f"(h = {h:g}): coarse-grain onto a regular grid")
    r, unit, cell = material.lattice_family
    offsets = np.rint(r.numpy()[:, None] * unit.numpy() / h).astype(np.int64)
    influence = material.influence(r, params["delta"], params).detach().numpy()
    volume = (partial_volume(r, params["delta"], h, material.bonds.rule) * cell).detach().numpy()
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
    rows, cols = np.nonzero(missing)
    other, gamma = rows.copy(), np.zeros(len(rows))
    empty = target[rows, cols] < 0
    if free is not None and empty.any():
        where = origin + site[rows[empty], cols[empty]] * h
        broken = np.asarray(free(where), bool)
        if broken.shape != (len(where),):
            raise ValueError("free(sites) must return one bool per site")
        nearest = cKDTree(x).query(where)[1]
        collar = np.flatnonzero(empty)[~broken]
        other[collar], gamma[collar] = nearest[~broken], 1.0
    return rows, other, (offsets[cols] * h).astype(float), influence[cols], volume[cols], gamma
