"""The scene at fixed parameters (``Scene.at(params)``): the exact bond force of
``bayespd.nonlinear`` at the current intact fractions mu, the reactions, the tangent T of the
Newton steps of ``quasistatic`` and the theta-steps of ``fracture``, and the dofs solved for.

The residual at load factor lambda is r(u) = f_int(u; mu) + lambda p - eps u on the free dofs
(Dodwell 2019 eq 3). Bond-based (a ``pairwise`` law, ``materials.base``):
T is the exact Hessian of the bond energy at u, k mu [n n^T + (e/r) (I - n n^T)] per bond (n =
y/|y|), with the geometric part e/r kept only in tension (e > 0), so T is positive
semi-definite and the step a descent direction; this keeps a particle or fragment that hangs on
its last bonds stable (the linearised stiffness gives it no transverse stiffness, and a Newton
iteration with it stalls or diverges there). LPS (any other law): T is the linearised
stiffness of the damaged body (``material.terms(params, intact)``: broken bonds removed; the
Hessian at u = 0), factorised once per damage state: modified Newton, contracting the error by
O(max stretch) per iteration away from hanging pieces. A mechanism that is still attached (T
singular) gets a small diagonal shift (``LoadedBody.tangent``).

Detached pieces: with eps = 0, a piece of the intact-bond graph that holds no Dirichlet
particle (an isolated particle, a fragment) has its dofs dropped from the solve: it keeps the
displacement it had when it came loose, and T stays positive definite. With eps > 0 nothing
is dropped: the confinement of eq 3 holds such pieces.
"""
from __future__ import annotations

import weakref
from functools import cached_property

import numpy as np
import scipy.sparse as sp
import torch

from bayespd import bond_loops
from bayespd.nonlinear import NonlinearBonds
from bayespd.connectivity import FloatingPieces
from bayespd.linalg.woodbury import LocalChange
from bayespd.linalg.sparse import NotPositiveDefiniteError

MECHANISM_SHIFT = 1e-8  # relative diagonal shift of a singular tangent (see LoadedBody.tangent)


class LoadedBody:
    """A ``Scene`` at fixed ``params`` (its moduli and "delta"), made by ``Scene.at``: its
    material in exact kinematics (``NonlinearBonds``), its constraints, the loads at load factor
    1 and the confinement ``eps`` (Dodwell 2019 eq 3). ``loaded``: the particles whose reaction
    and mean displacement are recorded (``Scene.at``)."""

    def __init__(self, scene, params: dict, loaded=None):
        material, p = scene.material, scene.particles
        self.material, self.params, self.eps = material, params, scene.eps
        self.particles, self.bonds = p, material.bonds
        self.kinematics = NonlinearBonds(material)
        self.forces = self.kinematics.at(params)
        self.constraints, self.load = scene.constraints, scene.force
        if loaded is None:
            loaded = np.zeros(p.n, dtype=bool)
            for region in [bc for bc in scene.dirichlet if any(v not in (None, 0) for v in bc.value)] + scene.loads:
                loaded |= region.mask
        self.loaded = np.asarray(loaded, dtype=bool)
        if not self.loaded.any():
            raise ValueError("nothing is recorded: pass loaded= (the particles whose reaction is "
                             "recorded) with at least one particle")
        self._fixed = self.constraints.fixed_particles
        self._patterns = {}

    @cached_property
    def _floating(self) -> FloatingPieces:
        """The body's own tracker (``active`` without ``pieces``), made on first use: a fracture
        run asks with its own (``floating_pieces``)."""
        return FloatingPieces(self.bonds, self._fixed)

    @property
    def n_bonds(self) -> int:
        return self.bonds.n

    def move(self, u: torch.Tensor, lam: float) -> torch.Tensor:
        """u with its prescribed dofs set to lambda times their values (free dofs kept)."""
        c = self.constraints
        return c.embed(c.free(u)) + lam * c.prescribed

    def internal(self, u: torch.Tensor, intact, components=None) -> torch.Tensor:
        """f_int at u (``components``: ``kinematics.components(u)``, when known)."""
        return self.forces.force(u, intact, components)

    def residual(self, u: torch.Tensor, lam: float, intact) -> torch.Tensor:
        """f_int + lambda p - eps u, shape (N, dim) (the prescribed dofs included)."""
        return self.internal(u, intact) + lam * self.load - self.eps * u

    def reaction(self, u: torch.Tensor, intact, f_int: torch.Tensor | None = None) -> torch.Tensor:
        """Total force on the loaded particles from outside the body: -(f_int - eps u) summed
        (the support force under displacement control, lambda p under force control);
        ``f_int``: the internal force at u when already known."""
        f = (self.internal(u, intact) if f_int is None else f_int) - self.eps * u
        return -f[torch.as_tensor(self.loaded)].sum(0)

    def mean_displacement(self, u: torch.Tensor) -> torch.Tensor:
        return u[torch.as_tensor(self.loaded)].mean(0)

    def floating_pieces(self) -> FloatingPieces:
        """A tracker of its own of the pieces that come loose (``active``'s ``pieces``), for a
        run that shares this body with runs interleaved with it (``linalg.lockstep``)."""
        return FloatingPieces(self.bonds, self._fixed)

    def active(self, intact, pieces: FloatingPieces | None = None) -> np.ndarray:
        """Flat indices of the dofs solved for: the free dofs, less those of pieces that hold
        no Dirichlet particle when eps = 0 (see the module docstring); ``pieces``: the tracker
        to ask (default the body's own, which follows the latest caller's damage)."""
        free = self.constraints.free_dofs
        if self.eps > 0:
            return free
        floating = np.zeros(self.particles.n, dtype=bool)
        floating[(self._floating if pieces is None else pieces)(intact)] = True
        return free[~floating[free // self.particles.dim]]

    def tiles(self, dofs: np.ndarray, width: float) -> np.ndarray:
        """A label per flat dof index in ``dofs``: the square (cube) of side ``width`` on
        the particle grid that holds its particle."""
        x = np.asarray(self.particles.x)[dofs // self.particles.dim]
        cell = np.floor((x - x.min(0)) / width).astype(np.int64)
        return np.unique(cell, axis=0, return_inverse=True)[1].reshape(-1)

    @property
    def geometric(self) -> bool:
        """True when the tangent depends on u: a ``pairwise`` (bond-based) law, whose exact
        bond Hessian is known."""
        return self.material.pairwise

    def operator(self, intact, active: np.ndarray, u: torch.Tensor | None = None) -> sp.csc_matrix:
        """T + eps I on the ``active`` dofs (scipy CSC), T the tangent of the module docstring
        at u (default u = 0, where both tangents are the damaged linearised stiffness)."""
        sub, values = self._operator(intact, active, u)
        return sub.matrix(values)

    def tangent(self, intact, active: np.ndarray):
        """u -> a factor of ``operator`` at u: for each u (bond-based) or once, on the first
        call (LPS). CHOLMOD's analysis is kept per active set. A singular T (a mechanism that
        is still attached: a fragment on a hinge, a particle on bonds without tension) gets
        its diagonal shifted by MECHANISM_SHIFT times its mean: the Newton step along the
        mechanism becomes large, and the bonds it stretches break in the next update."""
        def factor(u):
            sub, values = self._operator(intact, active, u)
            try:
                return sub.factorize(values)
            except NotPositiveDefiniteError:  # a mechanism: shift the step, not the equilibrium
                diag = self._restricted(active)[2]
                values[diag] += MECHANISM_SHIFT * float(values[diag].mean())
                return sub.factorize(values)

        if self.geometric:
            return factor
        once = {}

        def fixed(u):
            if "factor" not in once:
                once["factor"] = factor(None)
            return once["factor"]

        return fixed

    def _operator(self, intact, active, u):
        sub, entries, diag = self._restricted(active)
        values = self._tangent(intact, u)[entries]
        values[diag] += self.eps
        return sub, torch.from_numpy(values)

    def operator_change(self, before, after, active: np.ndarray, u: torch.Tensor | None = None,
                        u_after: torch.Tensor | None = None) -> LocalChange:
        """operator(after) - operator(before) on the ``active`` dofs (sorted): a change on the
        dofs near the bonds whose intact fraction changed, for ``woodbury.LocallyUpdated``.
        Bond-based: assembled from those bonds and the bonds between their end particles,
        whose tangent moves from u to ``u_after`` (default u), so the geometric stiffness of
        the damaged zone, where pieces hang on their last bonds, follows the displacement
        (a better preconditioner of the exact tangent); ``rows``: the active dofs of those ends."""
        before, after = torch.as_tensor(before), torch.as_tensor(after)
        if not self.geometric:
            sub, entries, _ = self._restricted(active)
            return LocalChange.of(sub.matrix(self._tangent(after, u)[entries] - self._tangent(before, u)[entries]))
        d, i, j = self.particles.dim, self.bonds.i, self.bonds.j
        changed = np.flatnonzero(after.numpy() != before.numpy())
        ends = np.zeros(self.particles.n, dtype=bool)
        ends[i[changed]] = ends[j[changed]] = True
        bonds = self._bonds_among(ends)
        local = np.full(self.material.pattern.n, -1)
        local[active] = np.arange(len(active))
        ends_dofs = local[(d * np.flatnonzero(ends)[:, None] + np.arange(d)).reshape(-1)]
        u_after = u if u_after is None else u_after
        return LocalChange(len(active), ends_dofs[ends_dofs >= 0],
                           *self._change_entries(u, u_after, before.numpy(), after.numpy(), bonds, local))

    def _change_entries(self, u, u_after, before, after, bonds, local):
        """(rows, cols, values) of the tangent change of ``operator_change`` over ``bonds``:
        compiled (``bond_loops.tangent_change``) where it can, else from ``_bond_hessians``."""
        if bond_loops.usable(u, u_after):
            def at(v):  # u as float64 numpy (None: zero)
                return np.zeros((self.particles.n, self.particles.dim)) if v is None else np.asarray(v, dtype=np.float64)

            xi, length = self.kinematics.geometry(torch.float64)
            return bond_loops.tangent_change(at(u), at(u_after),
                                             self.kinematics.ends, xi.numpy(), length.numpy(),
                                             self.forces.k.detach().numpy(), bonds, before, after, local)
        d, i, j = self.particles.dim, self.bonds.i, self.bonds.j
        H = (self._bond_hessians(u_after, bonds) * after[bonds, None, None]
             - self._bond_hessians(u, bonds) * before[bonds, None, None])
        dofs = local[d * np.stack([i[bonds], j[bonds]], 1)[:, :, None] + np.arange(d)]  # (bonds, 2, d)
        p, q = dofs[:, 0], dofs[:, 1]
        rows = np.concatenate([np.broadcast_to(x[:, :, None], H.shape) for x in (p, q, p, q)])
        cols = np.concatenate([np.broadcast_to(x[:, None, :], H.shape) for x in (p, q, q, p)])
        keep = (rows >= 0) & (cols >= 0)
        return rows[keep], cols[keep], np.concatenate([H, H, -H, -H])[keep]

    def _bonds_among(self, mask: np.ndarray) -> np.ndarray:
        """The bonds (sorted) whose two end particles are both in ``mask``: read from the
        bonds of the masked particles (by their first end i), not from a pass over all bonds."""
        indptr, by_first = self._bonds_by_first
        p = np.flatnonzero(mask)
        counts = indptr[p + 1] - indptr[p]
        offsets = np.repeat(indptr[p] - np.cumsum(counts) + counts, counts)
        candidates = by_first[offsets + np.arange(counts.sum())]
        return np.sort(candidates[mask[self.bonds.j[candidates]]])

    @cached_property
    def _bonds_by_first(self) -> tuple[np.ndarray, np.ndarray]:
        """(indptr, bonds): the bonds whose first end i is particle p are bonds[indptr[p]:indptr[p + 1]]."""
        i = self.bonds.i
        indptr = np.concatenate([[0], np.cumsum(np.bincount(i, minlength=self.particles.n))])
        return indptr, np.argsort(i, kind="stable")

    def _tangent(self, intact, u) -> np.ndarray:
        """Values of T on the material's pattern."""
        intact = torch.as_tensor(intact)
        if not self.geometric:
            return self.material.numeric_stiffness(self.params, intact).numpy().copy()
        H = self._bond_hessians(u) * intact.numpy()[:, None, None]
        N, d, i, j = self.particles.n, self.particles.dim, self.bonds.i, self.bonds.j
        S = np.stack([np.bincount(i, H[:, a, c], minlength=N) + np.bincount(j, H[:, a, c], minlength=N)
                      for a in range(d) for c in range(d)], 1)  # ii: the sum over the bonds of i
        return np.concatenate([-H.reshape(-1), S.reshape(-1)])[tangent_sources(self.material)]

    def _bond_hessians(self, u, bonds=slice(None)) -> np.ndarray:
        """Bond-based: the intact Hessian blocks k [c I + (1 - c) n n^T] (b, d, d) of
        ``bonds`` at u (default 0), c = max(e / r, 0) (module docstring)."""
        d, i, j = self.particles.dim, self.bonds.i[bonds], self.bonds.j[bonds]
        xi = self.kinematics.xi[bonds].numpy()
        y = xi if u is None else xi + (u[j] - u[i]).numpy()
        r = np.sqrt(np.einsum("ba,ba->b", y, y))
        n = y / r[:, None]
        c = np.maximum(1 - self.kinematics.length[bonds].numpy() / r, 0)
        k = np.broadcast_to(self.forces.k.detach().numpy(), (self.n_bonds,))[bonds]
        H = ((k * (1 - c))[:, None] * n)[:, :, None] * n[:, None, :]
        for a in range(d):
            H[:, a, a] += k * c
        return H

    def _restricted(self, active: np.ndarray):
        key = active.tobytes()
        if key not in self._patterns:
            mask = np.zeros(self.material.pattern.n, dtype=bool)
            mask[active] = True
            sub, entries = self.material.pattern.restrict(mask)
            k = np.arange(sub.n)
            self._patterns = {key: (sub, entries, sub.position(k, k))}  # keep the latest only
        return self._patterns[key]


_SOURCES = weakref.WeakKeyDictionary()  # material -> tangent_sources, as long as the material lives


def tangent_sources(material) -> np.ndarray:
    """For each entry of a bond-based ``material``'s pattern, its place in [-H (bonds, d, d),
    S (particles, d, d)]: an off-diagonal block belongs to one bond (H symmetric serves ij and
    ji), a diagonal block is the sum S over a particle's bonds. It depends on the material
    alone, so it is made once per material: the bodies of an ensemble's draws, one scene each
    on a shared material (``bayespd.scenes.notched_plate``), share it."""
    if material not in _SOURCES:
        _SOURCES[material] = _tangent_sources(material)
    return _SOURCES[material]


def _tangent_sources(material) -> np.ndarray:
    n, d, pattern = material.particles.n, material.particles.dim, material.pattern
    i, j = material.bonds.i, material.bonds.j

    def blocks(p, q):  # pattern positions (len(p), d, d) of the blocks (p_k, q_k)
        a = np.arange(d)
        rows = np.broadcast_to(d * p[:, None, None] + a[:, None], (len(p), d, d))
        cols = np.broadcast_to(d * q[:, None, None] + a[None, :], (len(p), d, d))
        return pattern.position(rows.reshape(-1), cols.reshape(-1)).reshape(-1)

    if np.any(np.diff(np.sort(np.minimum(i, j) * n + np.maximum(i, j))) == 0):
        raise ValueError("a bond is listed twice: give each pair of particles one bond")
    diagonal = blocks(np.arange(n), np.arange(n))
    sources = np.full(pattern.nnz, -1)
    bond_entries = np.arange(len(i) * d * d)
    sources[blocks(i, j)] = bond_entries
    sources[blocks(j, i)] = bond_entries
    sources[diagonal] = len(i) * d * d + np.arange(len(diagonal))
    if np.any(sources < 0):
        raise ValueError("the pattern has entries no bond makes: a bond-based pattern is "
                         "the bonds' blocks and the diagonal")
    return sources
