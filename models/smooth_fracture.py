"""Quasi-static loading of a bond-based body under the smoothed damage law (You 2023 eq 3.10),
differentiable in the critical stretch s0: the forward model of ``models/damage_criterion.py``.

Small-strain kinematics: the extension of bond b is e_b = n_b . (u_j - u_i) = (B u)_b, its
stretch s_b = e_b / |xi_b|. With the history maximum h_b of the stretch (the reference counts
as 0) and the intact fraction gamma_b = (1 - tanh((max(h_b, s_b) - s0) / eta)) / 2, the strain
energy is 1/2 sum_b k_b gamma_b e_b^2 (k_b of ``NonlinearBonds(material).at(...)``, the PMB
coefficients) and equilibrium at load factor lam on the free dofs f is

    R(u_f) = B_f^T (k gamma e) = 0,   e = B_f u_f + lam B_c u_c,

(displacement control: the Dirichlet values are lam times theirs). Monolithic Newton with the
exact Jacobian J = B_f^T diag(k (gamma + gamma' s [s > h])) B_f (dense: small scenes), halving
steps that do not reduce |R|. Gradient in s0: at each converged step one more Newton update
u_f <- u* - J^-1 R(u*; h, s0) with u* and J detached carries exactly du_f/ds0 =
-J^-1 (dR/ds0 + dR/dh dh/ds0) (implicit function theorem), and h <- max(h, s) carries the
history's dependence on s0 into the next step. First derivatives are exact; second ones are
not (use NUTS, SVI or Laplace with hessian="gauss-newton").
"""
from __future__ import annotations

import numpy as np
import torch

from bayespd import Constraints, ConvergenceError, NonlinearBonds


class SmoothFracture:
    """A bond-based (``pairwise``) material at ``params`` (with "delta") under Dirichlet regions (their values are
    those at load factor 1), with the smoothed damage law of width ``eta``."""

    def __init__(self, material, params: dict, dirichlet, eta: float):
        if not material.pairwise:
            raise ValueError("SmoothFracture is bond-based (a pairwise law): build the scene with "
                             "bp.BondBased (or another pairwise law), not bp.LPS")
        if not float(eta) > 0:
            raise ValueError(f"the smoothing width eta must be positive, got {eta}")
        p = material.particles
        bonds = material.bonds
        with torch.no_grad():
            self.k = NonlinearBonds(material).at(params).k.detach()
        n_hat = bonds.xi / bonds.length[:, None]
        B = np.zeros((bonds.n, p.n * p.dim))
        rows = np.arange(bonds.n)
        for a in range(p.dim):
            B[rows, p.dim * bonds.j + a] += n_hat[:, a]
            B[rows, p.dim * bonds.i + a] -= n_hat[:, a]
        c = Constraints(p, None, list(dirichlet))
        if not c.has_prescribed:
            raise ValueError("displacement control needs a Dirichlet region with a non-zero value")
        self.constraints, self.eta, self.particles = c, float(eta), p
        self.B_f = torch.as_tensor(B[:, c.free_dofs])
        self.e_c = torch.as_tensor(B @ c.prescribed.numpy().reshape(-1))  # extension per unit lam
        self.length = torch.as_tensor(bonds.length)

    def _parts(self, u_f, lam, h, s0):
        e = self.B_f @ u_f + lam * self.e_c
        s = e / self.length
        top = torch.maximum(h, s)
        t = torch.tanh((top - s0) / self.eta)
        gamma = 0.5 * (1 - t)
        slope = torch.where(s > h, -0.5 * (1 - t**2) / self.eta, torch.zeros_like(s))
        return e, s, gamma, slope

    def residual(self, u_f, lam, h, s0):
        e, _, gamma, _ = self._parts(u_f, lam, h, s0)
        return self.B_f.T @ (self.k * gamma * e)

    def _jacobian(self, u_f, lam, h, s0):
        _, s, gamma, slope = self._parts(u_f, lam, h, s0)
        return self.B_f.T @ ((self.k * (gamma + slope * s))[:, None] * self.B_f)

    def _newton(self, u_f, lam, h, s0, rtol, max_iter):
        """Newton with step halving; where it stalls (an unstable crack step: J indefinite),
        staggered iterations (secant stiffness B_f^T diag(k gamma) B_f, SPD, damage updated
        between solves, as bayespd.solvers.quasistatic) bring it to the fixed point."""
        scale = float((self.B_f.T @ (self.k * lam * self.e_c)).norm()) + 1e-300
        r = self.residual(u_f, lam, h, s0)
        for it in range(max_iter + 1000):
            if float(r.norm()) <= rtol * scale:
                return u_f
            if it < max_iter:
                du = torch.linalg.solve(self._jacobian(u_f, lam, h, s0), r)
                step = 1.0
                for _ in range(30):
                    trial = u_f - step * du
                    r_trial = self.residual(trial, lam, h, s0)
                    if float(r_trial.norm()) < float(r.norm()):
                        break
                    step /= 2
                else:  # no descent: switch to the staggered iteration
                    it = max_iter
            if it >= max_iter:
                gamma = self._parts(u_f, lam, h, s0)[2]
                K = self.B_f.T @ ((self.k * gamma)[:, None] * self.B_f)
                trial = torch.linalg.solve(K, -self.B_f.T @ (self.k * gamma * lam * self.e_c))
                r_trial = self.residual(trial, lam, h, s0)
            u_f, r = trial, r_trial
        raise ConvergenceError(f"the equilibrium at load factor {lam:g} did not converge "
                               f"(|R| = {float(r.norm()):.3g}): use smaller load steps or a larger eta")

    def _step(self, u_f, h, lam, s0, rtol, max_iter):
        """Equilibrium at lam from (u_f, h), then the implicit-differentiation update."""
        with torch.no_grad():
            u_star = self._newton(u_f.detach(), lam, h.detach(), s0.detach(), rtol, max_iter)
            J = self._jacobian(u_star, lam, h.detach(), s0.detach())
        u_f = u_star - torch.linalg.solve(J, self.residual(u_star, lam, h, s0))
        return u_f, torch.maximum(h, self._parts(u_f, lam, h, s0)[1])

    def _advance(self, u_f, h, lam_from, lam, s0, rtol, max_iter, splits):
        """From lam_from to lam; a step whose Newton iteration fails is halved (up to
        ``splits`` times): the intermediate equilibria join the history, as finer load steps."""
        try:
            return self._step(u_f, h, lam, s0, rtol, max_iter)
        except ConvergenceError:
            if splits == 0:
                raise
        mid = 0.5 * (lam_from + lam)
        u_f, h = self._advance(u_f, h, lam_from, mid, s0, rtol, max_iter, splits - 1)
        return self._advance(u_f, h, mid, lam, s0, rtol, max_iter, splits - 1)

    def run(self, s0, load_factors, observe=None, rtol: float = 1e-10, max_iter: int = 50, splits: int = 4):
        """Displacements (N, dim) at each load factor (or ``observe(u)`` of each), stacked;
        differentiable in s0 (see the module docstring)."""
        s0 = torch.as_tensor(s0, dtype=torch.float64)
        c = self.constraints
        h = torch.zeros(len(self.length))
        u_f = torch.zeros(len(c.free_dofs))
        out, previous = [], 0.0
        for lam in np.asarray(load_factors, dtype=float):
            u_f, h = self._advance(u_f, h, previous, lam, s0, rtol, max_iter, splits)
            previous = lam
            u = c.embed(u_f) + lam * c.prescribed
            out.append(u if observe is None else observe(u))
        return torch.stack(out)
