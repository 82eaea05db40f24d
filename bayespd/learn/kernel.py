"""Phase 1 of paper 004's two-phase learning (eqs 4.2-4.7): the 2D Lame moduli lambda, mu, the
Bernstein kernel coefficients D and the horizon delta of an LPS model from non-fracture data.

The model is ``bayespd.materials.LPS`` with the ``Bernstein`` influence (eqs 4.2-4.3) in plane
strain of unit thickness, so its in-plane moduli are the sheet's 2D ones: kappa = K + G/3 =
lambda + mu with K = lambda + 2 mu / 3, G = mu (``lps_params``). Only the shape of D matters (LPS
absorbs its scale into m), so the fit normalises it (``normalised``).

Unknowns: z = (log(lambda + mu), log mu, d) with D = d, or D = exp(d) (``positive=True``: a
non-negative kernel, which phase 2 needs: the damaged LPS recomputes m from the intact bonds, and
with a sign-changing kernel that sum can cancel to ~0 next to a crack). The first two constraints of eq 4.4 (lambda + mu > 0,
mu > 0) hold for every z, lambda may be negative. The eigenvalue constraints of eq 4.4 use
matrices Gamma, Phi of the paper's ref. [47], which the text does not give; their purpose is that
the discrete operator be invertible (apart from rigid motions) with a margin zeta. On a periodic
grid that is exactly a condition on the operator's Fourier symbol S(k) (``PeriodicSheet.symbol``):

    coercivity = min_{k != 0} Lambda_min(S(k)) / (mu V min(|k|^2, delta^-2)) >= zeta,

which is 1 for local elasticity at long waves and <= 0 for a kernel that makes some wave cost no
energy. The fit adds rho * max(0, zeta - coercivity)^2 to the misfit and ``check_solvable``
refuses a result that still violates it.

Misfit: instead of the paper's equation residual (4.6), the displacement misfit of the solved
model, J = mean_m ||u_m(p) - u_m^data||^2 / ||u_m^data||^2 (zero-mean fields). The solve is the
Fourier one (``PeriodicSheet.spectral_solve``: the same numbers as the sparse solve with the
project's adjoint, ``spectral=False``, at a fraction of the cost on the periodic grid); minimised by L-BFGS-B with a
scale-free stopping rule (relative decrease ``ftol`` of J, which is itself relative).
delta (and P) are hyperparameters tuned on the validation loads (Table 1), as in Algorithm 1.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import scipy.optimize
import torch

from bayespd.materials.checks import ParameterRangeError
from bayespd.validate import positive

ZETA = 0.05   # the solvability margin of eq 4.4 (on the normalised coercivity above)
RHO = 10.0    # weight of the constraint penalty against the relative misfit


class UnsolvableKernel(ParameterRangeError):
    """A kernel whose discrete LPS operator violates the solvability constraint (eq 4.4) or has
    m <= 0 (to the samplers and optimisers: a rejected trial point)."""


def lps_params(lam, mu, D, delta) -> dict:
    """LPS params (plane strain, unit thickness) whose in-plane Lame moduli are (lam, mu)."""
    lam, mu = torch.as_tensor(lam), torch.as_tensor(mu)
    return {"K": lam + 2 * mu / 3, "G": mu, "D": torch.as_tensor(D), "delta": torch.as_tensor(delta)}


def normalised(influence, D, delta) -> torch.Tensor:
    """D scaled so that int_0^delta omega r^3 dr equals that of omega = 1 (delta^4 / 4)."""
    D = torch.as_tensor(D)
    return D * (torch.as_tensor(delta) ** 4 / 4) / influence.moment(3, delta, {"D": D})


def coercivity(sheet, params) -> torch.Tensor:
    """The normalised smallest eigenvalue of the operator's symbol (module docstring); differentiable."""
    k = sheet.wavevectors
    low = torch.linalg.eigvalsh(sheet.symbol(params, k))[:, 0]
    k2 = (k**2).sum(1)
    volume = float(sheet.material.particles.volume[0])
    scale = params["G"] * volume * torch.minimum(k2, torch.as_tensor(params["delta"]) ** -2)
    return (low / scale).min()


def solvability_penalty(sheet, params, zeta: float = ZETA) -> torch.Tensor:
    """RHO (zeta - coercivity)^2 where the coercivity is below zeta, else 0 (then no derivative
    of eigvalsh is taken: it is not finite at repeated eigenvalues); ``UnsolvableKernel`` for m <= 0."""
    try:
        c = coercivity(sheet, params)
    except ParameterRangeError:
        raise
    except ValueError as error:  # the material refuses a non-positive weighted volume m
        raise UnsolvableKernel(f"this kernel is not admissible: {error}") from error
    return RHO * (zeta - c) ** 2 if float(c.detach()) < zeta else torch.zeros((), dtype=c.dtype)


def check_solvable(sheet, params, zeta: float = ZETA) -> float:
    """The coercivity of ``params``; raises ``UnsolvableKernel`` below ``zeta``."""
    try:
        c = float(coercivity(sheet, params).detach())
    except ValueError as error:  # the material refuses a non-positive weighted volume m
        raise UnsolvableKernel(f"this kernel is not admissible: {error}") from error
    if not c >= zeta:
        raise UnsolvableKernel(
            f"the kernel violates the solvability constraint (eq 4.4): coercivity {c:.3g} < zeta = {zeta:g}, "
            "so some wave of the discrete LPS operator costs (almost) no energy: fit it with the constraint "
            "(learn_kernel), lower the Bernstein degree, or change the horizon")
    return c


@dataclass
class KernelFit:
    """The learned model: 2D moduli, normalised D, delta; fit diagnostics."""
    lam: float
    mu: float
    D: np.ndarray
    delta: float
    coercivity: float
    misfit: float
    iterations: int
    wall_time_s: float
    converged: bool
    message: str
    history: list = field(default_factory=list)

    def params(self) -> dict:
        return lps_params(self.lam, self.mu, self.D, self.delta)


def relative_errors(sheet, params, forces, u_data, spectral: bool = True) -> torch.Tensor:
    """||u_m(p) - u_m|| / ||u_m|| per load m (zero-mean fields), differentiable in params; by the
    Fourier solve, or (``spectral=False``) the sparse solve with the project's adjoint."""
    u = sheet.spectral_solve(params, forces) if spectral else sheet.solve(params, forces)
    data = sheet.zero_mean(torch.as_tensor(u_data))
    return torch.linalg.vector_norm(u - data, dim=(1, 2)) / torch.linalg.vector_norm(data, dim=(1, 2))


def learn_kernel(sheet, forces, u_data, delta: float, start=None, positive_kernel: bool = False,
                 zeta: float = ZETA, maxiter: int = 200, ftol: float = 1e-10) -> KernelFit:
    """Fit (lambda, mu, D) at horizon ``delta`` to displacements ``u_data`` (loads, N, 2) under
    nodal ``forces``, with the solvability penalty, from D = const and ``start`` = (lambda, mu)
    (default: both |f| / (V k_min^2 |u|), the order of a long-wave modulus of the data)."""
    influence = sheet.material.influence
    P = influence.degree
    positive("delta", delta, "pass the horizon")
    forces, u_data = torch.as_tensor(forces), torch.as_tensor(u_data)
    if start is None:
        scale = float(forces.norm() / u_data.norm()) / float(sheet.material.particles.volume[0]) * (2 * np.pi / sheet.box.min()) ** -2
        start = (0.5 * scale, 0.5 * scale)
    lam0, mu0 = start
    z0 = np.concatenate([[np.log(lam0 + mu0), np.log(mu0)], np.zeros(P + 1) if positive_kernel else np.ones(P + 1)])
    history, t0 = [], time.perf_counter()

    def unpack(z):
        kappa, mu = torch.exp(z[0]), torch.exp(z[1])
        return lps_params(kappa - mu, mu, coefficients(z), delta)

    def coefficients(z):
        return torch.exp(z[2:]) if positive_kernel else z[2:]

    def objective(znp):
        z = torch.tensor(znp, requires_grad=True)
        try:
            p = unpack(z)
            J = (relative_errors(sheet, p, forces, u_data) ** 2).mean() + solvability_penalty(sheet, p, zeta)
            # D's scale is free (LPS absorbs it into m): pin it without touching the shape
            J = J + 1e-3 * (z[2:].mean() if positive_kernel else torch.log((z[2:] ** 2).sum())) ** 2
        except ValueError:  # m <= 0 somewhere: outside the admissible set; the line search steps back
            return 1e6, np.zeros_like(znp)
        J.backward()
        history.append(float(J.detach()))
        return float(J.detach()), z.grad.numpy()

    res = scipy.optimize.minimize(objective, z0, jac=True, method="L-BFGS-B",
                                  options={"maxiter": maxiter, "ftol": ftol, "gtol": 1e-9})
    z = torch.as_tensor(res.x)
    p = unpack(z)
    c = check_solvable(sheet, p, zeta)
    misfit = float((relative_errors(sheet, p, forces, u_data) ** 2).mean())
    kappa, mu = float(torch.exp(z[0])), float(torch.exp(z[1]))
    return KernelFit(kappa - mu, mu, normalised(influence, coefficients(z), delta).numpy(), float(delta), c, misfit,
                     int(res.nit), time.perf_counter() - t0, bool(res.success), str(res.message), history)
