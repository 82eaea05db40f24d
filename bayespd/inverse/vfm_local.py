"""Local (continuum) virtual work on the measured grid: the classical VFM's weak form with the
LPS moduli's constants, free of the PD surface effect.

    W*_int,k = -sum_i V_i eps*_k,i : C(a) : eps_i,       eps = sym(D u),  eps* = sym(D u*),

D the gradient by finite differences along the grid's axes (central, second-order one-sided
where a neighbour is missing; exact for quadratic fields), summed by the midpoint rule over
the particles' cells, and C(a) the isotropic
in-plane law of ``bayespd.materials.lps`` written in the PD constants (a_s, a_d) of
``vfm.pd_constants``: kappa = a_s + a_d / d^2, G = a_d / c, sigma = kappa tr(eps) I +
2 G dev(eps), so C(a) = a_s C_s + a_d C_d with

    eps* : C_s : eps = tr eps* tr eps,
    eps* : C_d : eps = tr eps* tr eps / d^2 + (2 / c) (eps* : eps - tr eps* tr eps / d).

Traction-free surfaces are natural in a weak form, so a straight free edge (a grid line, which
the cells tile exactly) needs no treatment, unlike the PD operator with truncated families
(``vfm``), whose virtual works are biased by 0.4-0.6 % each near the supports and the free
surfaces (``docs/results.md``, VFM). What the weak form does not handle, and the default
fields (``local_fields``) keep away from: a curved boundary (a staircase of cells) and the
singular data at support and load patches. The works are linear in (a_s, a_d) and in the
data, so the closed form, ``vfm_noise`` and ``vfm_defaults`` apply unchanged.
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import torch

from bayespd.inverse.vfm import VirtualWork, pd_constants


def neighbours(particles):
    """at(offset) -> (N,) index of the particle at x + offset h (offset: integer vector), -1 where
    none; the particles must lie on one regular grid of spacing h."""
    x, h = particles.x, particles.h
    index = np.round((x - x.min(0)) / h).astype(np.int64)
    if np.abs(index * h + x.min(0) - x).max() > 1e-6 * h:
        raise ValueError("the local virtual work needs particles on one regular grid of spacing h "
                         "(a DIC or FE grid, e.g. from bp.read_field); for scattered particles use the PD "
                         "virtual work: vfm_defaults.estimate(..., work='pd')")
    lookup = {tuple(k): i for i, k in enumerate(index)}
    return lambda offset: np.array([lookup.get(tuple(k), -1) for k in index + np.asarray(offset)])


def gradient_operator(particles) -> sp.csr_matrix:
    """D (N dim^2, N dim): (D u)[i, a, b] = d u_a / d x_b at particle i (row i dim^2 + a dim + b)
    by differences along the grid's axes over the particles present (central; second-order
    one-sided at an edge; first-order where only one neighbour exists)."""
    x, h, dim = particles.x, particles.h, particles.dim
    n = len(x)
    at = neighbours(particles)

    rows, cols, vals = [], [], []
    for b in range(dim):
        e = np.zeros(dim, np.int64)
        e[b] = 1
        p1, m1, p2, m2 = at(e), at(-e), at(2 * e), at(-2 * e)
        stencils = [((p1 >= 0) & (m1 >= 0), [(p1, 0.5), (m1, -0.5)]),
                    ((p1 >= 0) & (m1 < 0) & (p2 >= 0), [(None, -1.5), (p1, 2.0), (p2, -0.5)]),
                    ((m1 >= 0) & (p1 < 0) & (m2 >= 0), [(None, 1.5), (m1, -2.0), (m2, 0.5)]),
                    ((p1 >= 0) & (m1 < 0) & (p2 < 0), [(None, -1.0), (p1, 1.0)]),
                    ((m1 >= 0) & (p1 < 0) & (m2 < 0), [(None, 1.0), (m1, -1.0)])]
        covered = np.zeros(n, bool)
        for mask, terms in stencils:
            mask = mask & ~covered
            covered |= mask
            i = np.flatnonzero(mask)
            for node, w in terms:
                j = i if node is None else node[i]
                for a in range(dim):
                    rows.append(i * dim * dim + a * dim + b), cols.append(j * dim + a), vals.append(np.full(len(i), w / h))
        if not covered.all():
            k = int(np.flatnonzero(~covered)[0])
            raise ValueError(f"particle {k} at {x[k].tolist()} has no neighbour along axis {b}: a line one "
                             "particle thick has no strain; remove it from the grid")
    return sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                         shape=(n * dim * dim, n * dim))


def _constants_parts(D, volume, dim: int, c: float):
    """(K_s, K_d): the local stiffness matrices D^T V C_p D of the module docstring."""
    n = len(volume)
    sym = sp.lil_matrix((dim * dim, dim * dim))
    for a in range(dim):
        for b in range(dim):
            sym[a * dim + b, a * dim + b] += 0.5
            sym[a * dim + b, b * dim + a] += 0.5
    trace = np.zeros((1, dim * dim))
    trace[0, [a * dim + a for a in range(dim)]] = 1.0
    tt = sp.csr_matrix(trace.T @ trace)
    per_point = {"s": tt, "d": tt / dim**2 + (2 / c) * (sym.T @ sym - tt / dim)}
    V = sp.diags(np.repeat(volume, dim * dim))
    return [(D.T @ V @ sp.kron(sp.identity(n), per_point[p]) @ D).tocsr() for p in ("s", "d")]


class LocalWork(VirtualWork):
    """:class:`vfm.VirtualWork` with the local virtual works of the module docstring (same
    interface; the scene's LPS material gives the dimension, plane and c; ``fixed`` is not used
    by the works but kept for the interface)."""

    def _basis(self):
        p, m = self.material.particles, self.material
        D = gradient_operator(p)
        self.parts = _constants_parts(D, p.volume, p.dim, m.c_d)
        W = self.ustar.reshape(self.n_fields, -1).numpy().T
        self.Ps, self.Pd = (torch.as_tensor(np.ascontiguousarray((k @ W).T)).reshape(self.ustar.shape) for k in self.parts)
        self.linear = True
        size = self.Ps.abs() + self.Pd.abs()
        self.needed = (size > 1e-10 * size.amax(dim=(1, 2), keepdim=True)).numpy()

    def internal(self, u, params: dict) -> torch.Tensor:
        """W*_int per field at the moduli K, G of ``params`` (differentiable in them)."""
        a_s, a_d = pd_constants(self.material, params["K"], params["G"])
        return -(a_s * (self.Ps * u).sum(dim=(1, 2)) + a_d * (self.Pd * u).sum(dim=(1, 2)))
