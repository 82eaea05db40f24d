"""Linear pieces shared by the time integrators.

``LinearForce`` is f(u) = p - A u with A = K + eps I: the force of the potential of Dodwell 2019
eq 3 with the linearised bond energy, V(u) = u^T K u / 2 - p^T u + (eps / 2) u^T u, of the
intact or the damaged body (``material.terms(params, intact)``).
``largest_eigenvalue`` (Lanczos) gives stable time steps; ``bayespd.linalg.factors`` factorises.
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import torch

from bayespd.linalg.assembly import to_numpy
from bayespd.connectivity import floating_particles
from bayespd.linalg.factors import spd_factor
from bayespd.linalg.sparse import NotPositiveDefiniteError

class LinearForce:
    """f(u) = p - A u for a sparse symmetric A (n x n) and load p (n,); u is (n,) or (n, batch).

    ``matrix`` is A as scipy CSR (what the semi-implicit Langevin step takes as its operator).
    ``floating``: particles whose piece of the body has no support and no confinement, so
    that A is singular (from ``linear_elastic``; empty when unknown).
    """

    def __init__(self, A, p=None, floating=None):
        self.matrix = sp.csr_matrix(A, dtype=np.float64)
        n = self.matrix.shape[0]
        self.load = torch.zeros(n) if p is None else torch.as_tensor(p, dtype=torch.float64).reshape(-1)
        if self.load.shape != (n,):
            raise ValueError(f"load must have {n} entries, got {tuple(self.load.shape)}")
        self.floating = np.zeros(0, dtype=np.int64) if floating is None else np.asarray(floating)

    @property
    def n(self) -> int:
        return self.matrix.shape[0]

    def stiffness_times(self, u: torch.Tensor) -> torch.Tensor:
        """A u."""
        return torch.from_numpy(np.asarray(self.matrix @ to_numpy(u))).to(u.dtype)

    def __call__(self, u: torch.Tensor) -> torch.Tensor:
        p = self.load.to(u.dtype).reshape(-1, *([1] * (u.dim() - 1)))
        return p - self.stiffness_times(u)

    def energy(self, u: torch.Tensor) -> torch.Tensor:
        """V(u) = u^T A u / 2 - p^T u (per batch column)."""
        return (u * (0.5 * self.stiffness_times(u) - self.load.to(u.dtype).reshape(-1, *([1] * (u.dim() - 1))))).sum(0)

    def equilibrium(self) -> torch.Tensor:
        """A^-1 p: the minimiser of V, i.e. the mean of the invariant law in the elastic regime.
        Refused (NotPositiveDefiniteError naming a particle and the fix) when A is singular
        because a piece of the body floats."""
        if len(self.floating):
            k = int(self.floating[0])
            raise NotPositiveDefiniteError(
                f"the stiffness is singular: {len(self.floating)} particle(s) (e.g. particle {k}) "
                "belong to pieces held by no Dirichlet region and no intact bond to one (a particle "
                "isolated by damage, a fragment, or an unsupported body), and eps = 0, so they "
                "have rigid-body modes. Pass eps > 0 to linear_elastic (the confinement "
                "(eps/2) u.u of Dodwell 2019 eq 3; e.g. 1e-6 times the mean diagonal of K), or "
                "constrain or remove those particles")
        return torch.from_numpy(spd_factor(self.matrix).solve(self.load.numpy()))


def linear_elastic(material, params: dict, load=None, eps: float = 0.0,
                   constraints=None, intact=None) -> LinearForce:
    """The linearised elastic force of ``material`` with confinement eps (Dodwell 2019 eq 3).

    ``load`` is nodal forces (N, dim). With ``constraints`` (``boundary.Constraints``) the
    state is the free dofs and prescribed displacements enter the load as -K_fc u_c;
    without, the state is all N*dim dofs (node-major) and eps > 0 removes the rigid modes.
    ``intact``: per-bond intact fractions of a damage state (``material.terms``). With eps = 0
    the particles of unsupported pieces are recorded in ``floating`` (a singular A is fine for
    explicit dynamics; ``LinearForce.equilibrium`` refuses it).
    """
    if not eps >= 0:
        raise ValueError(f"the confinement eps must be >= 0, got {eps}")
    values = material.numeric_stiffness(params, intact)
    n_all = material.pattern.n
    p = torch.zeros(n_all) if load is None else torch.as_tensor(load, dtype=torch.float64).reshape(-1)
    if p.shape != (n_all,):
        raise ValueError(f"load must be nodal forces (N, dim) with N*dim = {n_all}")
    if constraints is None:
        K = material.pattern.matrix(values)
    else:
        K = constraints.pattern.matrix(constraints.free_values(values))
        if constraints.has_prescribed:
            u_c = constraints.prescribed.reshape(-1).numpy()
            p = p - torch.from_numpy(material.pattern.matrix(values) @ u_c)
        p = constraints.free(p)
    floating = None
    if eps == 0:
        fixed = np.zeros(material.particles.n, dtype=bool) if constraints is None else constraints.fixed_particles
        floating = floating_particles(material.bonds, intact, fixed)
    return LinearForce(K + eps * sp.identity(K.shape[0], format="csr"), p, floating)


def as_matvec(operator):
    """A numpy matvec from a scipy matrix or a callable."""
    if callable(operator):
        return operator
    return lambda v: operator @ v


def largest_eigenvalue(matvec, n: int, tol: float = 1e-8) -> float:
    """lambda_max of a symmetric operator on R^n by Lanczos (scipy ``eigsh``, fixed start
    vector, so deterministic). The Ritz value approaches lambda_max from below."""
    if n == 1:
        return float(np.asarray(matvec(np.ones(1))).reshape(-1)[0])
    op = spla.LinearOperator((n, n), matvec=lambda v: np.asarray(matvec(v)).reshape(-1), dtype=np.float64)
    v0 = np.random.default_rng(0).standard_normal(n)
    return float(spla.eigsh(op, k=1, which="LA", tol=tol, v0=v0, return_eigenvectors=False)[0])


def hessian_operator(force, u: torch.Tensor, h: float | None = None):
    """v -> (f(u) - f(u + h v)) / h: the Hessian of V at u by a forward difference (exact
    for a linear force), for stability limits when no operator is given; the default h,
    eps^(3/8) (1.3e-6 in float64, 2.5e-3 in float32), keeps the rounding error eps / h small."""
    u = u.detach().reshape(u.shape[0], -1)[:, 0]
    f0 = force(u)
    h = h or torch.finfo(u.dtype).eps ** 0.375 * max(1.0, float(u.abs().max()))

    def matvec(v):
        v = torch.as_tensor(np.asarray(v), dtype=u.dtype)
        return to_numpy((f0 - force(u + h * v)) / h)

    return matvec
