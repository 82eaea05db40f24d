"""Geometrically exact (nonlinear) bond kinematics, internal force and potential energy.

With eta = u_j - u_i and the deformed bond y = xi + eta, the extension is e = |y| - |xi| and
the stretch s = e / |xi| (Dodwell 2019 eq 1-2; You 2023 eq 3.11). Each bond carries its intact
fraction mu in [0, 1] (from ``bayespd.damage``; 1 when no damage law is present), held fixed
while the force is taken: the force is -dV/du at the current damage state.

The material owns its law (``bayespd.materials``): ``at(params)`` asks it for its force object
(``material.nonlinear``), whose ``force``/``energy`` are the per-step calls; e.g. PMB's in
``materials/pmb.py``, LPS's (with the floored weighted volume of a broken particle) in
``materials/lps.py``.

Total potential energy (Dodwell 2019 eq 3): V(u) = sum of bond energies - p . u + (eps/2) u . u.
For small u both forces equal the linearised -K u up to O(|u|^2).

The force is written by hand, never through autograd of the energy: one sparse product with
the signed bond-dof incidence D (eta = D u, rows (component, bond)), a per-bond scalar, and one
with D^T (f = -D^T (t y / |y|)); it is differentiable (twice) in u, the moduli, the horizon and
mu. The two CSR products replace four gathers and a scatter of the bond arrays
(benchmarks/README.md, "A crack zone ordered last"). On the CPU, with no gradient to record,
the stretch and the PMB force are one compiled loop each (``bond_loops``, numba, optional).

Rounding: the extension is evaluated as e = eta . (xi + y) / (|y| + |xi|) (= |y| - |xi|,
since |y|^2 - |xi|^2 = eta . (y + xi)), which carries a relative rounding error of a few
machine epsilons at any strain; |y| - |xi| would lose log10(1/s) digits to cancellation
(in float32 at s = 1e-4 a relative error of 1e-3). This is what makes float32 usable for
explicit dynamics (``at(..., dtype=torch.float32)``; float64 is the default).
"""
from __future__ import annotations

import warnings
from functools import cached_property

import numpy as np
import scipy.sparse as sp
import torch

from bayespd import bond_loops


class NonlinearBonds:
    """Exact bond kinematics of a material (``bayespd.materials``; index tensors built once).

    ``at(params)`` evaluates the material's per-bond coefficients once per parameter value
    (``params`` holds "delta") and returns its force object, whose ``force(u, intact)`` /
    ``energy(u, intact, load, eps)`` are the cheap per-step calls; ``force(u, params, intact)``
    does both at once.
    """

    def __init__(self, material):
        self.material = material
        self.i, self.j = material.i, material.j
        self.xi = torch.as_tensor(material.bonds.xi)
        self.length = material.length
        self.n, self.dim = material.particles.n, material.dim
        self._geometry = {}

    def geometry(self, dtype) -> tuple[torch.Tensor, torch.Tensor]:
        """(xi as (dim, n_bonds), |xi|) in ``dtype`` (converted once per dtype)."""
        if dtype not in self._geometry:
            if dtype not in (torch.float32, torch.float64):
                raise ValueError(f"u must be float64 (default) or float32, got {dtype}")
            self._geometry[dtype] = (self.xi.to(dtype).T.contiguous(), self.length.to(dtype))
        return self._geometry[dtype]

    @cached_property
    def ends(self) -> tuple[np.ndarray, np.ndarray]:
        """(i, j) as int32 numpy arrays, for ``bond_loops``."""
        return self.material.bonds.i.astype(np.int32), self.material.bonds.j.astype(np.int32)

    def incidence(self, like: torch.Tensor) -> tuple:
        """(D, D^T) for tensors like ``like`` (its dtype and device): row a n_bonds + b of D
        holds +1 at the flat dof d j + a and -1 at d i + a of bond b = (i, j), so D u stacks
        eta = u_j - u_i by component; scipy CSR on the CPU (faster than torch's CSR
        product there), torch CSR elsewhere. Apply with ``product``."""
        key = ("incidence", like.dtype, like.device)
        if key not in self._geometry:
            d, nb = self.dim, len(self.i)
            i, j = self.material.bonds.i, self.material.bonds.j
            rows = np.tile(np.arange(d * nb), 2)
            cols = np.concatenate([d * j + a for a in range(d)] + [d * i + a for a in range(d)])
            signs = np.repeat([1.0, -1.0], d * nb).astype(np.float32 if like.dtype == torch.float32 else np.float64)
            D = sp.csr_matrix((signs, (rows, cols)), shape=(d * nb, d * self.n))
            pair = (D, D.T.tocsr())
            if like.device.type != "cpu":
                pair = tuple(_torch_csr(A, like.dtype).to(like.device) for A in pair)
            self._geometry[key] = pair
        return self._geometry[key]

    def components(self, u: torch.Tensor):
        """(y, |y|, e) with y (dim, n_bonds) the deformed bonds xi + u_j - u_i by component and
        e = |y| - |xi| (cancellation-free, see the module docstring); pass them to ``stretch``
        and ``force`` to evaluate both at one u from one gather."""
        if u.shape != (self.n, self.dim):
            raise ValueError(f"u must have shape ({self.n}, {self.dim}), got {tuple(u.shape)}")
        xi, length = self.geometry(u.dtype)
        eta = product(*self.incidence(u), u.reshape(-1)).view(self.dim, -1)
        y = eta + xi
        r = torch.hypot(y[0], y[1]) if self.dim == 2 else torch.sqrt(_component_sum(y * y))
        return y, r, _component_sum(eta * (y + xi)) / (r + length)

    def shared_components(self, u: torch.Tensor):
        """``components(u)`` to hand to both ``stretch`` and ``force`` at one u, or None where
        ``bond_loops`` evaluates each from u itself, at less cost (a ``pairwise`` law such as
        PMB on the CPU, no gradient)."""
        compiled = self.material.pairwise and bond_loops.usable(u)
        return None if compiled else self.components(u)

    def kinematics(self, u: torch.Tensor):
        """(y, |y|, e): deformed bond vectors y = xi + u_j - u_i (n_bonds, dim), their lengths
        and the extensions e = |y| - |xi|."""
        y, r, e = self.components(u)
        return y.T, r, e

    def deformed(self, u: torch.Tensor):
        """(y, |y|): deformed bond vectors xi + u_j - u_i and their lengths."""
        return self.kinematics(u)[:2]

    def stretch(self, u: torch.Tensor, components=None) -> torch.Tensor:
        """s = (|xi + eta| - |xi|) / |xi| per bond for u of shape (N, dim) (``components``:
        those of u, when known)."""
        if components is None and bond_loops.usable(u):
            return bond_loops.stretch(u, self.ends, *self.geometry(u.dtype))
        return (components or self.components(u))[2] / self.geometry(u.dtype)[1]

    def at(self, params: dict, dtype=torch.float64):
        """The material's force object (``material.nonlinear``) at ``params`` (differentiable),
        in ``dtype`` (float32: for large explicit dynamics only; the displacement must match)."""
        self.geometry(dtype)
        return self.material.nonlinear(self, params, dtype)

    def force(self, u, params: dict, intact=None) -> torch.Tensor:
        """Internal force -dV_strain/du, shape (N, dim)."""
        return self.at(params, u.dtype).force(u, intact)

    def energy(self, u, params: dict, intact=None, load=None, eps: float = 0.0):
        """Total potential energy V(u) of Dodwell 2019 eq 3."""
        return self.at(params, u.dtype).energy(u, intact, load, eps)


def _component_sum(p: torch.Tensor) -> torch.Tensor:
    """p[0] + p[1] (+ p[2]) for p of shape (dim, n_bonds), row by row: torch's reductions over
    a short leading dimension (``sum(0)``, ``linalg.vector_norm(dim=0)``) are slower
    (benchmarks/README.md, "The 3D bond kernel")."""
    out = p[0] + p[1]
    for row in p[2:]:
        out = out + row
    return out


def product(A, AT, x: torch.Tensor) -> torch.Tensor:
    """A x for a constant sparse A given with its transpose AT (``NonlinearBonds.incidence``:
    scipy CSR, or torch CSR off the CPU); differentiable in x, to any order."""
    if isinstance(A, torch.Tensor):
        return A @ x
    return _ScipyProduct.apply(x, A, AT)


class _ScipyProduct(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x, A, AT):
        ctx.A, ctx.AT = A, AT
        return torch.from_numpy(A @ x.detach().numpy())

    @staticmethod
    def backward(ctx, grad):
        return _ScipyProduct.apply(grad, ctx.AT, ctx.A), None, None


def _torch_csr(A: sp.csr_matrix, dtype) -> torch.Tensor:
    """A scipy CSR matrix as a torch CSR tensor (torch's "beta" notice silenced)."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="Sparse CSR tensor support is in beta")
        return torch.sparse_csr_tensor(torch.from_numpy(A.indptr), torch.from_numpy(A.indices),
                                       torch.from_numpy(A.data).to(dtype), A.shape, check_invariants=True)
