"""Phase 1 of paper 004 (eqs 4.2-4.7) with a structured model error: the posterior over the 2D
moduli, the horizon and the kernel shape from the MD sheet's measured static dispersion (issue 28).

    lambda + mu, mu, delta, shape (or d)   as models/md_kernel.py
    s_b   ~ HalfNormal(0.1)   the relative model error on shell b of |k| h
    C_o   : Delta_o = L_o^T C_o L_o - I ~ GOE(s_b(k_o)) + GOE(sigma_m),   S(k_o) = L_o L_o^T the PD symbol

C_o is the compliance the sinusoidal loads measure on orbit o (``bayespd.learn.dispersion``).
PD and the coarse-grained MD differ by their dispersion, an error correlated over the whole sheet
for each load: the nodal likelihood of md_kernel.py counts each orbit's error 2 N times per
load (and its posterior sd of mu is 0.03 % where the learned moduli miss the MD sheet's long-wave
ones by 3 %). Here each orbit holds one symmetric relative compliance error Delta_o, entries
independent, N(0, s^2) on the diagonal and N(0, s^2 / 2) off it (the rotation-invariant law, so
the choice of factor L does not matter), the off-diagonal only where n1 n2 != 0 (on the axes
both fields have none by mirror symmetry). C = L^-T (I + Delta) L^-1 is linear in Delta, so the
density of C is that of Delta times det(S)^(q/2) (q = 3 or 2 entries).

``measurement`` sigma_m: the measured compliances are not exact (the MD sheet's response at the
loads' size is not linear, and coarse graining adds its part): a measurement error of the same law,
sd sigma_m, fixed from the data (experiments/md_learning.py: the training records' response that
no compliance holds, ``learn.dispersion.off_orbit_response``). On the training compliances it
adds to the model error's variance (s_b^2 + sigma_m^2: the two are not separable there); it
separates them in prediction, where the model error at a training wave is known only up to it
(``learn.dispersion.orbit_error_posterior``) and a predicted record has its own.
"""
from __future__ import annotations

import math

import pyro
import pyro.distributions as dist
import torch
from pyro.distributions.torch_distribution import TorchDistribution
from torch.distributions import constraints

from bayespd import relative_compliance_error, shell_of, solvability_penalty
from bayespd.models.md_kernel import kernel_prior
from bayespd.models.observations import check_shape


class CompliancePerOrbit(TorchDistribution):
    """Measured compliances C (O, 2, 2) given the PD symbols S (O, 2, 2), the relative error sd s
    (O,) and ``off_diagonal`` (O,): the law in the module docstring."""

    arg_constraints = {}
    support = constraints.real

    def __init__(self, S, s, off_diagonal, tau=None, validate_args=None):
        self.S, self.s, self.tau = S, s, tau
        self.off = torch.as_tensor(off_diagonal, dtype=torch.bool)
        super().__init__(torch.Size(), S.shape[-3:], validate_args=validate_args)

    def log_prob(self, C):
        Delta, logdet = relative_compliance_error(self.S, C)
        half = math.sqrt(0.5)
        entries = ((Delta[..., 0, 0], self.s, 1.0), (Delta[..., 1, 1], self.s, 1.0),
                   (Delta[..., 0, 1][self.off], half * self.s[self.off], half))
        total = ((1.0 + self.off.to(logdet.dtype) / 2) * logdet).sum()  # det(S)^(q/2), q = 2 or 3
        for value, sd, w in entries:
            if self.tau is None:
                total = total + dist.Normal(0.0, sd).log_prob(value).sum()
            else:  # plus one offset of the entry common to every orbit, sd tau (tau / sqrt 2 off the diagonal)
                factor = (w * self.tau).expand(len(value), 1)
                total = total + dist.LowRankMultivariateNormal(torch.zeros_like(value), factor, sd**2).log_prob(value)
        return total

    def sample(self, sample_shape=torch.Size()):
        with torch.no_grad():
            shape = torch.Size(sample_shape) + self.S.shape
            A = torch.randn(shape, dtype=self.S.dtype) * self.s[:, None, None]
            Linv = torch.linalg.inv(torch.linalg.cholesky(self.S))
            if self.tau is not None:
                A = A + torch.randn(torch.Size(sample_shape) + (1, 2, 2), dtype=A.dtype) * self.tau
            return Linv.transpose(-1, -2) @ (torch.eye(2, dtype=A.dtype) + _goe(A, self.off)) @ Linv


def _goe(A, off):
    """A symmetric matrix with diagonal A's and off-diagonal (A_01 + A_10) / 2 times ``off``:
    N(0, s^2) and N(0, s^2 / 2) entries for A of iid N(0, s^2)."""
    offdiag = (A[..., 0, 1] + A[..., 1, 0]) / 2 * off
    return torch.stack([torch.stack([A[..., 0, 0], offdiag], -1), torch.stack([offdiag, A[..., 1, 1]], -1)], -2)


def md_dispersion(sheet, wavevectors, off_diagonal, shells, nominal: float, positive_kernel: bool = False,
                  common: bool = True, measurement: float = 0.0):
    """A Pyro model ``model(C=None)`` for the compliances C (O, 2, 2) measured at ``wavevectors``
    (O, 2) (``bayespd.learn.dispersion.measured_compliance``; ``off_diagonal`` (O,) as it returns);
    ``shells``: edges in |k| h of the relative errors' shells (each must hold an orbit).
    ``common``: with the offset common to all orbits (site ``tau``); ``measurement``: sigma_m
    (module docstring). Sites ``lam_plus_mu``, ``mu``, ``delta``, ``shape`` (or ``d``), ``s`` (and ``tau``)."""
    k = torch.as_tensor(wavevectors, dtype=torch.float64)
    shell = shell_of(k.numpy(), sheet.material.particles.h, shells)
    found = torch.bincount(shell, minlength=len(shells) + 1)
    if not bool((found > 0).all()):
        raise ValueError(f"every shell needs an orbit (orbits per shell {found.tolist()}): choose edges in |k| h "
                         "between the loads' wavenumbers")
    if not measurement >= 0:
        raise ValueError(f"the measurement error's sd must be non-negative, got {measurement}")
    draw = kernel_prior(sheet, nominal, positive_kernel)
    count = int(2 * len(k) + torch.as_tensor(off_diagonal).sum())

    def model(C=None):
        if C is not None:
            C = check_shape(C, (len(k), 2, 2), "C", "the measured compliance of every orbit")
        params = draw()
        s = pyro.sample("s", dist.HalfNormal(0.1 * torch.ones(len(shells) + 1, dtype=k.dtype)).to_event(1))
        pyro.factor("solvability", -count * solvability_penalty(sheet, params))
        tau = pyro.sample("tau", dist.HalfNormal(torch.tensor(0.1, dtype=k.dtype))) if common else None
        sd = (s[shell] ** 2 + measurement**2).sqrt()
        pyro.sample("C", CompliancePerOrbit(sheet.symbol(params, k), sd, off_diagonal, tau), obs=C)

    return model
