"""Phase 2 of paper 004's learning (eqs 3.10, 3.16, 4.8-4.9): the critical stretch s0 of the
smoothed damage law from a coarse-grained fracture record, the kernel and moduli held at phase 1's.

Bond state (eq 3.16): S_ij^n = |xi_ij + u_j^n - u_i^n| / |xi_ij| - 1 from the data, its running
maximum over frames, and gamma_ij^n = (1 - tanh((max_{m<=n} S_ij^m - s0) / eta)) / 2
(``bayespd.damage.SmoothStep``). Equation residual (eq 4.9) at the interior frames n:

    r_i^n = rho_i (u_i^{n+1} - 2 u_i^n + u_i^{n-1}) / dt^2 + (K(gamma^n) u^n)_i / V_i - b_i^n,

with K(gamma) the project's damaged linearised LPS (``Material.terms(params, intact=gamma)``:
bond weights gamma w, weighted volume m recomputed). That stands in for the paper's free-surface
correction (eqs 3.13-3.15, 3.18-3.21): a broken bond leaves the family and m, as there, but the
dilatation is not corrected by the tensor M. Res(s0) = sum_n dt ||r^n||^2 over ``nodes`` (the
nodes away from the prescribed edges), minimised over log s0 by bounded Brent (the paper uses
bisection on the same one-dimensional problem).

Units: positions and u in A, time in ps, rho in g/mol per A^2 (MASS converts to eV ps^2 / A^4),
b in eV/A per A^2, moduli in eV/A^2.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import scipy.optimize
import scipy.sparse
import torch

from bayespd.damage import SmoothStep
from bayespd.validate import positive

MASS = 1.0 / 9648.533212  # eV ps^2 / A^2 per g/mol (1 g/mol = 1.0364e-4 eV ps^2 / A^2)
ETA = 0.05                # the smoothing width of eq 3.10 used in paper 004 sec. 4


def max_stretch(material, u) -> torch.Tensor:
    """Running maximum over frames of the bond stretch (eq 3.16) (F, bonds) for u (F, N, 2)."""
    u = torch.as_tensor(u)
    xi = torch.as_tensor(material.bonds.xi)
    y = xi + u[:, material.j] - u[:, material.i]
    s = torch.linalg.vector_norm(y, dim=-1) / material.length - 1
    return torch.cummax(torch.clamp(s, min=0.0), dim=0).values  # the reference state counts as 0


@dataclass
class FractureData:
    """A coarse-grained dynamic record on the material's nodes: density ``rho`` (F, N), displacement
    ``u`` and force density ``b`` (F, N, 2), frame interval ``dt`` (ps) and the nodes where the
    residual is evaluated (``nodes``, bool (N,))."""
    rho: np.ndarray
    u: np.ndarray
    b: np.ndarray
    dt: float
    nodes: np.ndarray

    def __post_init__(self):
        positive("dt", self.dt, "pass the frame interval in ps")
        if self.u.ndim != 3 or self.u.shape[0] < 3 or self.b.shape != self.u.shape or self.rho.shape != self.u.shape[:2]:
            raise ValueError("rho (F, N), u and b (F, N, 2) with at least 3 frames are needed for eq 4.9's "
                             f"central difference; got {self.rho.shape}, {self.u.shape}, {self.b.shape}")


class DamageResidual:
    """Res(s0) of eq 4.9 for one record and fixed phase-1 ``params`` (module docstring)."""

    def __init__(self, material, params: dict, data: FractureData, eta: float = ETA):
        self.material, self.params, self.data, self.eta = material, params, data, eta
        self.stretch = max_stretch(material, data.u).numpy()
        u = data.u
        self.inertia = MASS * data.rho[1:-1, :, None] * (u[2:] - 2 * u[1:-1] + u[:-2]) / data.dt**2
        self.volume = material.particles.volume
        pat = material.pattern
        self._csc = (pat.rows, pat.cols, pat.n)

    def _internal(self, gamma: np.ndarray, u: np.ndarray) -> np.ndarray:
        rows, cols, n = self._csc
        values = self.material.numeric_stiffness(self.params, gamma).numpy()
        K = scipy.sparse.csc_matrix((values, (rows, cols)), shape=(n, n))
        return (K @ u.reshape(-1)).reshape(-1, 2) / self.volume[:, None]

    def residuals(self, s0: float) -> np.ndarray:
        """r^n (F - 2, N, 2) at the interior frames."""
        law = SmoothStep(s0, self.eta)
        d = self.data
        out = np.empty_like(self.inertia)
        for n in range(1, len(d.u) - 1):
            gamma = law.intact(torch.as_tensor(self.stretch[n])).numpy()
            out[n - 1] = self.inertia[n - 1] + self._internal(gamma, d.u[n]) - d.b[n]
        return out

    def __call__(self, s0: float) -> float:
        r = self.residuals(s0)[:, self.data.nodes]
        return float(self.data.dt * (r**2).sum())


@dataclass
class CriterionFit:
    s0: float
    residual: float
    residual_intact: float
    evaluations: int
    wall_time_s: float


def learn_s0(residual: DamageResidual, bounds=(1e-3, 1.0), xatol: float = 1e-3) -> CriterionFit:
    """s0* = argmin Res(s0) (eq 4.8) by bounded Brent on log s0 to a relative ``xatol``; also
    reports Res with every bond intact (s0 -> infinity), the no-damage reference."""
    lo, hi = (positive("bounds", b, "pass 0 < low < high") for b in bounds)
    t0 = time.perf_counter()
    res = scipy.optimize.minimize_scalar(lambda z: residual(float(np.exp(z))), bounds=(np.log(lo), np.log(hi)),
                                         method="bounded", options={"xatol": xatol})
    return CriterionFit(float(np.exp(res.x)), float(res.fun), residual(1e6), int(res.nfev), time.perf_counter() - t0)
