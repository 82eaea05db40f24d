"""Overdamped Langevin dynamics of Dodwell 2019 eq 4,

    dU = -eta^-1 C grad V(U) dt + sqrt(2 C) dB,   f = -grad V (internal + external force),

with V of eq 3 (including the confinement (eps/2) u.u) and a noise covariance C
(``bayespd.solvers.noise``).

Invariant law. The Fokker-Planck equation of eq 4 is d_t rho = div(C (eta^-1 rho grad V +
grad rho)), whose flux vanishes for rho ~ exp(-V / eta): eta is the temperature, and for any
positive-definite C the invariant law in the elastic regime, V = u^T A u / 2 - p^T u with
A = K + eps I, is N(A^-1 p, eta A^-1). Eq 4 as printed therefore already has the law the
issue states; the form dU = -C grad V dt + sqrt(2 eta C) dB is the same process run at time
t / eta. We implement eq 4 as printed: with dB = 0 it is the paper's gradient flow
eta du/dt = -grad V, preconditioned by C.

Time stepping, the theta-scheme with a fixed SPD operator A (the linearised Hessian of V),
a = dt / eta and Brownian increments dB_n ~ N(0, dt I):

    (I + theta a C A) U_{n+1} = U_n + a C (f(U_n) + theta A U_n) + sqrt(2) C^{1/2} dB_n,

solved in its increment form (I + theta a C A) (U_{n+1} - U_n) = a C f(U_n) + sqrt(2) C^{1/2} dB_n
(the same equation; no product with A, and no cancellation between U_n and its update).

theta = 0 is Euler-Maruyama (no solve), stable for linear f iff dt < 2 eta / lambda_max(C A)
(for theta < 1/2 the limit is 2 eta / ((1 - 2 theta) lambda_max(C A))); theta >= 1/2 is
unconditionally stable for linear f; theta = 1 is linearly implicit Euler (damps stiff modes,
the choice for nonlinear forces). For f = p - A U the chain's stationary law is exactly
N(A^-1 p, eta (A + (theta - 1/2) a A C A)^-1): theta = 1/2 samples eta A^-1 exactly at any dt;
EM's covariance is too large and implicit Euler's too small by O(dt).
"""
from __future__ import annotations

import math

import numpy as np
import torch

from bayespd.solvers.dynamics import (GrowthMonitor, NumericalInstabilityError, Trajectory, _check_steps,
                                      _Saver, _fix)
from bayespd.linalg.assembly import to_numpy
from bayespd.solvers.linear import as_matvec, hessian_operator, largest_eigenvalue


def _generator(generator) -> torch.Generator:
    if isinstance(generator, torch.Generator):
        return generator
    if isinstance(generator, (int, np.integer)):
        return torch.Generator().manual_seed(int(generator))
    raise ValueError("pass generator= (a torch.Generator or an int seed) so the run is "
                     "reproducible, or brownian= increments")


class Langevin:
    """Dodwell 2019 eq 4 for ``force(u) -> f`` (u of shape (n,) or (n, chains)), a
    ``noise.Covariance`` C on the same n dofs, temperature/damping ``eta`` and, for
    theta > 0, ``operator`` A (scipy sparse SPD, e.g. ``LinearForce.matrix``: K + eps I)."""

    def __init__(self, force, covariance, eta: float = 1.0, operator=None):
        if not (math.isfinite(eta) and eta > 0):
            raise ValueError(f"eta must be finite and positive, got {eta}")
        if operator is not None and operator.shape != (covariance.n, covariance.n):
            raise ValueError(f"operator must be {covariance.n} x {covariance.n} like C")
        self.force, self.C, self.eta, self.operator = force, covariance, float(eta), operator
        self._cached = None

    def explicit_limit(self, u0=None) -> float:
        """2 eta / lambda_max(C A), the Euler-Maruyama step limit, with A = ``operator`` or
        the force's Hessian at u0; lambda_max(C A) = lambda_max(T^T A T), C = T T^T."""
        A = as_matvec(self.operator) if self.operator is not None else hessian_operator(self.force, u0)
        T = self.C

        def matvec(v):
            Av = np.asarray(A(to_numpy(T.sample(torch.from_numpy(v)))))
            return to_numpy(T.adjoint(torch.from_numpy(Av)))

        return 2 * self.eta / largest_eigenvalue(matvec, T.n_xi)

    def euler_maruyama(self, u0, dt: float, steps: int, **kw) -> Trajectory:
        """theta = 0 (see ``run``)."""
        return self.run(u0, dt, steps, theta=0.0, **kw)

    def semi_implicit(self, u0, dt: float, steps: int, theta: float = 1.0, **kw) -> Trajectory:
        """The linearly implicit theta-scheme, theta in [1/2, 1] (see ``run``)."""
        if not 0.5 <= theta <= 1:
            raise ValueError("semi_implicit needs theta in [1/2, 1]; theta = 0 is euler_maruyama")
        return self.run(u0, dt, steps, theta=theta, **kw)

    def run(self, u0, dt: float, steps: int, theta: float = 0.0, generator=None, brownian=None,
            save_every: int = 0) -> Trajectory:
        """``steps`` steps of the theta-scheme from u0 (n,) or (n, chains).

        Noise from ``generator`` (torch.Generator or int seed), or given Brownian increments
        ``brownian`` (steps, n_xi[, chains]) of variance dt (zeros: the deterministic flow).
        Blow-up (non-finite or geometric growth of |U_n - U_0|^2) raises
        NumericalInstabilityError naming the step limit.
        """
        _check_steps(dt, steps, save_every)
        if not 0 <= theta <= 1:
            raise ValueError("theta must lie in [0, 1]")
        if theta > 0 and self.operator is None:
            raise ValueError("theta > 0 needs operator= (the sparse SPD A, e.g. K + eps I)")
        if u0.shape[0] != self.C.n:
            raise ValueError(f"u0 must have {self.C.n} rows (the dofs of C)")
        batch = tuple(u0.shape[1:])
        if brownian is not None:
            if tuple(brownian.shape) != (steps, self.C.n_xi, *batch):
                raise ValueError(f"brownian must have shape {(steps, self.C.n_xi, *batch)}")
        else:
            generator = _generator(generator)
        a = dt / self.eta
        solve = self._solver(theta * a) if theta > 0 else None
        u = u0.clone()
        monitor, saves = GrowthMonitor(steps), _Saver(u, save_every)
        for n in range(1, steps + 1):
            dB = brownian[n - 1] if brownian is not None else math.sqrt(dt) * torch.randn(
                (self.C.n_xi, *batch), generator=generator, dtype=u.dtype)
            increment = a * self.C.matvec(self.force(u)) + math.sqrt(2) * self.C.sample(dB)
            u_new = u + (increment if solve is None else solve(increment))
            if monitor(n, float(((u_new - u0) ** 2).sum())):
                raise self._blow_up(n, dt, theta, u0, monitor)
            u = u_new
            saves(n, u)
        return Trajectory(saves.times(dt), saves.stack(), u)

    def _solver(self, b: float):
        """The solver of (I + b C A) x = r, factorised once per b (the latest kept)."""
        if self._cached is None or self._cached[0] != b:
            self._cached = (b, self.C.implicit_solver(self.operator, b))
        return self._cached[1]

    def _blow_up(self, n, dt, theta, u0, monitor) -> NumericalInstabilityError:
        where = (f"the Langevin run (theta = {theta:g}) blew up at step {n} (t = {n * dt:g}): "
                 f"|U_n - U_0|^2 grew beyond {monitor.factor:.0e} times its size by step {max(n // 2, 1)}")
        if theta >= 0.5:
            return NumericalInstabilityError(
                f"{where}. theta >= 1/2 is unconditionally stable for the linear part, so the "
                "force is stiffer than the operator A of the implicit step: reduce dt or pass a "
                "stiffer operator")
        limit = self.explicit_limit(u0) / (1 - 2 * theta)
        return NumericalInstabilityError(
            f"{where}. dt = {dt:g} against the explicit limit 2 eta / ((1 - 2 theta) "
            f"lambda_max(C A)) = {limit:g} at U_0: {_fix(dt, limit)}, or use semi_implicit "
            "(theta >= 1/2), which is stable at any dt")
